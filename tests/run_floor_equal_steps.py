"""The floor (or office) at equal training steps, not wall time: every keyframe of the walk
followed by --per-kf steps, then --tail steps; the whole-map error of the network alone
(implicit), the surfel map alone (explicit, unsigned) and the fused answer, and by distance
to the surface (share of points, mean signed error, mean |error| implicit, fused), in cm.
Figures of docs/scaling-notes.md, "Surfel bounds":

    .venv/bin/python tests/run_floor_equal_steps.py --method submaps --training '{"surfel_bounds": false}'
    .venv/bin/python tests/run_floor_equal_steps.py --method submaps
"""
import argparse
import json
import time

import numpy as np

from aisdf.bench import scaling, scaling_walk
from aisdf.structure.fusion import DEFAULT_FUSE_RADIUS, fuse
from aisdf.structure.surfel_map import explicit_sdf

ap = argparse.ArgumentParser()
ap.add_argument("--scene", default="floor")
ap.add_argument("--method", default="submaps")
ap.add_argument("--per-kf", type=float, default=6.0)
ap.add_argument("--tail", type=int, default=570)
ap.add_argument("--kf", type=int, default=200)
ap.add_argument("--training", default="{}")
ap.add_argument("--submaps", default="{}")
a = ap.parse_args()
cfg = scaling.resolve("full", keyframes=a.kf, n_points=50000)
seq, frames, spk = scaling_walk.scene_frames(a.scene, cfg)
whole = scaling_walk.whole_scorer(seq, frames, cfg)
tr = json.loads(a.training)
if a.method == "single":
    pipe = scaling.METHODS["single"][1]("cpu", tr)
else:
    from aisdf.submaps.pipeline import SubmapPipeline
    pipe = SubmapPipeline.from_settings("cpu", training=tr, atlanta=True, submaps=json.loads(a.submaps))
t0 = time.time(); debt = 0.0; tstep = 0.0
for i, f in enumerate(frames):
    try:
        pipe.add_keyframe(scaling_walk.frame_of(f))
    except ValueError as e:
        print("rejected", i, e)
    debt += a.per_kf
    while debt >= 1:
        s = time.perf_counter(); pipe.step(); tstep += time.perf_counter() - s; debt -= 1
def report(tag):
    p, gt = whole.points, whole.gt
    fi = np.asarray(pipe.sdf(p), np.float64)
    s = pipe.surfels()
    d_e, g_e, _ = explicit_sdf(p, s)
    ff, _, use = fuse(fi, None, d_e, None, DEFAULT_FUSE_RADIUS)
    out = {"tag": tag, "steps": pipe.steps, "step_ms": round(1e3 * tstep / max(pipe.steps, 1), 1),
           "implicit": round(100 * np.mean(np.abs(fi - gt)), 2),
           "explicit": round(100 * np.mean(np.abs(np.abs(d_e) - gt)), 2),
           "fused": round(100 * np.mean(np.abs(ff - gt)), 2), "fused_share": round(float(use.mean()), 3)}
    a_gt = np.abs(gt)
    for lo, hi in [(0, .1), (.1, .3), (.3, 1), (1, 3), (3, 99)]:
        m = (a_gt >= lo) & (a_gt < hi)
        if not m.any():
            continue
        out[f"band{lo}-{hi}"] = (round(float(m.mean()), 3), round(100 * np.mean(fi[m] - gt[m]), 2), round(100 * np.mean(np.abs(fi[m] - gt[m])), 2),
                                 round(100 * np.mean(np.abs(ff[m] - gt[m])), 2))
    if hasattr(pipe, "submaps"):
        out["submaps"] = len(pipe.submaps)
    print(json.dumps(out), flush=True)
report("walk_end")
for _ in range(a.tail):
    s = time.perf_counter(); pipe.step(); tstep += time.perf_counter() - s
report("tail")
print("wall", round(time.time() - t0))
