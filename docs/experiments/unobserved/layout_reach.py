"""Table Ib's unobserved points against the layout prior: is their nearest true surface
predicted, and does the surfel map hold its plane? The keyframes of the standard profile's walk
through the submap mapper's intake (no training: the prior needs only surfels and observed space).

    python docs/experiments/unobserved/layout_reach.py atlanta     # or manhattan
"""
import sys, time, numpy as np
from aisdf.bench.profiles import BenchConfig, PROFILES
from aisdf.bench.scenes import make_scene
from aisdf.bench.evaluation import EvalSet, nearest_surface
from aisdf.submaps.pipeline import SubmapPipeline
from aisdf.mapping.frames import Frame
from aisdf.keyframes import KeyframeSelector
from aisdf import protocol
from aisdf.query.engine import QueryEngine
from aisdf.query.answer import predicted_layout
from aisdf.structure import layout as L
from scipy.spatial import cKDTree
name = sys.argv[1]
cfg = BenchConfig(**{**PROFILES["standard"], "profile": "standard", "scenes": [name]})
scene = make_scene(name, cfg.opts_for(name), None)
frames = list(scene.frames)
pipe = SubmapPipeline.from_settings("cpu")
sel = KeyframeSelector(); t = time.time()
for i, f in enumerate(frames):
    if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
        try: pipe.add_keyframe(Frame(i, f["stamp"], f["depth"], f["K"], f["T_WC"]))
        except ValueError: pass
print("keyframes", len(pipe.keyframes), f"{time.time()-t:.0f}s")
eng = QueryEngine(device="cpu", bake=False)
for k, data in pipe.map_messages(1, changed_only=False, epoch=1):
    eng.take(k, protocol.unpack(data))
st = eng.state
lay = predicted_layout(st)
P = lay.points if lay is not None else np.zeros((0, 3))
es = EvalSet(scene, frames, 60000, np.random.default_rng([0, len(frames) - 1]), split=True)
u = ~es.observed
p, gt = es.points[u], es.gt[u]
q = nearest_surface(scene, p, gt); ok = np.all(np.isfinite(q), 1); p, gt, q = p[ok], gt[ok], q[ok]
dq = cKDTree(P).query(q)[0] if len(P) else np.full(len(q), np.inf)
print("predicted points", len(P), "; unobserved points", len(q), "; their nearest true surface within 5 cm of a predicted point:", np.mean(dq < 0.05).round(3), " 20 cm:", np.mean(dq < 0.2).round(3))
# planes known from surfels?
S = st.surfels
pl = L.planes(S, 0.05)
n = np.asarray(scene.gt_grad(p), np.float64); n /= np.linalg.norm(n, axis=1, keepdims=True)
onplane = np.zeros(len(q), bool)
for P_ in pl:
    if P_.area < L.LayoutConfig().min_area: continue
    onplane |= (np.abs(q @ P_.normal - P_.offset) < 0.05) & (np.abs(n @ P_.normal) > 0.95)
print(f"on a surfel plane (area >= {L.LayoutConfig().min_area} m^2):", onplane.mean().round(3), "; of those predicted within 5 cm:", np.mean(dq[onplane] < 0.05).round(3))
# observed state of q cells
obs = st.observed
try:
    o = obs.contains(q)
except Exception as e:
    o = None; print("observed lookup failed", e)
if o is not None:
    o = np.asarray(o, bool)
    print("q cells observed (free or surface):", o.mean().round(3), "; on plane & not predicted & observed:", np.mean(o[onplane & (dq >= 0.05)]).round(3))
from aisdf.bench.evaluation import measured_depth_points
kf_ids = {int(k.frame.frame_id) if hasattr(k, "frame") else int(k.frame_id) for k in pipe.keyframes}
for label, fr in (("all frames", frames), ("keyframes only", [frames[i] for i in sorted(kf_ids)])):
    M = measured_depth_points(fr, scene.max_depth)
    Mn = np.asarray(scene.gt_grad(M), np.float64); Mn /= np.maximum(np.linalg.norm(Mn, axis=1, keepdims=True), 1e-9)
    seen = np.zeros(len(q), bool); cnt = np.zeros(len(q), int)
    key = np.round(np.c_[np.abs(n) * 20, np.abs(np.einsum("ij,ij->i", n, q)) / 0.02]).astype(int)
    planes_, inv = np.unique(key, axis=0, return_inverse=True); inv = inv.ravel()
    for k in range(len(planes_)):
        i = np.flatnonzero(inv == k)[0]; nn, off = n[i], n[i] @ q[i]
        c = int((np.abs(Mn[np.abs(M @ nn - off) < 0.02] @ nn) > 0.95).sum())
        cnt[inv == k] = c
    print(f"{label}: nearest surface on a plane with >= 50 depth points: {np.mean(cnt >= 50):.3f}; of those not on a surfel plane: {np.mean(cnt[~onplane] >= 50):.3f}; median count there {np.median(cnt[~onplane]):.0f}")
from aisdf.structure.surfel_types import Surfels
KS = Surfels.concat([k.surfels for k in pipe.keyframes if getattr(k, "surfels", None) is not None and len(k.surfels)])
on_k = np.zeros(len(q), bool); on_any = np.zeros(len(q), bool)
for P_ in L.planes(KS, 0.05):
    hit = (np.abs(q @ P_.normal - P_.offset) < 0.05) & (np.abs(n @ P_.normal) > 0.95)
    on_any |= hit
    if P_.area >= L.LayoutConfig().min_area: on_k |= hit
print("on a plane of the keyframes' own surfels (before merging): any area", on_any.mean().round(3), f"; >= {L.LayoutConfig().min_area} m^2", on_k.mean().round(3), "(global map:", onplane.mean().round(3), ")")
print("cleared by free space:", pipe.intake.cleared)
