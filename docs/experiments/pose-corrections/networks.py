"""Reset vs keep after a pose correction: a walk whose second half drifts (up to 40 cm and 4
degrees), mapped by the submap mapper, then corrected in one batch; SDF error of the networks
(mapper.sdf) against the building's exact SDF, near the true surfaces and at the ghost surfaces
the drifted keyframes put, right after the correction and after more steps."""
import json
import time
import numpy as np, torch
torch.set_num_threads(1)
from aisdf.keyframes import keyframe_message
from aisdf.mapper.factory import make_mapper
from aisdf.synthetic import SyntheticSequence
from aisdf.geometry import backproject, transform, valid_depth

N, STRIDE, STEPS = 240, 6, 8
seq = SyntheticSequence(building="office", n_frames=N, H=60, W=80, seed=0)
ids = list(range(0, N, STRIDE))
half = ids[len(ids) // 2]

def drift(i):
    s = max(0.0, (i - half) / (N - half))
    a = np.radians(4.0 * s)
    D = np.eye(4); D[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    D[:3, 3] = [0.4 * s, -0.2 * s, 0.0]
    c = seq.frame(i)["T_WC"][:3, 3]
    D[:3, 3] += c - D[:3, :3] @ c  # turn about the camera
    return D

def pts_of(i, T):
    f = seq.frame(i); d = np.where(valid_depth(f["depth"], 12.0), f["depth"], 0)
    return transform(T, backproject(d, f["K"])[d > 0][::13])

rng = np.random.default_rng(0)
true_pts = np.concatenate([pts_of(i, seq.frame(i)["T_WC"]) for i in ids if i > half])
ghost_pts = np.concatenate([pts_of(i, drift(i) @ seq.frame(i)["T_WC"]) for i in ids if i > half])
gt_g = seq.gt_sdf(ghost_pts)
ghost_pts = ghost_pts[gt_g > 0.15]  # where the drift put a surface into free space
near = true_pts + rng.normal(0, 0.1, true_pts.shape)

def err(p):
    return {"near_cm": round(100 * float(np.mean(np.abs(p.sdf(near) - seq.gt_sdf(near)))), 2),
            "phantom": round(float(np.mean(p.sdf(ghost_pts) < 0.05)), 3)}

def build(drifted, kind="submaps", **sub):
    p = make_mapper(kind, "cpu", {}, submaps=sub)
    for i in ids:
        kf = keyframe_message(seq.frame(i))
        if drifted:
            kf.T_WC = drift(i) @ kf.T_WC
        p.add_keyframe(kf)
        for _ in range(STEPS):
            p.step()
    return p

out = {"ghost_points": len(ghost_pts), "near_points": len(near)}
t = time.time(); right = build(False); out["right_build_s"] = time.time() - t
ghost_pts = ghost_pts[right.observed.contains(ghost_pts)]  # seen as free space by the right poses
out["ghost_points"] = len(ghost_pts)
out["right"] = err(right)
for _ in range(300):
    right.step()
out["right+300"] = err(right)
print("right", out["right"], out["right+300"], flush=True)
for mode in ("reset", "keep"):
    p = build(True, repose_networks=mode)
    r = {"before": err(p)}
    corr = {("depth", i): seq.frame(i)["T_WC"] for i in ids if i > half}
    rep = p.repose(corr)
    r["repose"] = {k: rep[k] for k in ("reposed", "submaps", "removed", "reset", "timings_ms")}
    owed = sum(p.retraining.values())
    t = time.perf_counter()
    for _ in range(owed):
        p.step()
    r["retrain"] = {"steps": owed, "s": round(time.perf_counter() - t, 2)}
    r["after"] = err(p)
    for k in (100, 300):
        for _ in range(100 if k == 100 else 200):
            p.step()
        r[f"+{k}"] = err(p)
    out[mode] = r
    print(mode, json.dumps(r), flush=True)
print(json.dumps(out, indent=1))
