"""Cost of a pose correction batch as the map grows: the floor building, keyframes added
without training, then (a) the newest 10 keyframes moved by 5 cm (what a map -> odom follower
sends), (b) half the keyframes moved by 30 cm and 3 degrees (a loop closure)."""
import sys, time, json
import numpy as np, torch
torch.set_num_threads(1)
from aisdf.keyframes import keyframe_message
from aisdf.mapper.factory import make_mapper
from aisdf.synthetic import SyntheticSequence

n_kf = int(sys.argv[1]) if len(sys.argv) > 1 else 200
STRIDE = 6
seq = SyntheticSequence(building="floor", n_frames=n_kf * STRIDE, H=120, W=160, seed=0)
p = make_mapper("submaps", "cpu", {}, keyframes={"skip_redundant": False})
t = time.perf_counter()
for i in range(0, n_kf * STRIDE, STRIDE):
    p.add_keyframe(keyframe_message(seq.frame(i)))
add_s = time.perf_counter() - t
keys = list(p.frames)
print(f"{len(keys)} keyframes, {len(p.submaps)} submaps, {len(p.surfels())} surfels, added in {add_s:.1f} s", flush=True)

def shift(T, dx, deg):
    a = np.radians(deg)
    D = np.eye(4); D[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    D[:3, 3] = [dx, 0, 0]
    return D @ T

for name, ks, dx, deg in (("newest 10 by 5 cm", keys[-10:], 0.05, 0.0),
                          ("half by 30 cm, 3 deg", keys[len(keys) // 2:], 0.3, 3.0)):
    corr = {k: shift(p.frames[k].frame.T_WC, dx, deg) for k in ks}
    t = time.perf_counter()
    rep = p.repose(corr)
    print(name, f"{time.perf_counter() - t:.2f} s", json.dumps({k: rep[k] for k in ("reposed", "timings_ms")}),
          f"submaps {len(rep['submaps'])} reset {len(rep['reset'])}", flush=True)
