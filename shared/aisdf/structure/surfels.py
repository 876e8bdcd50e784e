"""Atlanta-aware rectangular surfels of one keyframe (paper Sec. III-C). Pure numpy.

``extract_surfels(depth, K, T_WC, atlanta, ...)`` returns world-frame ``Surfels`` and the
(H, W) surfel mask. Steps:

1. ``keyframe_points`` (surfel_image.py): the depth image is block-averaged by ``stride``
   (invalid pixels left out; blocks across an occlusion edge dropped, as their mean is a
   flying point), and normals come from the averaged image with edge-aware differences,
   so a 320x240 image gives ~4800 points with low-noise normals. The same points serve
   the Atlanta update (``normals_W``): compute them once per keyframe.
2. Each point goes to the Atlanta direction (vertical or a horizontal one) its normal is
   nearest to, if within ``normal_deg`` of +-v.
3. Per direction, 1-point plane RANSAC with the normal fixed to v (surfel_fit.py). With
   the normal fixed a hypothesis is an offset d = v . p, so RANSAC over every point is a
   sliding window on the sorted offsets (exhaustive, deterministic); best plane, remove
   its inliers, repeat (floor and a table top). Inliers: |v . p - d| < max(inlier_min,
   inlier_sigmas * sigma(z)) with the Kinect-like depth noise sigma(z); d is their
   noise-weighted mean (per rectangle, over its own points).
4. Inliers are projected into the plane's 2D frame: axes (vertical, vertical x h) for a
   wall of direction h; for floors and ceilings (h, vertical x h) with h = horizontal[0]
   (the paper, ``floor_axes="reference"``) or, by default, the Atlanta horizontal that
   gives the plane's points the tightest bounding box (a table along an oblique wall).
   An occupancy grid of the inliers (cell from the points' spacing, 1-cell holes closed)
   and its summed-area table score candidate axis-aligned rectangles spanned by random
   pairs of occupied cells (and the bounding box): score = occupied - empty_penalty *
   empty cells, so a rectangle over an empty region scores low; the best is grown or
   shrunk side by side while the score improves, kept if filled >= min_fill, then its
   cells are removed and the search repeats (greedy). A kept rectangle is shrunk to the
   bounding box of its points (so it does not reach past the face by a grid cell) and
   dropped if the points' convex hull fills less than ``min_hull_fill`` of it.
5. The surfel normal is +-v, towards the camera (free space). The mask holds the pixels
   whose full-resolution point lies on a kept surfel (within the inlier distance).
"""

from __future__ import annotations

import numpy as np

from .atlanta import AtlantaFrame, LocalAtlanta, perpendicular
from .surfel_config import SurfelConfig, depth_sigma, inlier_threshold
from .surfel_fit import find_planes, find_rectangles
from .surfel_image import KeyframePoints, keyframe_points, surfel_mask
from .surfel_types import Surfels

__all__ = ["SurfelConfig", "KeyframePoints", "keyframe_points", "extract_surfels", "surfels_of_points",
           "surfel_mask"]


def _floor_axis(p: np.ndarray, vert: np.ndarray, horizontals: list[np.ndarray]) -> np.ndarray:
    """Of the Atlanta horizontals, the axis whose frame gives the points' smallest robust bounding box.

    The paper aligns floor rectangles with horizontal[0]; in an Atlanta room a table or a
    room part along another wall direction is covered far better along that direction."""
    best, best_area = horizontals[0], np.inf
    for h in horizontals:
        A = np.stack([h, np.cross(vert, h)], axis=1)
        lo, hi = np.percentile(p @ A, [2, 98], axis=0)
        area = float(np.prod(hi - lo))
        if area < best_area * 0.97:  # prefer earlier (horizontal[0]) on near ties
            best, best_area = h, area
    return best


