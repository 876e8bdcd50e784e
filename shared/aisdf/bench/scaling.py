"""``aisdf bench scaling``: from one room to a floor, one network against submaps (issue 7).

In one run, for every scene (the office, the floor) and every method (``METHODS``: a
factory of a mapping pipeline), the scene is walked at one keyframe per ``period_s``
(1 s) of wall time:

* the keyframes are rendered up front (the floor's whole walk, room by room; the office's
  loop), then keyframe k is added at t = k periods while the mapper steps continuously in
  between, as the mapper service does;
* at the end of every period, the messages the mapper would publish then are encoded
  (``pipe.map_messages(version)``: only what changed) and, for comparison, everything
  (``changed_only=False``); their bytes are counted;
* after the walk (t = n periods), training goes on for ``tail_s`` more (60 s).

Evaluations pause the clock (as does encoding the messages, which the service does on
another thread): the whole map's mean SDF error at the end of the walk and ``tail_s``
later, on points along the rays of every keyframe (``metrics.eval_points``: one point per
ray, depth uniform in [0.1, D + 0.1], as the demo and ``aisdf bench`` draw them; here every
keyframe is used since they are 1 s apart) against the exact SDF; and for the floor each
room's error ``after_visit_s`` after the camera leaves it (points of the visit's keyframes
inside that room's region), then again at the end of the walk and at the end (the same
points; the ratio end / after-visit says whether it was forgotten).

Measured: per-step wall time (mean, p95), mapper memory (``pipe.memory()``: bytes held by
keyframes, models with their optimiser state, observed space; per keyframe), bytes
published per second while walking (changed only, and republishing everything), the
errors above, the share of the whole map's points where the answer is more than 5 cm above
the exact SDF (``TOO_HIGH_M``: the side on which a planner would cut a corner; a mean error
hides it), where the error is (the share of points whose nearest surface no keyframe
measured, ``UNMEASURED_M``, their part of the mean error and the error on the others), and
the issue's criteria evaluated per method. ``run`` writes
``scaling.json`` and ``scaling.md`` under ``out``; ``--seeds N`` walks every scene N times
(seeds seed .. seed + N - 1) and judges the mean (``scaling_seeds.py``); ``--quick`` is a
tiny walk (a dozen keyframes a quarter second apart, spread over the whole floor) for CI.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from ..config import Model, deep_merge
from .scaling_walk import TOO_HIGH_M, scene_frames, walk, whole_scorer

log = logging.getLogger("aisdf.bench.scaling")


# ------------------------------------------------------------------ methods (factories)


def _single(preset: str, training: dict):
    from ..pipeline import MappingPipeline

    return MappingPipeline.from_settings(preset, training=training, atlanta=True)


def _submaps(preset: str, training: dict):
    try:
        from ..submaps import SubmapPipeline
    except ImportError:
        from ..submaps.pipeline import SubmapPipeline
    return SubmapPipeline.from_settings(preset, training=training, atlanta=True)


# name -> (label, factory(preset, training overrides) -> a pipeline with add_keyframe, step,
# sdf, map_messages, memory, n_keyframes, steps). Add a method by adding an entry.
METHODS: dict[str, tuple[str, Callable[[str, dict], Any]]] = {
    "single": ("single network", _single),
    "submaps": ("submaps", _submaps),
}


# ------------------------------------------------------------------ configuration


class ScalingConfig(Model):
    scenes: list[str] = Field(default_factory=lambda: ["office", "floor"], description="synthetic buildings")
    methods: list[str] = Field(default_factory=lambda: ["single", "submaps"], description="METHODS keys")
    keyframes: int = Field(200, ge=2, description="keyframes per walk")
    period_s: float = Field(1.0, gt=0, description="wall seconds between keyframes (and per publication)")
    tail_s: float = Field(60.0, ge=0, description="training after the walk (wall seconds)")
    after_visit_s: float = Field(5.0, ge=0, description="a room is scored this long after the camera leaves it")
    preset: str = Field("cpu", description="training preset")
    training: dict[str, Any] = Field(default_factory=dict, description="TrainingConfig overrides")
    H: int = Field(120, ge=8)
    W: int = Field(160, ge=8)
    noise: bool = Field(True, description="Kinect-like depth noise")
    n_points: int = Field(200_000, ge=100, description="whole-map evaluation points")
    n_room_points: int = Field(20_000, ge=50, description="evaluation points per room")
    seed: int = Field(0, description="building, walk, noise and training seed")
    seeds: int = Field(1, ge=1, description="walks per method and scene, seeds seed, seed + 1, ...; the table and "
                       "the criteria take their mean (scaling_seeds.py)")
    threads: int | None = Field(None, ge=1, description="torch threads (None: torch's default)")
    out: str = Field("runs/bench-scaling", description="results folder")
    progress: bool = Field(True, description="print a line per event")
    source: Literal["served", "fused", "implicit", "measured"] = Field(
        "served", description="the answer scored (and judged by the criteria): served = query/sdf's default for "
        "the mapper (fused with its published measured points: protocol 1.4 with submaps, 1.5 with one network; "
        "fused for a mapper that sends none), fused = the network and surfel map (1.3's answer), implicit = the network alone, "
        "measured = fused with the measured surface; all are in the table")


PROFILES: dict[str, dict[str, Any]] = {
    "full": {},
    "quick": {"keyframes": 12, "period_s": 0.25, "tail_s": 2.0, "after_visit_s": 0.0, "H": 48, "W": 64,
              "n_points": 3000, "n_room_points": 300,
              "training": {"network": {"width": 64}, "n_rays": 40, "window_size": 3}},
}


def resolve(profile: str = "full", **overrides: Any) -> ScalingConfig:
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
    return ScalingConfig.model_validate(deep_merge(PROFILES[profile], {k: v for k, v in overrides.items()
                                                                        if v is not None}))


# ------------------------------------------------------------------ criteria and report


def criteria(res: dict) -> dict[str, dict]:
    """The issue's 'done when' figures, per method: {method: {criterion: {value, limit, ok}}}."""
    out: dict[str, dict] = {}
    tail = f"{res['config']['tail_s']:g} s"
    for m, by_scene in res["runs"].items():
        fl, of = by_scene.get("floor"), by_scene.get("office")
        c: dict[str, dict] = {}
        if fl:
            c[f"floor error {tail} after the walk <= 5 cm"] = _crit(fl["error_end_cm"], 5.0)
            if fl["rooms"]:
                worst = max((r["ratio_end"] or 0.0) for r in fl["rooms"].values())
                c[f"every room: error {tail} after the walk / just after its visit <= 1.2"] = _crit(worst, 1.2)
            if fl.get("bytes_ratio") is not None:
                c["bytes/s walking the floor <= 1/3 of republishing everything"] = _crit(fl["bytes_ratio"], 1 / 3)
        if fl and of:
            c[f"floor error <= 1.5x the office's ({tail} after)"] = _crit(_ratio(fl["error_end_cm"], of["error_end_cm"]), 1.5)
            c["step time floor <= 1.2x office (mean)"] = _crit(_ratio(fl["step_ms"]["mean"], of["step_ms"]["mean"]), 1.2)
            c["memory per keyframe, floor / office (no limit)"] = {
                "value": round(fl["memory_per_keyframe"] / of["memory_per_keyframe"], 3), "limit": None, "ok": None}
        out[m] = c
    return out


