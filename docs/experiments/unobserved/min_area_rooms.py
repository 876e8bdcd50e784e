"""The layout prior's ``min_area`` on the rooms bench: one trained map per seed, the served answer
with the layout predicted at several ``min_area`` values (everything else as `aisdf bench rooms`).

    python docs/experiments/unobserved/min_area_rooms.py 3 [more seeds]
"""

import dataclasses
import sys

import numpy as np

from aisdf import metrics
from aisdf.bench.evaluation import labelled_building, near_furniture_mask, observed_mask
from aisdf.bench.methods import ComputeClock, make_runner, run_stream
from aisdf.bench.scenes import make_scene
from aisdf.structure import layout as L

AREAS = (0.5, 0.25, 0.1)
_default = L.LayoutConfig

for seed in [int(s) for s in sys.argv[1:]] or [3]:
    scene = make_scene("atlanta", {"n_frames": 20, "H": 240, "W": 320, "fps": 1.0, "scene_seed": seed})
    a = make_runner("aisdf", scene, ComputeClock(), "cpu", {"seed": 0, "steps_first_frame": 200, "steps_per_keyframe": 60})

    def at_end(i, t, seen):
        if i != len(scene) - 1:
            return
        p = metrics.eval_points(seen, n_points=20000, every=1, rng=np.random.default_rng([seed, i]), far_margin=scene.far_margin)
        gt = np.asarray(scene.gt_sdf(p), np.float64)
        keep = np.isfinite(gt)
        p, gt = p[keep], gt[keep]
        masks = {"all": np.ones(len(p), bool), "unobserved": ~observed_mask(scene, seen, p, gt),
                 "near furniture": near_furniture_mask(labelled_building(scene), p)}
        rows = {"no prior": a.query("served-noprior", p, False)[0]}
        for area in AREAS:
            L.LayoutConfig = lambda area=area, **kw: _default(**{"min_area": area, **kw})
            a._layout_key = None
            rows[f"min_area {area}"] = a.query("served", p, False)[0]
            rows[f"min_area {area}"] = rows[f"min_area {area}"], len(a.layout())
        L.LayoutConfig = _default
        print(f"atlanta seed {seed}: {len(p)} points")
        for k, v in rows.items():
            f, n = v if isinstance(v, tuple) else (v, 0)
            err = "  ".join(f"{m} {100 * np.abs(f - gt)[mk].mean():.2f}" for m, mk in masks.items())
            print(f"  {k:<16} {err}  ({n} predicted points)")

    run_stream(scene.frames, [a], "iterations", [len(scene) - 1], at_end, None)
