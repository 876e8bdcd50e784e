"""``aisdf bench scaling --seeds N``: the scaling walk once per seed, judged on the mean.

One walk on wall time is a lottery: between default runs of the submaps on the same code
the floor's error at the walk's end went 4.73-7.56 cm and the worst room's ratio
1.01-1.44, as wide as the effects being compared. Each seed changes the furniture's
jitter, the world frame, the walk, the depth noise and the training's draws; the rooms keep
their names. With N seeds every run is kept under ``out/seed-<s>/`` and the top-level
record holds, per method and scene, the mean of every figure over the seeds (a room's
ratio is the ratio of its mean errors; rooms not scored in every seed are left out), the
issue's criteria on those means, and each seed's own figures and criteria.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np

from .scaling_config import ScalingConfig
from .scaling_report import criteria, report
from .scaling_walk import room_ratio


# Per-walk detail that has no meaningful mean (kept in each seed's own record).
_NOT_AVERAGED = {"periods"}


def mean_record(recs: list[Any]) -> Any:
    """Mean over records of the same shape: numbers averaged, dicts key by key (keys that
    every record has, less ``_NOT_AVERAGED``), None where any is None, else the first's value."""
    first = recs[0]
    if any(r is None for r in recs):
        return None
    if all(isinstance(r, (int, float)) and not isinstance(r, bool) for r in recs):
        return round(float(np.mean(recs)), 4)
    if all(isinstance(r, dict) for r in recs):
        return {k: mean_record([r[k] for r in recs]) for k in first
                if k not in _NOT_AVERAGED and all(k in r for r in recs)}
    return first


def mean_runs(per_seed: list[dict]) -> dict:
    """{method: {scene: mean record}} over the seeds' ``runs`` (methods and scenes every seed has)."""
    out: dict[str, dict] = {}
    for m in per_seed[0]["runs"]:
        if not all(m in r["runs"] for r in per_seed):
            continue
        out[m] = {}
        for s in per_seed[0]["runs"][m]:
            if all(s in r["runs"][m] for r in per_seed):
                rec = mean_record([r["runs"][m][s] for r in per_seed])
                for room in rec.get("rooms", {}).values():
                    room["ratio_end"] = room_ratio(room)
                out[m][s] = rec
    return out


def run_seeds(cfg: ScalingConfig, run: Callable[[ScalingConfig], dict]) -> dict:
    """``run`` (``scaling.run``) once per seed (``cfg.seed``, ``cfg.seed + 1``, ...), then the mean record."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [cfg.seed + i for i in range(cfg.seeds)]
    t0 = time.time()
    per_seed = []
    for i, s in enumerate(seeds):
        if cfg.progress:
            print(f"seed {s} ({i + 1} of {len(seeds)})", flush=True)
        per_seed.append(run(cfg.model_copy(update={"seed": s, "seeds": 1, "out": str(out / f"seed-{s}")})))
    res: dict[str, Any] = {
        "config": cfg.model_dump(mode="json"), "scenes": per_seed[0]["scenes"], "mappers": per_seed[0]["mappers"],
        "machine": per_seed[0]["machine"], "seeds": seeds, "runs": mean_runs(per_seed),
        "unavailable": {k: v for r in per_seed for k, v in r.get("unavailable", {}).items()},
        "scene_info": per_seed[0]["scene_info"],
        "per_seed": [{"seed": s, "out": str(out / f"seed-{s}"), "criteria": r["criteria"],
                      "errors_cm": {m: {sc: {"walk_end": rr["error_walk_end_cm"], "end": rr["error_end_cm"]}
                                        for sc, rr in by.items()} for m, by in r["runs"].items()}}
                     for s, r in zip(seeds, per_seed)],
    }
    res["criteria"] = criteria(res)
    res["wall_s"] = round(time.time() - t0, 1)
    (out / "scaling.json").write_text(json.dumps(res, indent=1))
    (out / "scaling.md").write_text(report(res) + "\n")
    return res
