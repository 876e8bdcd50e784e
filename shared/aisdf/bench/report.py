"""Tables I-III as markdown and JSON, from the suite's results.

``results`` (what ``suite.run`` returns and writes as results.json)::

    {"mode": ..., "n_points": ..., "scenes": {scene: {
        "ground_truth": label, "gt_kind": "exact" | "mesh" | "reference",
        "runs": [  # one per seed
            {"seed": s, "final": {method: metrics (with the observed / unobserved split)},
             "ablation": {model: metrics},  # final metrics: also near furniture (synthetic)
             "over_time": [{"frame": i, "t": s, "methods": {method: metrics}}],
             "models": {model: summary (frames seen, keyframes, steps, compute, timings_ms)}}]}}}
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .evaluation import NEAR_FURNITURE_M
from .methods import ABLATION, LABELS, MODELS

METRICS = ("sdf_error_cm", "collision_cost_error", "gradient_cosine_distance")
SPLIT = ("observed_share", "sdf_error_observed_cm", "unobserved_share", "sdf_error_unobserved_cm")
FURNITURE = ("near_furniture_share", "sdf_error_near_furniture_cm", "sdf_error_away_from_furniture_cm",
             "near_furniture_unobserved_share", "sdf_error_near_furniture_unobserved_cm")
NO_LABELS = ("no labels: the Replica mesh and the 7-Scenes reference do not say which surface is furniture, so "
             "they have no near-furniture split")
SHORT = {"sdf_error_cm": "SDF (cm)", "collision_cost_error": "Collision", "gradient_cosine_distance": "Gradient"}
DIGITS = {"sdf_error_cm": 3, "collision_cost_error": 4, "gradient_cosine_distance": 3}
MODULES = {  # Table III columns: pipeline timing key -> label, in the paper's order
    "atlanta": "AF estimation", "surfels": "Extract surfels", "sampling": "Sampling", "bound": "Compute bound",
    "forward": "Forward", "backward": "Backward",
}
PAPER_TABLE3 = {"atlanta": 2, "surfels": 54, "sampling": 5, "bound": 7, "forward": 6, "backward": 14, "sum": 88}


def _agg(values: list[dict]) -> dict:
    """Mean and sample standard deviation (n - 1) over seeds of each metric and of the
    observed / unobserved and near-furniture splits (NaN-aware; a split no run has is left out)."""
    out = {}
    for m in METRICS + SPLIT + FURNITURE:
        v = np.array([d.get(m, np.nan) for d in values], dtype=np.float64)
        ok = v[np.isfinite(v)]
        if m not in METRICS and not len(ok):
            continue
        out[m] = float(ok.mean()) if len(ok) else float("nan")
        out[f"{m}_std"] = float(ok.std(ddof=1)) if len(ok) > 1 else 0.0
    out["seeds"] = len(values)
    out["n_points"] = int(np.mean([d.get("n_points", 0) for d in values])) if values else 0
    return out


def _fmt(v, m: str) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.{DIGITS[m]}f}"


def _cell(a: dict, m: str, digits: int | None = None, scale: float = 1.0) -> str:
    """The mean, and ``± std`` over seeds when there are several."""
    v = a.get(m, float("nan")) * scale
    if not math.isfinite(v):
        return "n/a"
    d = DIGITS.get(m, 2) if digits is None else digits
    return f"{v:.{d}f} ± {a[m + '_std'] * scale:.{d}f}" if a.get("seeds", 1) > 1 else f"{v:.{d}f}"


def _gt_short(s: dict) -> str:
    return {"exact": "exact", "mesh": "mesh", "reference": "**reference, not truth**"}.get(s["gt_kind"], s["gt_kind"])


def _header(results: dict) -> list[str]:
    return [f"Mode: **{results['mode']}** ({results['mode_note']}). Profile: {results['profile']}. "
            f"Points: up to {results['n_points']:,} along rays of every 5th frame seen (iSDF's protocol); "
            f"seeds: {_seeds(results['seeds'])}. Lower is better; best per scene and metric in **bold**"
            + (" (by the mean); mean ± standard deviation over the seeds." if _nseeds(results['seeds']) > 1 else "."),
            ""]


def _nseeds(seeds) -> int:
    return len(seeds) if isinstance(seeds, list) else int(seeds)


def _seeds(seeds) -> str:
    if not isinstance(seeds, list):
        return str(seeds)
    return f"{len(seeds)} ({', '.join(str(s) for s in seeds)})"


def table1(results: dict) -> tuple[str, dict]:
    methods = results["methods"]
    data: dict = {"title": "Table I", "mode": results["mode"], "methods": methods, "scenes": {}}
    lines = ["# Table I: SDF error (cm), collision cost error (epsilon 2 m), gradient cosine distance", ""]
    lines += _header(results)
    head = ["Scene", "Ground truth"] + [f"{LABELS.get(m, m)}: {SHORT[k]}" for m in methods for k in METRICS]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, s in results["scenes"].items():
        agg = {m: _agg([r["final"][m] for r in s["runs"] if m in r["final"]]) for m in methods}
        data["scenes"][scene] = {"ground_truth": s["ground_truth"], "gt_kind": s["gt_kind"], "methods": agg}
        best = {k: sorted(v for v in (agg[m][k] for m in methods) if math.isfinite(v)) for k in METRICS}
        cells = []
        for m in methods:
            for k in METRICS:
                c = _cell(agg[m], k)
                cells.append(f"**{c}**" if best[k] and agg[m][k] == best[k][0] and len(methods) > 1 else c)
        name = f"{scene} ({_gt_short(s)})" if s["gt_kind"] == "reference" else scene
        lines.append("| " + " | ".join([name, _gt_short(s)] + cells) + " |")
    if results.get("unavailable"):
        lines += ["", "Left out: " + "; ".join(f"{m} ({why})" for m, why in results["unavailable"].items())]
    lines += near_furniture_lines(results, data)
    lines += ["", "Ground truth per scene:", ""]
    lines += [f"- {scene}: {s['ground_truth']}" for scene, s in results["scenes"].items()]
    if "aisdf-served" in methods or "aisdf-baked" in methods:
        lines += ["", "AiSDF served: the query service's default answer (`source: \"fused\"`), composed by "
                  "`aisdf.query.answer.served_answer` from the network, the signed distance to the global surfels "
                  "(within 2 m), the mapper's measured points and the layout predicted beyond what was observed "
                  "(`aisdf.structure.layout`; the no-prior column leaves it out), as the service composes an exact "
                  "answer; by "
                  "default the service answers from its bake of that field (trilinear, within 5 mm where "
                  "refined): " + ("the baked column is that reply (a query engine that baked the map)."
                                  if "aisdf-baked" in methods else "not in this table (`--methods aisdf-baked`).")]
    lines += ["", "## Run details (seed 0)", "",
              "| Scene | Model | Frames seen | Keyframes | Steps | Compute (s) | Surfels | Up error (deg) |",
              "|---|---|---|---|---|---|---|---|"]
    for scene, s in results["scenes"].items():
        for model, r in s["runs"][0]["models"].items():
            cells = ["-" if r.get(k) is None else r[k] for k in ("keyframes", "steps", "surfels", "up_error_deg")]
            lines.append(f"| {scene} | {model} | {r['frames_seen']} / {s['frames']} | {cells[0]} | {cells[1]} | "
                         f"{r['compute_s']:.1f} | {cells[2]} | {cells[3]} |")
    return "\n".join(lines) + "\n", data


def table1b(results: dict) -> tuple[str, dict]:
    """Table I's SDF error split by whether each point's nearest true surface was observed
    (``evaluation``'s docstring), with the share of points in each."""
    methods = results["methods"]
    data: dict = {"title": "Table Ib", "methods": methods, "scenes": {}}
    lines = ["# Table Ib: SDF error (cm) where the nearest true surface was observed, and where not", "",
             "A point's nearest true surface point is p - s n (s the true distance, n its unit gradient); observed: "
             "a measured depth point (any pixel of every 5th frame, back-projected) lies within 5 cm of it. "
             "Shares: of the points of Table I." + (" Mean ± standard deviation over the seeds."
                                                   if _nseeds(results["seeds"]) > 1 else ""), "",
             "| Scene | Method | Observed: share (%) | Observed: SDF (cm) | Unobserved: share (%) | "
             "Unobserved: SDF (cm) | All: SDF (cm) |", "|---|---|---|---|---|---|---|"]
    for scene, s in results["scenes"].items():
        data["scenes"][scene] = {}
        for m in methods:
            a = _agg([r["final"][m] for r in s["runs"] if m in r["final"]])
            if "observed_share" not in a:
                continue
            data["scenes"][scene][m] = {k: a[k] for k in a if k.split("_std")[0] in SPLIT + ("sdf_error_cm",)}
            lines.append(f"| {scene} | {LABELS.get(m, m)} | {_cell(a, 'observed_share', 1, 100)} | "
                         f"{_cell(a, 'sdf_error_observed_cm', 2)} | {_cell(a, 'unobserved_share', 1, 100)} | "
                         f"{_cell(a, 'sdf_error_unobserved_cm', 2)} | {_cell(a, 'sdf_error_cm', 2)} |")
    return "\n".join(lines) + "\n", data


def _near_note() -> str:
    return (f"Near furniture: the point's nearest true surface is furniture, or a furniture surface lies within "
            f"{100 * NEAR_FURNITURE_M:g} cm of it (or it is inside furniture); furniture is every solid of the "
            "synthetic building that an Atlanta room layout does not hold (tables, chairs, shelves, cabinets, boxes, "
            "the staircase; the layout: walls, floor, ceiling, interior walls). Away: the other points.")


def near_furniture_lines(results: dict, data: dict) -> list[str]:
    """Table I's near-furniture rows: per scene, the share of points near furniture and each
    method's SDF error (cm) there / away from it (n/a for a scene without labels)."""
    methods = results["methods"]
    lines = ["", "**Near furniture**: SDF error (cm) near furniture / away from it. " + _near_note(), "",
             "| Scene | Near furniture (% of points) | " + " | ".join(LABELS.get(m, m) for m in methods) + " |",
             "|---|" + "---:|" * (len(methods) + 1)]
    unlabelled = []
    for scene in results["scenes"]:
        agg = data["scenes"][scene]["methods"]
        if not any("near_furniture_share" in agg[m] for m in methods):
            unlabelled.append(scene)
            lines.append(f"| {scene} | n/a | " + " | ".join("n/a" for _ in methods) + " |")
            continue
        share = next(_cell(agg[m], "near_furniture_share", 1, 100) for m in methods if "near_furniture_share" in agg[m])
        cells = [f"{_cell(agg[m], 'sdf_error_near_furniture_cm', 2)} / {_cell(agg[m], 'sdf_error_away_from_furniture_cm', 2)}"
                 for m in methods]
        lines.append(f"| {scene} | {share} | " + " | ".join(cells) + " |")
    data["near_furniture_m"] = NEAR_FURNITURE_M
    if unlabelled:
        lines += ["", f"n/a ({', '.join(unlabelled)}): {NO_LABELS}."]
    return lines


def table1c(results: dict) -> tuple[str, dict]:
    """Table I's SDF error near furniture, the part of it whose nearest surface no camera
    measured, and away from furniture, per scene and method (``evaluation``'s docstring)."""
    methods = results["methods"]
    data: dict = {"title": "Table Ic", "methods": methods, "near_furniture_m": NEAR_FURNITURE_M, "scenes": {},
                  "unlabelled": {}}
    lines = ["# Table Ic: SDF error (cm) near furniture, and away from it", "", _near_note() + " Unobserved: as in "
             "Table Ib. Shares: of the points of Table I." + (" Mean ± standard deviation over the seeds."
                                                             if _nseeds(results["seeds"]) > 1 else ""), "",
             "| Scene | Method | Near furniture: share (%) | Near: SDF (cm) | Near and unobserved: share (%) | "
             "Near and unobserved: SDF (cm) | Away: SDF (cm) | All: SDF (cm) |", "|---|---|---|---|---|---|---|---|"]
    for scene, s in results["scenes"].items():
        data["scenes"][scene] = {}
        for m in methods:
            a = _agg([r["final"][m] for r in s["runs"] if m in r["final"]])
            if "near_furniture_share" not in a:
                continue
            data["scenes"][scene][m] = {k: a[k] for k in a if k.split("_std")[0] in FURNITURE + ("sdf_error_cm",)}
            lines.append(f"| {scene} | {LABELS.get(m, m)} | {_cell(a, 'near_furniture_share', 1, 100)} | "
                         f"{_cell(a, 'sdf_error_near_furniture_cm', 2)} | "
                         f"{_cell(a, 'near_furniture_unobserved_share', 1, 100)} | "
                         f"{_cell(a, 'sdf_error_near_furniture_unobserved_cm', 2)} | "
                         f"{_cell(a, 'sdf_error_away_from_furniture_cm', 2)} | {_cell(a, 'sdf_error_cm', 2)} |")
        if not data["scenes"][scene]:
            data["unlabelled"][scene] = NO_LABELS
            lines.append(f"| {scene} | every method | n/a | n/a | n/a | n/a | n/a | n/a |")
    if data["unlabelled"]:
        lines += ["", f"n/a ({', '.join(data['unlabelled'])}): {NO_LABELS}."]
    return "\n".join(lines) + "\n", data


def table2(results: dict) -> tuple[str, dict]:
    lines = ["# Table II: ablation of Atlanta-aware sampling (surfel mask, surfel loss)", ""]
    lines += _header(results)
    data: dict = {"title": "Table II", "mode": results["mode"], "scenes": {}}
    scenes = {k: v for k, v in results["scenes"].items() if any(r.get("ablation") for r in v["runs"])}
    if not scenes:
        return "\n".join(lines + ["No ablation was run (--ablation named no scene of this run)."]) + "\n", data
    head = ["Surfel mask", "Surfel loss"] + [f"{sc}: {SHORT[k]}" for sc in scenes for k in METRICS]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, s in scenes.items():
        data["scenes"][scene] = {"ground_truth": s["ground_truth"], "rows": []}
        for (mask, loss), model in ABLATION:
            a = _agg([r["ablation"][model] for r in s["runs"] if model in r.get("ablation", {})])
            data["scenes"][scene]["rows"].append({"surfel_mask": mask, "surfel_loss": loss, "model": model, **a})
    for j, ((mask, loss), _model) in enumerate(ABLATION):
        cells = []
        for scene in scenes:
            rows = data["scenes"][scene]["rows"]
            for k in METRICS:
                finite = [r[k] for r in rows if math.isfinite(r[k])]
                v = rows[j][k]
                cells.append(f"**{_fmt(v, k)}**" if finite and v == min(finite) else _fmt(v, k))
        lines.append("| " + " | ".join(["✓" if mask else "×", "✓" if loss else "×"] + cells) + " |")
    lines += ["", "Both off is iSDF; both on is AiSDF (w/o explicit map)."]
    return "\n".join(lines) + "\n", data


def table3(results: dict) -> tuple[str, dict]:
    """Mean per-module runtime (ms) over scenes and seeds, per neural model; the voxel map's
    integration and ESDF update; the paper's RTX 3090 row for comparison."""
    per_model: dict[str, list[dict]] = {}
    memory: dict[str, list[dict]] = {}
    for s in results["scenes"].values():
        for r in s["runs"]:
            for model, summ in r["models"].items():
                per_model.setdefault(model, []).append(summ.get("timings_ms", {}))
                if "memory_mb" in summ:
                    memory.setdefault(model, []).append(summ["memory_mb"])
    data: dict = {"title": "Table III", "unit": "ms", "machine": results.get("machine", {}), "models": {},
                  "paper_rtx3090": PAPER_TABLE3}
    for model, ts in per_model.items():
        keys = sorted({k for t in ts for k in t})
        data["models"][model] = {k: float(np.mean([t[k] for t in ts if k in t])) for k in keys}
    for model, ms in memory.items():
        data["models"][model].update({f"{k}_mb": float(np.mean([x[k] for x in ms])) for k in ms[0]})
    voxel = {m: t for m, t in data["models"].items() if m in MODELS and MODELS[m].kind == "voxel"}
    neural = {m: t for m, t in data["models"].items() if m not in voxel}
    extra = sorted({k for t in neural.values() for k in t} - set(MODULES) - {"sum", "step_wall", "keyframe_wall"})
    cols = list(MODULES) + extra
    lines = ["# Table III: runtime per module (ms)", "",
             f"Machine: {results.get('machine', {}).get('summary', '?')}. Trainer modules (sampling .. backward) are "
             "means per training step; AF estimation and surfel extraction are means per keyframe; Total adds the "
             "module means, as the paper does. Measured around the calls: step wall = one `pipeline.step()`, "
             "keyframe wall = one `pipeline.add_keyframe()` (with the Atlanta frame and surfels).", ""]
    head = ["Model"] + [MODULES.get(c, c) for c in cols] + ["**Total**", "Step wall", "Keyframe wall"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for model, t in neural.items():
        cells = [f"{t[c]:.1f}" if c in t else "-" for c in cols]
        walls = [f"{t[k]:.1f}" if k in t else "-" for k in ("step_wall", "keyframe_wall")]
        lines.append("| " + " | ".join([model] + cells + [f"**{t.get('sum', float('nan')):.1f}**"] + walls) + " |")
    lines.append("| paper (RTX 3090) | " + " | ".join(str(PAPER_TABLE3.get(c, "-")) for c in cols) +
                 f" | **{PAPER_TABLE3['sum']}** | - | - |")
    if voxel:
        lines += ["", "| Voxel map | Integrate (ms / frame) | ESDF update (ms, whole grid) | TSDF blocks (MB) | "
                  "ESDF grids (MB) |", "|---|---|---|---|---|"]
        nan = float("nan")
        for m, v in voxel.items():
            lines.append(f"| {LABELS.get(m, m)} | {v.get('integrate', nan):.1f} | {v.get('esdf', nan):.1f} | "
                         f"{v.get('tsdf_mb', nan):.1f} | {v.get('esdf_mb', nan):.1f} |")
        lines += ["", "Means over scenes and seeds. ESDF update: the whole dense grid, at every evaluation; ESDF "
                  "grids: the distance field, its observed mask and its gradient grids (float32), over the scene's "
                  "box."]
    return "\n".join(lines) + "\n", data


def _clean(o):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    return o


def write_json(path: Path, obj) -> None:
    Path(path).write_text(json.dumps(_clean(obj), indent=2))


def write_tables(out: Path, results: dict) -> dict[str, str]:
    """table1/1b/1c/2/3 .md and .json under ``out``; returns the markdown by name."""
    md = {}
    for name, fn in (("table1", table1), ("table1b", table1b), ("table1c", table1c), ("table2", table2),
                     ("table3", table3)):
        text, data = fn(results)
        (out / f"{name}.md").write_text(text)
        write_json(out / f"{name}.json", data)
        md[name] = text
    return md
