"""Model fitting of surfel extraction: 1-point plane RANSAC with a fixed normal, and greedy
axis-aligned rectangles on a plane's 2D occupancy grid. Pure numpy."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_closing
from scipy.spatial import ConvexHull, QhullError

from .surfel_config import SurfelConfig


def find_planes(offsets: np.ndarray, thr: np.ndarray, weights: np.ndarray, config: SurfelConfig,
                min_points: int) -> list[tuple[float, np.ndarray]]:
    """1-point RANSAC with a fixed normal, exhaustively: [(offset, inlier bool mask)], best first."""
    out: list[tuple[float, np.ndarray]] = []
    remaining = np.ones(len(offsets), dtype=bool)
    t = float(np.median(thr)) if len(thr) else config.inlier_min
    for _ in range(config.max_planes_per_direction):
        idx = np.flatnonzero(remaining)
        if len(idx) < min_points:
            break
        o = np.sort(offsets[idx])
        cnt = np.searchsorted(o, o + t, "right") - np.searchsorted(o, o - t, "left")
        i = int(np.argmax(cnt))
        if cnt[i] < min_points:
            break
        d = o[i]
        for _ in range(2):  # refine: noise-weighted mean of the inliers
            inl = remaining & (np.abs(offsets - d) < thr)
            if not inl.any():
                break
            d = float(np.average(offsets[inl], weights=weights[inl]))
        inl = remaining & (np.abs(offsets - d) < thr)
        if inl.sum() < min_points:
            remaining[np.abs(offsets - o[i]) < t] = False
            continue
        out.append((d, inl))
        remaining &= ~inl
    return out


# ----------------------------------------------------------------------------- rectangles

_MOVES = np.array([m for side in range(4) for m in
                   [np.eye(4, dtype=np.int64)[side] * (k if side % 2 else -k) for k in (1, 2, 4, 8, -1, -2, -4)]])


def _rect_sums(sat: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Sums over cell rectangles r (..., 4) = (i0, i1, j0, j1) inclusive, from a zero-padded SAT."""
    i0, i1, j0, j1 = r[..., 0], r[..., 1] + 1, r[..., 2], r[..., 3] + 1
    return sat[i1, j1] - sat[i0, j1] - sat[i1, j0] + sat[i0, j0]


def _score(sat: np.ndarray, r: np.ndarray, penalty: float) -> np.ndarray:
    occ = _rect_sums(sat, r)
    area = (r[..., 1] - r[..., 0] + 1) * (r[..., 3] - r[..., 2] + 1)
    return occ - penalty * (area - occ)


def _hull_fill(p: np.ndarray, ext: np.ndarray, r: float) -> float:
    """Convex hull area of points / area of their bounding box (extents ext), both grown by r
    (the half sample spacing the hull of samples misses along every edge)."""
    try:
        hull = ConvexHull(p)
    except QhullError:
        return 0.0
    grown = hull.volume + hull.area * r + np.pi * r * r  # 2D: volume = area, area = perimeter
    return float(grown / ((ext[0] + 2 * r) * (ext[1] + 2 * r)))


def find_rectangles(uv: np.ndarray, cell: float, config: SurfelConfig,
                    rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Greedy axis-aligned rectangles over 2D points (P, 2): [(lo (2,), hi (2,), point mask)]."""
    cfg = config
    mn = uv.min(axis=0)
    span = uv.max(axis=0) - mn
    cell = max(cell, float(np.sqrt((span[0] + cell) * (span[1] + cell) / cfg.max_cells)))
    ij = np.floor((uv - mn) / cell).astype(np.int64)
    shape = ij.max(axis=0) + 1
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    occ = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape) > 0
    pad = np.pad(occ, 1)  # close 1-cell sampling holes only, so no gap of a real edge is bridged
    occ = (binary_closing(pad, np.ones((2, 1), bool)) | binary_closing(pad, np.ones((1, 2), bool)))[1:-1, 1:-1] | occ
    free = np.ones(len(uv), dtype=bool)  # points not yet in a rectangle
    out = []
    hi4 = np.array([shape[0] - 1, shape[0] - 1, shape[1] - 1, shape[1] - 1])
    pen = cfg.empty_penalty
    for _ in range(cfg.max_rects_per_plane):
        cells = np.flatnonzero(occ)
        if len(cells) < 4:
            break
        sat = np.zeros((shape[0] + 1, shape[1] + 1), np.int32)
        np.cumsum(np.cumsum(occ, axis=0, dtype=np.int32), axis=1, out=sat[1:, 1:])
        ci, cj = np.divmod(cells, shape[1])
        ab = rng.integers(len(cells), size=(2, cfg.n_candidates))
        ia, ja = ci[ab], cj[ab]
        cand = np.empty((cfg.n_candidates + 1, 4), np.int64)
        cand[:-1, 0], cand[:-1, 1] = ia.min(axis=0), ia.max(axis=0)
        cand[:-1, 2], cand[:-1, 3] = ja.min(axis=0), ja.max(axis=0)
        cand[-1] = ci.min(), ci.max(), cj.min(), cj.max()
        sc = _score(sat, cand, pen)
        k = int(np.argmax(sc))
        r, best = cand[k], sc[k]
        for _ in range(64):  # hill-climb: move one side at a time while the score improves
            m = np.clip(r + _MOVES, 0, hi4)
            m = m[(m[:, 0] <= m[:, 1]) & (m[:, 2] <= m[:, 3])]
            s = _score(sat, m, pen)
            k = int(np.argmax(s))
            if s[k] <= best:
                break
            best, r = s[k], m[k]
        area = (r[1] - r[0] + 1) * (r[3] - r[2] + 1)
        filled = _rect_sums(sat, r) / area
        if filled < cfg.min_fill:
            break
        inside = free & (ij[:, 0] >= r[0]) & (ij[:, 0] <= r[1]) & (ij[:, 1] >= r[2]) & (ij[:, 1] <= r[3])
        occ[r[0]: r[1] + 1, r[2]: r[3] + 1] = False
        free &= ~inside
        if inside.sum() < cfg.min_rect_points:
            continue
        lo, hi = uv[inside].min(axis=0), uv[inside].max(axis=0)
        ext = hi - lo
        if ext.min() < cfg.min_side or ext[0] * ext[1] < cfg.min_area:
            continue
        if _hull_fill(uv[inside], ext, cell / 3) < cfg.min_hull_fill:
            continue  # the points do not fill their box (a face not aligned with these axes)
        out.append((lo, hi, inside))
    return out
