"""``aisdf bench scaling``: from one room to a floor, one network against submaps.

In one run, for every scene (the office, the floor) and every mapper (``mappers``: kinds of
``aisdf.mapper``, made by ``aisdf.mapper.factory.make_mapper``), the scene is walked at one keyframe per ``period_s``
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
measured, ``UNMEASURED_M``, their part of the mean error and the error on the others), the
error near furniture and away from it (``evaluation.near_furniture_mask``: the points whose
nearest surface is furniture or within 30 cm of it; the buildings' labels), and
the criteria evaluated per mapper (``scaling_report.py``). ``run`` writes
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
from pathlib import Path
from typing import Any

import numpy as np

from ..config import deep_merge
from .scaling_config import LABELS, PROFILES, ScalingConfig, make, resolve
from .scaling_report import criteria, report
from .scaling_seeds import run_seeds
from .scaling_walk import scene_frames, walk, whole_scorer

log = logging.getLogger("aisdf.bench.scaling")

__all__ = ["LABELS", "PROFILES", "ScalingConfig", "criteria", "make", "report", "resolve", "run"]


def _machine(threads: int | None) -> str:
    import torch

    return (f"{platform.machine()}, {os.cpu_count()} CPU cores, torch threads {threads or torch.get_num_threads()} "
            "(as the preset set them)")


def run(cfg: ScalingConfig) -> dict:
    if cfg.seeds > 1:
        return run_seeds(cfg, run)
    import torch

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    unknown = [m for m in cfg.mappers if m not in LABELS]
    if unknown:
        raise SystemExit(f"unknown mapper(s) {unknown}; known: {', '.join(LABELS)}")
    say = (lambda s: print(s, flush=True)) if cfg.progress else (lambda s: None)
    training = deep_merge(cfg.training, {"seed": cfg.seed})
    res: dict[str, Any] = {"config": cfg.model_dump(mode="json"), "scenes": list(cfg.scenes),
                           "mappers": list(cfg.mappers), "machine": _machine(cfg.threads), "runs": {},
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
        for m in cfg.mappers:
            if m in res["unavailable"]:
                continue
            try:
                pipe = make(m, cfg.preset, training)
            except ImportError as e:
                res["unavailable"][m] = f"{type(e).__name__}: {e}"
                log.warning("mapper %s not available: %s", m, e)
                continue
            say(f"{name} / {LABELS[m]}: {len(frames)} keyframes, one per {cfg.period_s:g} s, then "
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
    p.add_argument("--mapper", dest="mappers", nargs="+", choices=list(LABELS), help="mapper kinds walked (default: "
                   "all)")
    p.add_argument("--keyframes", type=int, help="keyframes per walk (default 200)")
    p.add_argument("--period-s", type=float, help="wall seconds between keyframes (default 1)")
    p.add_argument("--tail-s", type=float, help="training after the walk (default 60 s)")
    p.add_argument("--after-visit-s", type=float, help="score a room this long after leaving it (default 5 s)")
    p.add_argument("--preset", choices=["cpu", "paper", "auto"], help="training preset (default cpu)")
    p.add_argument("--n-points", type=int, help="whole-map evaluation points (default 200000)")
    p.add_argument("--seed", type=int)
    p.add_argument("--seeds", type=int, help="walks per mapper and scene (seeds seed, seed + 1, ...); the table and "
                   "the criteria take their mean, and each seed's figures follow (default 1)")
    p.add_argument("--source", choices=["served", "fused", "implicit", "measured"], help="the answer judged "
                   "(default served: query/sdf's default for the mapper; the table shows the others)")
    p.add_argument("--threads", type=int, help="torch threads")
    p.add_argument("--out", help="results folder (default runs/bench-scaling)")
    p.add_argument("--served", action="store_true", help="then walk each scene through the real query service and "
                   "mapper over Zenoh (aisdf bench served): what planners get, beside the newest map's exact answer")
    p.add_argument("--served-only", action="store_true", help="only the walk through the real services")
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
        "scenes", "mappers", "keyframes", "period_s", "tail_s", "after_visit_s", "preset", "n_points", "seed",
        "seeds", "source", "threads", "out", "training")})


def main(args) -> None:
    cfg = config_from_args(args)
    if not getattr(args, "served_only", False):
        res = run(cfg)
        print(report(res))
        print(f"results in {Path(res['config']['out']) / 'scaling.json'} ({res['wall_s']:.0f} s)")
    if getattr(args, "served", False) or getattr(args, "served_only", False):
        from .served import main as served_main

        served_main(["--scenes", *cfg.scenes, "--keyframes", str(cfg.keyframes), "--period-s", str(cfg.period_s),
                     "--tail-s", str(cfg.tail_s), "--preset", cfg.preset, "--seed", str(cfg.seed),
                     "--width", str(cfg.W), "--height", str(cfg.H), "--out", str(Path(cfg.out) / "served")])