def _crit(value: float | None, limit: float) -> dict:
    if value is None or not np.isfinite(value):
        return {"value": None, "limit": round(limit, 4), "ok": None}
    return {"value": round(float(value), 4), "limit": round(limit, 4), "ok": bool(value <= limit)}


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def _mb(b: int) -> str:
    return f"{b / 1e6:.1f}"


def report(res: dict) -> str:
    cfg = res["config"]
    seeds = res.get("seeds")
    lines = [f"Scaling: {', '.join(res['scenes'])}; {cfg['keyframes']} keyframes, one per {cfg['period_s']:g} s of "
             f"wall time, then {cfg['tail_s']:g} s more training; preset {cfg['preset']}; {res['machine']}. "
             f"Errors are those of the {cfg.get('source', 'implicit')} answer unless said otherwise."
             + (f" Every figure is the mean over seeds {', '.join(map(str, seeds))}." if seeds else ""), ""]
    avail = [m for m in res["methods"] if m in res["runs"]]
    src = cfg.get("source", "implicit")
    others = [k for k in ("served", "fused", "implicit") if k != src]
    head = "| | " + " | ".join(f"{s}: {METHODS[m][0]}" for s in res["scenes"] for m in avail) + " |"
    lines += [head, "|---|" + "---:|" * (len(res["scenes"]) * len(avail))]
    rows = [
        ("keyframes", lambda r: f"{r['keyframes']:,.0f}"),  # means over seeds are not whole: rounded
        ("training steps (walk / +tail)",
         lambda r: f"{r['steps_walk_end']:,.0f} / {r['steps_end'] - r['steps_walk_end']:,.0f}"),
        ("keyframes added late, mean / max (s)", lambda r: f"{r['keyframe_late_s']['mean']:.2f} / "
         f"{r['keyframe_late_s']['max']:.2f}"),
        ("step time mean / p95 (ms)", lambda r: f"{r['step_ms']['mean']:.1f} / {r['step_ms']['p95']:.1f}"
         if r["step_ms"]["n"] else "no step"),
        ("mapper memory (MB)", lambda r: _mb(r["memory_bytes"])),
        ("  keyframes / model+optimiser / observed / measured points (MB)",
         lambda r: " / ".join(_mb(r["memory_end"].get(k, 0)) for k in ("keyframes", "model", "observed", "measured"))),
        ("bytes per keyframe (kB)", lambda r: f"{r['memory_per_keyframe'] / 1e3:.1f}"),
        ("published while walking (kB/s)", lambda r: f"{r['bytes_per_s'] / 1e3:.1f}"),
        ("republishing everything (kB/s)", lambda r: f"{r['bytes_per_s_all'] / 1e3:.1f}"),
        (f"SDF error ({src}), end of the walk (cm)", lambda r: f"{r['error_walk_end_cm']:.2f}"),
        (f"SDF error ({src}), +{cfg['tail_s']:g} s (cm)", lambda r: f"{r['error_end_cm']:.2f}"),
        *[(f"  {o} answer: end of the walk / +{cfg['tail_s']:g} s (cm)",
           lambda r, o=o: f"{r['error_walk_end_by_source_cm'][o]:.2f} / {r['error_end_by_source_cm'][o]:.2f}"
           if o in r.get("error_end_by_source_cm", {}) else "-") for o in others],
        (f"answers > {100 * TOO_HIGH_M:g} cm above the truth ({src}), end of the walk / +{cfg['tail_s']:g} s "
         "(% of points)", lambda r: f"{r['too_high_walk_end_pct']:.1f} / {r['too_high_end_pct']:.1f}"
         if "too_high_end_pct" in r else "-"),
        (f"  ... of the fused answer (1.3, no measured points), end of the walk / +{cfg['tail_s']:g} s (%)",
         lambda r: f"{r['too_high_walk_end_by_source_pct']['fused']:.1f} / {r['too_high_end_by_source_pct']['fused']:.1f}"
         if "too_high_end_by_source_pct" in r else "-"),
        (f"fused with the measured surface (served since 1.4 with submaps, 1.5 with one network): error, end of the walk / "
         f"+{cfg['tail_s']:g} s (cm)",
         lambda r: f"{r['error_walk_end_by_source_cm']['measured']:.2f} / {r['error_end_by_source_cm']['measured']:.2f}"
         if "measured" in r.get("error_end_by_source_cm", {}) else "-"),
        (f"  ... answers > {100 * TOO_HIGH_M:g} cm above the truth, end of the walk / +{cfg['tail_s']:g} s (%)",
         lambda r: f"{r['too_high_walk_end_by_source_pct']['measured']:.1f} / "
         f"{r['too_high_end_by_source_pct']['measured']:.1f}"
         if "measured" in r.get("too_high_end_by_source_pct", {}) else "-"),
        (f"unknown space as occupied (1.6: the smaller of the served answer and the distance to unobserved space): "
         f"error, end of the walk / +{cfg['tail_s']:g} s (cm); answers > {100 * TOO_HIGH_M:g} cm above the truth, the same (%)",
         lambda r: f"{r['error_walk_end_by_source_cm']['unknown_occupied']:.2f} / "
         f"{r['error_end_by_source_cm']['unknown_occupied']:.2f}; {r['too_high_walk_end_by_source_pct']['unknown_occupied']:.1f}"
         f" / {r['too_high_end_by_source_pct']['unknown_occupied']:.1f}"
         if "unknown_occupied" in r.get("error_end_by_source_cm", {}) else "-"),
        (f"points whose nearest surface no keyframe measured ({src}), +{cfg['tail_s']:g} s: % of points, their "
         "part of the error / the error on the others (cm)",
         lambda r: f"{r['unmeasured_end']['points_pct']:.1f} %: {r['unmeasured_end']['error_cm']:.2f} / "
         f"{r['unmeasured_end']['rest_error_cm']:.2f}" if r.get("unmeasured_end") else "-"),
    ]
    for label, fn in rows:
        cells = []
        for s in res["scenes"]:
            for m in avail:
                r = res["runs"][m].get(s)
                cells.append(fn(r) if r else "-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    rooms = sorted({r for m in avail for r in (res["runs"][m].get("floor") or {}).get("rooms", {})})
    if rooms:
        lines += ["", f"Floor rooms: SDF error (cm) just after the visit ({cfg['after_visit_s']:g} s after leaving) / "
                      f"at the end of the walk / +{cfg['tail_s']:g} s (ratio +{cfg['tail_s']:g} s / after the visit)", ""]
        lines += ["| room | " + " | ".join(METHODS[m][0] for m in avail) + " |", "|---|" + "---|" * len(avail)]
        for room in rooms:
            cells = []
            for m in avail:
                r = res["runs"][m]["floor"]["rooms"].get(room)
                cells.append(f"{r['after_visit_cm']:.2f} / {r['walk_end_cm']:.2f} / {r['end_cm']:.2f} "
                             f"({r['ratio_end']:.2f})" if r else "-")
            lines.append(f"| {room} | " + " | ".join(cells) + " |")
    lines += ["", "Criteria (issue 7):", ""]
    lines += ["| criterion | " + " | ".join(METHODS[m][0] for m in avail) + " |", "|---|" + "---|" * len(avail)]
    names = list(dict.fromkeys(c for m in avail for c in res["criteria"].get(m, {})))
    for c in names:
        cells = []
        for m in avail:
            v = res["criteria"][m].get(c)
            cells.append("-" if v is None or v["value"] is None else f"{v['value']:.4g}" + ("" if v["ok"] is None else
                                                                        (" ✓" if v["ok"] else " ✗")))
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    if seeds:
        from .scaling_seeds import seeds_report

        lines += seeds_report(res, {m: METHODS[m][0] for m in METHODS})
    for m, why in res.get("unavailable", {}).items():
        lines.append(f"\n{m}: not run ({why})")
    return "\n".join(lines)


# ------------------------------------------------------------------ entry point


def _machine(threads: int | None) -> str:
    import torch

    return (f"{platform.machine()}, {os.cpu_count()} CPU cores, torch threads {threads or torch.get_num_threads()} "
            "(as the preset set them)")


def run(cfg: ScalingConfig) -> dict:
    if cfg.seeds > 1:
        from .scaling_seeds import run_seeds

        return run_seeds(cfg)
    import torch

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    unknown = [m for m in cfg.methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    say = (lambda s: print(s, flush=True)) if cfg.progress else (lambda s: None)
    training = deep_merge(cfg.training, {"seed": cfg.seed})
    res: dict[str, Any] = {"config": cfg.model_dump(mode="json"), "scenes": list(cfg.scenes),
                           "methods": list(cfg.methods), "machine": _machine(cfg.threads), "runs": {},
                           "unavailable": {}, "scene_info": {}}
    t_start = time.time()
    for name in cfg.scenes:
        t = time.perf_counter()
        seq, frames, per_kf = scene_frames(name, cfg)
        whole = whole_scorer(seq, frames, cfg)
        lo, hi = seq.scene.room.polygon.min(axis=0), seq.scene.room.polygon.max(axis=0)
        res["scene_info"][name] = {"footprint_m": np.round(hi - lo, 2).tolist(), "keyframes": len(frames),
                                   "stream_s_per_keyframe": round(per_kf, 4), "eval_points": len(whole.points),
                                   "visits": {r: [round(a, 2), round(b, 2)] for r, (a, b) in seq.visits.items()},
                                   "prepare_s": round(time.perf_counter() - t, 1)}
        for m in cfg.methods:
            if m in res["unavailable"]:
                continue
            try:
                pipe = METHODS[m][1](cfg.preset, training)
            except ImportError as e:
                res["unavailable"][m] = f"{type(e).__name__}: {e}"
                log.warning("method %s not available: %s", m, e)
                continue
            say(f"{name} / {METHODS[m][0]}: {len(frames)} keyframes, one per {cfg.period_s:g} s, then "
                f"{cfg.tail_s:g} s")
            res["runs"].setdefault(m, {})[name] = walk(pipe, seq, frames, per_kf, cfg, whole, say)
            del pipe
    res["machine"] = _machine(cfg.threads)  # after the pipelines: the preset sets torch's threads
    res["criteria"] = criteria(res)
    res["wall_s"] = round(time.time() - t_start, 1)
    (out / "scaling.json").write_text(json.dumps(res, indent=1))
    md = report(res)
    (out / "scaling.md").write_text(md + "\n")
    return res


def add_arguments(p) -> None:
    p.add_argument("--quick", action="store_true", help="a tiny walk (a dozen keyframes, seconds) for CI")
    p.add_argument("--scenes", nargs="+", help="synthetic buildings (default office floor)")
    p.add_argument("--methods", nargs="+", choices=list(METHODS), help="default: all")
    p.add_argument("--keyframes", type=int, help="keyframes per walk (default 200)")
    p.add_argument("--period-s", type=float, help="wall seconds between keyframes (default 1)")
    p.add_argument("--tail-s", type=float, help="training after the walk (default 60 s)")
    p.add_argument("--after-visit-s", type=float, help="score a room this long after leaving it (default 5 s)")
    p.add_argument("--preset", choices=["cpu", "paper", "auto"], help="training preset (default cpu)")
    p.add_argument("--n-points", type=int, help="whole-map evaluation points (default 200000)")
    p.add_argument("--seed", type=int)
    p.add_argument("--seeds", type=int, help="walks per method and scene (seeds seed, seed + 1, ...); the table and "
                   "the criteria take their mean, and each seed's figures follow (default 1)")
    p.add_argument("--source", choices=["served", "fused", "implicit", "measured"], help="the answer judged "
                   "(default served: query/sdf's default for the mapper; the table shows the others)")
    p.add_argument("--threads", type=int, help="torch threads")
    p.add_argument("--out", help="results folder (default runs/bench-scaling)")
    p.add_argument("--training", type=_json_map, help="training overrides over the preset (for submaps, over its "
                   "SUBMAP_PRESETS entry too), JSON, e.g. '{\"network\": {\"width\": 128}, \"lr_settle\": null}'")


def _json_map(text: str) -> dict:
    import argparse

    try:
        v = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"not JSON: {e}") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError("expected a JSON object")
    return v


def config_from_args(args) -> ScalingConfig:
    g = lambda k: getattr(args, k, None)  # noqa: E731
    return resolve("quick" if g("quick") else "full", **{k: g(k) for k in (
        "scenes", "methods", "keyframes", "period_s", "tail_s", "after_visit_s", "preset", "n_points", "seed",
        "seeds", "source", "threads", "out", "training")})


def main(args) -> None:
    res = run(config_from_args(args))
    print(report(res))
    print(f"results in {Path(res['config']['out']) / 'scaling.json'} ({res['wall_s']:.0f} s)")
