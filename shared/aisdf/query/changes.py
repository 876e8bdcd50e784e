"""What changed between two maps, for a bake that recomputes only that: the surfels that
moved (:func:`surfel_diff`) and the points whose nearest surfel may be one of them
(:func:`surfel_dirty`), the measured points that moved (:func:`measured_changes`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry import kdtree
from ..observed import pack_keys
from ..structure.measured import MeasuredPoints
from ..structure.surfel_types import Surfels


def surfel_boxes(s: Surfels) -> np.ndarray:
    """(N, 2, 3) world boxes of the rectangles."""
    h1, h2 = s.half_axes()
    half = np.abs(h1) + np.abs(h2)
    return np.stack([s.center - half, s.center + half], axis=1)


def surfel_diff(ref: Surfels | None, new: Surfels | None,
                tol: float = 0.0) -> tuple[Surfels, Surfels, Surfels | None]:
    """Which surfels changed between ``ref`` (the surfels the previous bake's samples were
    computed with) and ``new``: (changed: the changed ones' new geometry, then their old one
    (gone ones included); kept: the unchanged ones, in their reference geometry; the new
    reference). A surfel of ``new`` is unchanged when one of ``ref`` (nearest centre, same
    direction, matched once) lies within ``tol`` of it: no point of the rectangle moved more
    than ``tol`` (centre move plus the moves of its half axes), so no distance to it changed
    more than that. An unchanged surfel keeps its reference geometry (so small moves never
    add up unnoticed: a sample is at most 2 tol off); a changed or new one takes its new
    geometry, a gone one leaves the reference."""
    if new is None or not len(new):
        return (ref if ref is not None else Surfels()), Surfels(), new
    if ref is None or not len(ref):
        return new, Surfels(), new
    k = min(4, len(ref))
    _, nn = kdtree(ref.center).query(new.center, k=k)
    nn = nn.reshape(len(new), k)
    r1, r2 = ref.half_axes()
    n1, n2 = new.half_axes()
    match = np.full(len(new), -1)
    taken = np.zeros(len(ref), bool)
    best = np.full(len(new), np.inf)
    for c in range(k):
        j = nn[:, c]
        move = (np.linalg.norm(new.center - ref.center[j], axis=1)
                + np.minimum(np.linalg.norm(n1 - r1[j], axis=1), np.linalg.norm(n1 + r1[j], axis=1))
                + np.minimum(np.linalg.norm(n2 - r2[j], axis=1), np.linalg.norm(n2 + r2[j], axis=1)))
        ok = (move <= tol) & (new.direction == ref.direction[j]) & (move < best)
        # normals pointing the other way are another surface (a surfel is one-sided)
        ok &= np.sum(new.normal * ref.normal[j], axis=1) > 0
        best[ok], match[ok] = move[ok], j[ok]
    for i in np.argsort(best):  # one reference surfel per new one
        if match[i] >= 0:
            if taken[match[i]]:
                match[i] = -1
            else:
                taken[match[i]] = True
    same = match >= 0
    kept = ref[match[same]]
    return Surfels.concat([new[~same], ref[~taken]]), kept, Surfels.concat([kept, new[~same]])


def surfel_dirty(ref: Surfels | None, new: Surfels | None, tol: float, grow: float,
                 eps: float = 1e-3) -> tuple[Callable[[np.ndarray], np.ndarray], Surfels | None]:
    """(points (M, 3) -> (M,) bool: where the surfel distance the fused field uses may differ
    between ``ref`` and ``new`` (``surfel_diff``), the new reference). The fused answer uses
    the distance to the nearest surfel, and only within the fusion radius (``grow`` is that
    radius plus a margin), so a point is dirty only when a changed surfel (its old or new
    geometry) is within ``grow`` of it and no farther than the nearest kept surfel (+
    ``eps``, beyond the float32 screening of ``ExplicitSdf``): elsewhere the same kept
    surfel is the nearest before and after. A box test screens first."""
    from ..structure.surfel_map import ExplicitSdf

    changed, kept, out = surfel_diff(ref, new, tol)
    if not len(changed):
        return (lambda points: np.zeros(len(points), bool)), out
    boxes = surfel_boxes(changed)
    to_changed = ExplicitSdf(changed)
    to_kept = ExplicitSdf(kept) if len(kept) else None

    def dirty(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, np.float64).reshape(-1, 3)
        d = in_boxes(p, boxes, grow)
        idx = np.flatnonzero(d)
        if len(idx):
            dc = np.abs(to_changed(p[idx])[0])
            near = dc <= grow
            d[idx] = near
            idx, dc = idx[near], dc[near]
            if to_kept is not None and len(idx):
                d[idx] = dc <= np.abs(to_kept(p[idx])[0]) + eps
        return d

    return dirty, out


def in_boxes(points: np.ndarray, boxes: np.ndarray, grow: float, cell: float = 1.0) -> np.ndarray:
    """(M,) bool: points within ``grow`` of any axis-aligned box (binned, so many boxes and
    many points stay cheap)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(p), bool)
    if not len(boxes) or not len(p):
        return out
    lo, hi = boxes[:, 0] - grow, boxes[:, 1] + grow
    cells = np.floor(p / cell).astype(np.int64)
    key = pack_keys(cells)  # one sort of int64 keys groups the points by cell
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1], True])
    uc = cells[order[bounds[:-1]]]
    clo, chi = uc * cell, (uc + 1) * cell
    for n in range(len(uc)):  # boxes meeting this cell, then its points
        meet = np.all((lo <= chi[n]) & (hi >= clo[n]), axis=1)
        if not meet.any():
            continue
        ii = order[bounds[n]:bounds[n + 1]]
        q = p[ii]
        hit = np.zeros(len(ii), bool)
        for bl, bh in zip(lo[meet], hi[meet]):
            hit |= np.all((q >= bl) & (q <= bh), axis=1)
        out[ii] = hit
    return out