def _directions(atlanta: AtlantaFrame | LocalAtlanta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(D,3) vectors, (D,) direction indices (-1 vertical), and the floor reference axis."""
    V = np.vstack([atlanta.vertical[None], np.asarray(atlanta.horizontal).reshape(-1, 3)])
    idx = np.concatenate([[-1], np.asarray(atlanta.indices, dtype=np.int64)])
    ref = atlanta.reference
    ref = ref - (ref @ atlanta.vertical) * atlanta.vertical
    ref = ref / np.linalg.norm(ref) if np.linalg.norm(ref) > 1e-6 else perpendicular(atlanta.vertical)
    return V, idx, ref


def extract_surfels(depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, atlanta: AtlantaFrame | LocalAtlanta,
                    config: SurfelConfig | None = None, rng: np.random.Generator | None = None,
                    frame_id: int = -1, points: KeyframePoints | None = None,
                    floor_axes: np.ndarray | None = None) -> tuple[Surfels, np.ndarray]:
    """Surfels (world frame) and the (H, W) bool surfel mask of one keyframe.

    ``atlanta``: the keyframe's LocalAtlanta (only the directions it supports) or the
    global AtlantaFrame (all directions). ``points``: keyframe_points(...) if already
    computed (e.g. for the Atlanta update). ``floor_axes``: :func:`surfels_of_points`.
    """
    cfg = config or SurfelConfig()
    depth = np.asarray(depth, dtype=np.float64)
    frame = atlanta.frame if isinstance(atlanta, LocalAtlanta) else atlanta
    if not frame.valid or (isinstance(atlanta, LocalAtlanta) and not atlanta.initialised):
        return Surfels(), np.zeros(depth.shape, dtype=bool)
    kp = points if points is not None else keyframe_points(depth, K, T_WC, cfg)
    surfels = surfels_of_points(kp, atlanta, cfg, rng, frame_id, floor_axes=floor_axes)
    if len(surfels) == 0:
        return surfels, np.zeros(depth.shape, dtype=bool)
    return surfels, surfel_mask(depth, K, T_WC, surfels, cfg, kp.stride)


def surfels_of_points(kp: KeyframePoints, atlanta: AtlantaFrame | LocalAtlanta, config: SurfelConfig | None = None,
                      rng: np.random.Generator | None = None, frame_id: int = -1,
                      directions: set[int] | None = None, floor_axes: np.ndarray | None = None) -> Surfels:
    """Steps 2-4 on a keyframe's points: its surfels (world frame), no mask.

    ``directions``: extract only the planes of these direction indices (-1 the vertical,
    k ``horizontal[k]``; None: all of ``atlanta``'s). Every point still goes to the nearest of
    all of ``atlanta``'s directions, so a point of another wall never joins these planes
    (the mapper uses this for the keyframes that came before a direction was published).
    ``floor_axes``: (K, 3) the horizontals a floor's or a table's rectangle may be aligned
    with (``floor_axes: best``; None: every Atlanta horizontal). A keyframe fitted again
    after a pose correction keeps the axes it chose on arrival
    (``Structure.extract_again``): a partial view of a table is boxed more tightly along a
    wall direction published since, and its rectangle then overhangs the table's edges.
    """
    cfg = config or SurfelConfig()
    rng = rng or np.random.default_rng(frame_id if frame_id >= 0 else 0)
    frame = atlanta.frame if isinstance(atlanta, LocalAtlanta) else atlanta
    if not frame.valid or (isinstance(atlanta, LocalAtlanta) and not atlanta.initialised):
        return Surfels()
    V, dir_idx, ref = _directions(atlanta)
    floor_cands = ([*np.asarray(floor_axes, np.float64).reshape(-1, 3)] if floor_axes is not None and len(floor_axes)
                   else [ref, *np.asarray(frame.horizontal).reshape(-1, 3)])
    vert = V[0]
    P = len(kp.points_W)
    if P == 0:
        return Surfels()
    cosines = np.abs(kp.normals_W @ V.T)
    assign = np.argmax(cosines, axis=1)
    assign[cosines[np.arange(P), assign] < np.cos(np.radians(cfg.normal_deg))] = -1
    thr_all = inlier_threshold(kp.depth, cfg)
    w_all = 1.0 / depth_sigma(kp.depth, cfg) ** 2
    min_pts = max(cfg.min_plane_points, int(cfg.min_plane_fraction * P))
    rows: dict[str, list] = {k: [] for k in ("center", "normal", "axis1", "axis2", "extent", "direction")}
    for j, v in enumerate(V):
        sel = np.flatnonzero(assign == j)
        if len(sel) < min_pts or (directions is not None and int(dir_idx[j]) not in directions):
            continue
        pts = kp.points_W[sel]
        off = pts @ v
        for _, inl in find_planes(off, thr_all[sel], w_all[sel], cfg, min_pts):
            p_in = pts[inl]
            if j == 0:
                a1 = _floor_axis(p_in, vert, floor_cands) if cfg.floor_axes == "best" else ref
            else:
                a1 = vert
            a2 = np.cross(vert, a1 if j == 0 else v)
            A = np.stack([a1, a2], axis=1)
            side = np.median((kp.cam_W - p_in) @ v)
            n = v if side >= 0 else -v
            uv = p_in @ A
            cell = max(cfg.cell_min, cfg.cell_spacing * float(np.median(kp.spacing[sel][inl])))
            for lo, hi, inside in find_rectangles(uv, cell, cfg, rng):
                w = w_all[sel][inl][inside]
                d_r = float(np.average(off[inl][inside], weights=w))
                mid = (lo + hi) / 2
                # Of all the keyframe's points on this rectangle, most must have normals of this
                # direction: noisy normals of another wall can line up along its crossing line.
                slab = ((np.abs(kp.points_W @ v - d_r) < thr_all)
                        & np.all(np.abs(kp.points_W @ A - mid) <= (hi - lo) / 2, axis=1))
                if (assign[slab] == j).mean() < cfg.min_normal_share:
                    continue
                rows["center"].append(d_r * v + A @ mid)
                rows["normal"].append(n)
                rows["axis1"].append(a1)
                rows["axis2"].append(a2)
                rows["extent"].append(hi - lo)
                rows["direction"].append(dir_idx[j])
    if not rows["center"]:
        return Surfels()
    return Surfels(**rows, keyframe=np.full(len(rows["center"]), frame_id))
