"""Table Ib's unobserved points: is their nearest true surface on a plane any frame measured?

    python docs/experiments/unobserved/unseen_planes.py atlanta     # or manhattan

A plane counts as measured when at least 50 of the walk's depth points (1 cm voxels) lie within
2 cm of it with a surface normal within 18 degrees of its own, anywhere in the scene."""
import sys, numpy as np
from aisdf.bench.profiles import BenchConfig, PROFILES
from aisdf.bench.scenes import make_scene
from aisdf.bench.evaluation import EvalSet, nearest_surface, measured_depth_points
name = sys.argv[1]
prof = {**PROFILES["standard"], "profile": "standard", "scenes": [name]}
cfg = BenchConfig(**prof)
scene = make_scene(name, cfg.opts_for(name), None)
frames = list(scene.frames)
es = EvalSet(scene, frames, 60000, np.random.default_rng([0, len(frames) - 1]), split=True)
u = ~es.observed
p, gt = es.points[u], es.gt[u]
q = nearest_surface(scene, p, gt)
ok = np.all(np.isfinite(q), 1)
p, gt, q = p[ok], gt[ok], q[ok]
n = np.asarray(scene.gt_grad(p), np.float64); n /= np.linalg.norm(n, axis=1, keepdims=True)
n = np.where((gt < 0)[:, None], -n, n)  # outward at the surface... sign irrelevant for a plane
M = measured_depth_points(frames, scene.max_depth)
Mn = np.asarray(scene.gt_grad(M), np.float64); Mn /= np.maximum(np.linalg.norm(Mn, axis=1, keepdims=True), 1e-9)
key = np.round(np.c_[np.abs(n) * 20, (np.abs(np.einsum("ij,ij->i", n, q))) / 0.02]).astype(int)
planes, inv = np.unique(key, axis=0, return_inverse=True)
inv = inv.ravel()
seen = np.zeros(len(planes), bool)
for k in range(len(planes)):
    i = np.flatnonzero(inv == k)[0]
    nn, off = n[i], n[i] @ q[i]
    close = np.abs(M @ nn - off) < 0.02
    par = np.abs(Mn[close] @ nn) > 0.95
    seen[k] = par.sum() >= 50
share = np.mean(~seen[inv])
print(f"{name}: {len(es)} points, unobserved {u.mean()*100:.1f} %; of those, nearest surface on a plane no frame measured: {100*share:.0f} % ({len(planes)} planes, {int((~seen).sum())} unmeasured)")
from aisdf.bench.evaluation import labelled_building, near_furniture_mask
up = np.asarray(scene.up, np.float64)
hor = np.abs(n @ up) > 0.9
b = labelled_building(scene)
nf = near_furniture_mask(b, p) if b is not None else np.zeros(len(p), bool)
h = p @ up
print(f"  nearest surface horizontal {100*hor.mean():.0f} % (below the point {100*np.mean(hor & (n @ up > 0)):.0f} %), near furniture {100*nf.mean():.0f} %, "
      f"true distance quantiles {np.round(np.quantile(gt, [.1, .5, .9]), 2)} m")
