"""The report of ``aisdf bench scaling``: the criteria each mapper is judged by, and the
tables as markdown (the mean over seeds, and each seed's figures, when there are several)."""

from __future__ import annotations

import numpy as np

from .scaling_config import LABELS
from .evaluation import NEAR_FURNITURE_M
from .scaling_walk import TOO_HIGH_M


def criteria(res: dict) -> dict[str, dict]:
    """The scaling criteria, per mapper: {mapper: {criterion: {value, limit, ok}}}."""
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


def _f2(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _near_cells(r: dict) -> str:
    """The near-furniture split of one run: share; near, walk end / end; away, the same ("-": no labels)."""
    w, e = r.get("near_furniture_walk_end"), r.get("near_furniture_end")
    if not w or not e:
        return "-"
    return (f"{e['points_pct']:.1f} %; {_f2(w['error_cm'])} / {_f2(e['error_cm'])}; "
            f"{_f2(w['away_error_cm'])} / {_f2(e['away_error_cm'])}")


def _mb(b: int) -> str:
    return f"{b / 1e6:.1f}"


def report(res: dict) -> str:
    cfg = res["config"]
    seeds = res.get("seeds")
    lines = [f"Scaling: {', '.join(res['scenes'])}; {cfg['keyframes']} keyframes, one per {cfg['period_s']:g} s of "
             f"wall time, then {cfg['tail_s']:g} s more training; preset {cfg['preset']}; {res['machine']}. "
             f"Errors are those of the {cfg.get('source', 'implicit')} answer unless said otherwise."
             + (f" Every figure is the mean over seeds {', '.join(map(str, seeds))}." if seeds else ""), ""]
    avail = [m for m in res["mappers"] if m in res["runs"]]
    src = cfg.get("source", "implicit")
    others = [k for k in ("served", "fused", "implicit") if k != src]
    head = "| | " + " | ".join(f"{s}: {LABELS[m]}" for s in res["scenes"] for m in avail) + " |"
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
        (f"points near furniture (its nearest surface furniture, or within {100 * NEAR_FURNITURE_M:g} cm of it) "
         f"({src}): % of points; error there, end of the walk / +{cfg['tail_s']:g} s; away from furniture, the same (cm)",
         _near_cells),
        (f"  ... near furniture with an unmeasured nearest surface, +{cfg['tail_s']:g} s: % of points; error there (cm)",
         lambda r: f"{r['near_furniture_end']['unmeasured_pct']:.1f} %; {_f2(r['near_furniture_end']['unmeasured_error_cm'])}"
         if "unmeasured_pct" in (r.get("near_furniture_end") or {}) else "-"),
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
        lines += ["| room | " + " | ".join(LABELS[m] for m in avail) + " |", "|---|" + "---|" * len(avail)]
        for room in rooms:
            cells = []
            for m in avail:
                r = res["runs"][m]["floor"]["rooms"].get(room)
                cells.append(f"{r['after_visit_cm']:.2f} / {r['walk_end_cm']:.2f} / {r['end_cm']:.2f} "
                             f"({r['ratio_end']:.2f})" if r else "-")
            lines.append(f"| {room} | " + " | ".join(cells) + " |")
    lines += ["", "Criteria:", ""]
    lines += ["| criterion | " + " | ".join(LABELS[m] for m in avail) + " |", "|---|" + "---|" * len(avail)]
    names = list(dict.fromkeys(c for m in avail for c in res["criteria"].get(m, {})))
    for c in names:
        cells = []
        for m in avail:
            v = res["criteria"][m].get(c)
            cells.append("-" if v is None or v["value"] is None else f"{v['value']:.4g}" + ("" if v["ok"] is None else
                                                                        (" ✓" if v["ok"] else " ✗")))
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    if seeds:
        lines += seeds_report(res, LABELS)
    for m, why in res.get("unavailable", {}).items():
        lines.append(f"\n{m}: not run ({why})")
    return "\n".join(lines)


def seeds_report(res: dict, labels: dict[str, str]) -> list[str]:
    """Lines for the report: each seed's errors and how many seeds pass each criterion."""
    seeds = [p["seed"] for p in res["per_seed"]]
    tail = f"+{res['config']['tail_s']:g} s"
    lines = ["", f"Each seed (the tables above are the means over seeds {', '.join(map(str, seeds))}; "
                 f"errors at the end of the walk / {tail}, cm):", "",
             "| | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|" + "---:|" * len(seeds)]
    for m, by in res["runs"].items():
        for sc in by:
            cells = []
            for p in res["per_seed"]:
                e = p["errors_cm"].get(m, {}).get(sc)
                cells.append(f"{e['walk_end']:.2f} / {e['end']:.2f}" if e else "-")
            lines.append(f"| {sc}: {labels[m]} | " + " | ".join(cells) + " |")
    lines += ["", "| criterion, seeds passing | " + " | ".join(labels[m] for m in res["criteria"]) + " |",
              "|---|" + "---|" * len(res["criteria"])]
    names = list(dict.fromkeys(c for m in res["criteria"] for c in res["criteria"][m]))
    for c in names:
        cells = []
        for m in res["criteria"]:
            oks = [p["criteria"].get(m, {}).get(c, {}).get("ok") for p in res["per_seed"]]
            judged = [o for o in oks if o is not None]
            cells.append(f"{sum(judged)} of {len(judged)}" if judged else "-")
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return lines
