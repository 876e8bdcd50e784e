"""False clears on real data: a static scene's keyframes through the submap mapper's intake
(no training), and what free-space clearing retires; with a ground-truth mesh, the cleared
measured voxels' distance to it.

    python docs/experiments/clearing-real-data/real_clear.py $AISDF_DATA/7scenes-redkitchen/data 1 1000
    python docs/experiments/clearing-real-data/real_clear.py $AISDF_DATA/replica-office0-nvblox 10 2000

argv: dataset folder, every k-th frame, frames; a fourth ``strict`` turns the measured points'
window with holes off. Environment: MARGIN (clear_margin_m, 0.05), WDEG (clear_window_deg),
PASSES (clear_passes, 2)."""
import sys, time, numpy as np
from aisdf.datasets import open_dataset
from aisdf.submaps.pipeline import SubmapPipeline
from aisdf.mapping.frames import Frame
from aisdf.mapper import clearing
path, every, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
if len(sys.argv) > 4 and sys.argv[4] == "strict":
    clearing.HOLE_WINDOW_VALID = 2.0
rec = []
orig = clearing.clear_measured
def spy(m, ev, *a):
    cnt = None
    if m is not None and len(m):
        cnt = m.counts.copy(), m.keys.copy()
    k, p, solid = orig(m, ev, *a)
    if cnt is not None:
        cnt = cnt[0][np.isin(cnt[1], k)]
    if len(p):
        rec.append((p, cnt))
    return k, p, solid
clearing.clear_measured = spy
ds = open_dataset("7scenes" if "7scenes" in path else None, path)
print(ds.name, len(ds), ds.W, ds.H, sys.argv[4:] or "holes")
import os
pipe = SubmapPipeline.from_settings("cpu", keyframes={"clear_margin_m": float(os.environ.get("MARGIN", "0.05")), "clear_window_deg": float(os.environ["WDEG"]) if os.environ.get("WDEG") else None, "clear_passes": int(os.environ.get("PASSES", "2"))})
t0 = time.time(); stored = 0
for i in range(0, min(len(ds), n), every):
    f = ds.frame(i)
    try:
        stored += bool(pipe.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"])))
    except ValueError:
        pass
pix = sum(np.count_nonzero(k.metres()) for k in pipe.keyframes)
print(f"stored {stored} measured {len(pipe.measured)} cleared {pipe.intake.cleared}; pixels kept {pix}; {time.time()-t0:.0f} s")
m = ds.gt_mesh()
if m is not None and rec:
    import trimesh
    from scipy.spatial import cKDTree
    S, _ = trimesh.sample.sample_surface(m, 3_000_000, seed=0)
    tree = cKDTree(S)
    class _P:
        @staticmethod
        def closest_point(_m, q):
            d, _ = tree.query(q)
            return None, d, None
    trimesh.proximity = _P
    P = np.concatenate([r[0] for r in rec]); C = np.concatenate([r[1] for r in rec])
    _, d, _ = trimesh.proximity.closest_point(m, P)
    solid = C >= 3
    print(f"cleared voxels {len(P)} (>=3 px: {solid.sum()}); dist to mesh quantiles cm "
          f"{np.round(100*np.quantile(d, [0.1, 0.5, 0.9]), 1)}; within 3 cm: {(d < 0.03).sum()} "
          f"({100*(d < 0.03).mean():.1f} %), of the >=3 px ones: {(d[solid] < 0.03).sum()}")
    Pm = pipe.measured.sums / pipe.measured.counts[:, None]
    ok = pipe.measured.counts >= 3
    _, dm, _ = trimesh.proximity.closest_point(m, Pm[ok][::4])
    print(f"kept measured (>=3 px, every 4th): dist to mesh mean {100*dm.mean():.2f} cm, within 3 cm {100*(dm<0.03).mean():.1f} %")