def layout_changes(old: MeasuredPoints | None, new: MeasuredPoints | None,
                   tol: float = 0.01) -> MeasuredPoints | None:
    """The predicted layout points (protocol 1.13, ``structure.layout``) of one map with no
    point of the other within ``tol`` (both ways), or None when none moved more than that. A
    bake capped with ``old`` answers within ``tol`` of one capped with ``new`` wherever no
    such point is the nearest (``measured_dirty``)."""
    a = np.zeros((0, 3)) if old is None else old.points
    b = np.zeros((0, 3)) if new is None else new.points
    if not len(a) and not len(b):
        return None
    if not len(a) or not len(b):
        return MeasuredPoints(b if len(b) else a)
    gone = a[~np.isfinite(new.distance(a, within=tol))]
    came = b[~np.isfinite(old.distance(b, within=tol))]
    out = np.concatenate([gone, came])
    return MeasuredPoints(out) if len(out) else None


def measured_changes(old, new, cells) -> MeasuredPoints | None:
    """The measured points (protocol 1.4) that are in one of the submap sets ``old`` and
    ``new`` but not in the other, among the submaps of ``cells`` (those that changed), or
    None when none changed. A voxel's point moves only when a keyframe adds pixels to it, so
    an unchanged voxel's point is equal bit for bit."""
    moved = []
    for c in cells:
        a, b = old.submaps.get(c), new.submaps.get(c)
        pa = np.zeros((0, 3), np.float32) if a is None or a.measured is None else a.measured
        pb = np.zeros((0, 3), np.float32) if b is None or b.measured is None else b.measured
        if pa is pb:
            continue
        both = np.concatenate([pa, pb]).astype(np.float32)
        _, idx, counts = np.unique(both, axis=0, return_index=True, return_counts=True)
        moved.append(both[idx[counts == 1]])  # in one of the two only
    moved = [m for m in moved if len(m)]
    return MeasuredPoints(np.concatenate(moved)) if moved else None


def measured_dirty(moved: MeasuredPoints | None, held: MeasuredPoints | None, points: np.ndarray, grow: float,
                   eps: float = 1e-3, support: float = 0.0) -> np.ndarray:
    """(N,) bool: where the nearest measured point may differ between two maps whose measured
    points differ by ``moved`` (``measured_changes``: in one map only) and of which the newer
    holds ``held``. The answer depends on the measured points through the nearest one, and
    only within the fusion radius (``grow`` is that radius, or more), so a point is dirty only
    when a moved point is within ``grow`` of it and no farther than the nearest held point (+
    ``eps``): elsewhere the same unchanged point is the nearest before and after. ``support``:
    the answer also asks whether a measured point lies within this of something no farther
    than the nearest measured point (the fused answer's floor, 1.15: of the nearest surfel's
    nearest point, ``answer.FLOOR_SUPPORT``), so a moved point that much farther counts too."""
    grow, eps = grow + support, eps + support
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if moved is None or not len(p):
        return np.zeros(len(p), bool)
    d_moved = moved.distance(p, within=grow)
    out = np.isfinite(d_moved)
    idx = np.flatnonzero(out)
    if len(idx) and held is not None and len(held):
        out[idx] = d_moved[idx] <= held.distance(p[idx], within=grow) + eps
    return out


def submaps_changed_at(grid, new_cells, old_cells, changed, points: np.ndarray) -> np.ndarray:
    """(N,) bool: the points whose blended answer may differ between two submap sets on
    ``grid`` (cells ``old_cells`` and ``new_cells``) that differ in the submaps of ``changed``
    (added, replaced or gone). The blend at a point depends only on the submaps whose
    extended boxes hold it; a point no submap holds is answered by the nearest submap (the
    nearest in either set being a changed one is when that may differ)."""
    from ..submaps.field import covering, nearest_cell

    changed = set(changed)
    covered, touched = covering(grid, (set(new_cells), changed), points)
    out = touched.copy()
    rest = np.flatnonzero(~covered & ~touched)
    if len(rest) and changed:
        near_new = nearest_cell(grid, list(new_cells), points[rest]) if new_cells else []
        near_old = nearest_cell(grid, list(old_cells), points[rest]) if old_cells else []
        hit = np.zeros(len(rest), bool)
        for near in (near_new, near_old):
            if len(near):
                hit |= np.fromiter((c in changed for c in near), bool, len(rest))
        if not new_cells or not old_cells:
            hit[:] = True
        out[rest] = hit
    return out
