"""Pairs of 7-Scenes frames: the share of one frame's points the other's rays pass through
(``aisdf.mapper.clearing.FreeSpace``), how far beyond, and the same for wider windows.
    python docs/experiments/clearing-real-data/7s_diag.py   (reads $AISDF_DATA or ../shared/data)"""
import os
import numpy as np
from aisdf.datasets import open_dataset
from aisdf.mapper import clearing
from aisdf import geometry
ds = open_dataset("7scenes", os.path.join(os.environ.get("AISDF_DATA", "../shared/data"), "7scenes-redkitchen/data"))
def pts(f, step=4):
    d = f["depth"]; K = f["K"]; H, W = d.shape
    v, u = np.mgrid[0:H:step, 0:W:step]; D = d[v, u]; ok = geometry.valid_depth(D, 12.0)
    u, v, D = u[ok], v[ok], D[ok]
    P = np.stack([(u - K[0, 2]) / K[0, 0] * D, (v - K[1, 2]) / K[1, 1] * D, D], -1)
    return geometry.transform(f["T_WC"], P)
for a, b in [(0, 5), (0, 20), (50, 60), (100, 140), (200, 240), (10, 230)]:
    fa, fb = ds.frame(a), ds.frame(b)
    ev = clearing.FreeSpace(fb["depth"], fb["K"], fb["T_WC"])
    P = pts(fa)
    z, d = ev._lookup(P)
    passed, testable = ev.tested(P)
    ex = (d - z)[passed]
    print(f"{a}->{b}: tested {testable.sum()} passed {passed.sum()} ({100*passed.sum()/max(1,testable.sum()):.1f} %); excess cm quantiles {np.round(100*np.quantile(ex,[0.1,0.5,0.9]),1) if len(ex) else '-'}; z median {np.median(z[passed]) if passed.any() else 0:.2f}")
from scipy import ndimage
print("window radius sweep (strict windows, holes test nothing)")
for r in (2, 4, 6, 10):
    tot_t = tot_p = 0
    out = []
    for a, b in [(0, 20), (50, 60), (100, 140), (200, 240), (10, 230)]:
        fa, fb = ds.frame(a), ds.frame(b)
        ev = clearing.FreeSpace(fb["depth"], fb["K"], fb["T_WC"])
        dd = np.where(geometry.valid_depth(fb["depth"], 12.0), fb["depth"], 0).astype(np.float32)
        ev.dmin = ndimage.minimum_filter(dd, size=2 * r + 1, mode="nearest")
        passed, testable = ev.tested(pts(fa))
        out.append(f"{100*passed.sum()/max(1,testable.sum()):.1f}% of {testable.sum()}")
    print(r, out)
