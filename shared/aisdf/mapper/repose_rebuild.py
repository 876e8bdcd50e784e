"""What the map derived from keyframes follows their corrected poses (steps 2 and 3 of
:mod:`aisdf.mapper.repose`): the observed space, the measured points and the global surfel map
rebuilt where the moved keyframes were and are."""

from __future__ import annotations


import time
from dataclasses import replace

import numpy as np

from ..geometry import backproject, transform, valid_depth
from ..observed import ObservedSpace, pack_keys, unpack_keys
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels
from .intake import grow_bounds

FULL_SHARE = 0.25  # a batch moving more than this share of the stored keyframes pools every point again

Key = tuple[str, int]

def move_surfels(s: Surfels | None, delta: np.ndarray) -> Surfels | None:
    """The surfels moved by the rigid ``delta`` (world to world)."""
    if s is None or not len(s):
        return s
    R, t = delta[:3, :3], delta[:3, 3]
    return replace(s, center=s.center @ R.T + t, normal=s.normal @ R.T, axis1=s.axis1 @ R.T, axis2=s.axis2 @ R.T)


def _frustum_box(f, T: np.ndarray, max_depth: float, margin: float) -> tuple[np.ndarray, np.ndarray] | None:
    """A world box holding every point ``ObservedSpace.add`` marks for the frame at pose ``T``:
    its rays run from the camera centre through the image (a pyramid whose corners are the
    image's corner rays) to at most the deepest valid depth plus the margin. None: no depth."""
    d = f.metres()
    ok = valid_depth(d, max_depth)
    if not ok.any():
        return None
    reach = float(d[ok].max()) + margin
    H, W = d.shape
    K = np.asarray(f.K, np.float64)
    u, v = np.array([-1.0, W, -1.0, W]), np.array([-1.0, -1.0, H, H])
    dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(4)], -1)
    pts = np.vstack([T[:3, 3], (dirs * reach) @ T[:3, :3].T + T[:3, 3]])
    return pts.min(0), pts.max(0)


def rebuild_observed(intake, frames: list, moved: dict[Key, np.ndarray]) -> ObservedSpace:
    """The observed space with the keyframes ``moved`` (key -> old pose) at their new poses,
    as ``ObservedSpace.add`` of ``frames`` (every stored keyframe) in any order gives it. With
    per-voxel counts (since 1.11) each moved keyframe's marks at its old pose are taken out
    (``ObservedSpace.remove``) and marked at its new pose: the cost of the moved keyframes
    alone. Without (a space restored from an older checkpoint) the voxels the moved keyframes
    marked at their old poses (``gone``) are dropped, marked again by the stored keyframes
    whose frusta reach them (``_frustum_box``), and the moved keyframes are added at their new
    poses. Either way voxels no moved keyframe marked stay as they are (also those an evicted
    keyframe marked). A stored keyframe whose pixels newer rays cleared (``clearing``) takes
    out only the marks of the pixels it still holds."""
    old = intake.observed
    by_key = {f.key: f for f in frames}
    if old.counts is not None:  # each voxel counts the images marking it: take the old marks out
        for key, T in moved.items():
            f = by_key[key]
            d = f.metres()
            old.remove(d, f.K, T, intake.max_depth)
            old.add(d, f.K, f.T_WC, intake.max_depth)
        return old
    make = lambda: ObservedSpace(old.voxel, old.margin, old.max_rays)  # noqa: E731
    tmp = make()
    for key, T in moved.items():
        tmp.add(by_key[key].metres(), by_key[key].K, T, intake.max_depth)
    gone = tmp.keys
    out = make()
    out.load_state_dict({"voxel": old.voxel, "margin": old.margin, "keys": np.setdiff1d(old.keys, gone)})
    if len(gone):
        ijk = unpack_keys(gone)
        lo, hi = ijk.min(0), ijk.max(0)
        again = make()
        for f in frames:
            if f.key in moved:
                continue
            box = _frustum_box(f, np.asarray(f.T_WC, np.float64), intake.max_depth, old.margin)
            if box is None:
                continue
            b_lo, b_hi = np.floor(box[0] / old.voxel) - 1, np.floor(box[1] / old.voxel) + 1
            if np.all(b_lo <= hi) and np.all(b_hi >= lo):
                again.add(f.metres(), f.K, f.T_WC, intake.max_depth)
        back = again.keys[np.isin(again.keys, gone, assume_unique=True)]
        out.load_state_dict({"voxel": old.voxel, "margin": old.margin, "keys": np.union1d(out.keys, back)})
    for key in moved:
        f = by_key[key]
        out.add(f.metres(), f.K, f.T_WC, intake.max_depth)
    return out


def _voxel_keys(f, T: np.ndarray, m: MeasuredSurface) -> tuple[np.ndarray, np.ndarray]:
    """(the frame's depth with 0 where invalid, the voxel key of each of its pixels, -1 where
    none) as ``MeasuredSurface.add`` pools them at pose ``T``."""
    d = np.asarray(f.metres(), np.float64)
    ok = valid_depth(d, m.max_depth)
    k = np.full(d.shape, -1, np.int64)
    if ok.any():
        P = transform(np.asarray(T, np.float64), backproject(d, np.asarray(f.K, np.float64))[ok])
        k[ok] = pack_keys(np.floor(P / m.voxel).astype(np.int64))
    return np.where(ok, d, 0.0), k


def rebuild_measured(m: MeasuredSurface, frames: list, moved: dict[Key, np.ndarray]) -> MeasuredSurface:
    """The measured points with the keyframes ``moved`` (key -> old pose) at their new poses.
    Only the voxels a moved keyframe's pixels fall in, at its old pose or its new one, change:
    they are pooled again from every stored keyframe (``frames``, arrival order) whose frustum
    reaches them, with only its pixels in those voxels, so each such voxel's sums are added in
    the order and with the partial sums of a map built with these poses from the start (the
    same floats, bit for bit); every other voxel keeps its sums (evicted keyframes' included).
    A batch that moves more than ``FULL_SHARE`` of the keyframes pools every point again from
    the stored keyframes (cheaper then; what evicted keyframes gave is lost everywhere)."""
    by_key = {f.key: f for f in frames}
    if len(moved) > FULL_SHARE * len(frames):  # most of the map moved: pooled again from every keyframe
        out = MeasuredSurface(m.voxel, m.min_hits, m.max_depth)
        for f in frames:
            out.add(f.metres(), f.K, f.T_WC)
        return out
    touched = []
    for key, T in moved.items():
        touched += [_voxel_keys(by_key[key], T, m)[1], _voxel_keys(by_key[key], by_key[key].T_WC, m)[1]]
    touched = np.unique(np.concatenate([k[k >= 0] for k in touched])) if touched else np.zeros(0, np.int64)
    out = MeasuredSurface(m.voxel, m.min_hits, m.max_depth)
    if not len(touched):
        return m
    ijk = unpack_keys(touched)
    lo, hi = ijk.min(0) - 1, ijk.max(0) + 1
    for f in frames:
        T = np.asarray(f.T_WC, np.float64)
        box = _frustum_box(f, T, m.max_depth, 0.0)
        if box is None or not (np.all(np.floor(box[0] / m.voxel) <= hi) and np.all(np.floor(box[1] / m.voxel) >= lo)):
            continue
        d, k = _voxel_keys(f, T, m)
        keep = np.isin(k, touched)
        if keep.any():
            out.add(np.where(keep, d, 0.0), f.K, T)
    stay = ~np.isin(m.keys, touched, assume_unique=True)
    keys = np.concatenate([m.keys[stay], out.keys])
    order = np.argsort(keys, kind="stable")
    return MeasuredSurface.from_state_dict({
        "voxel": m.voxel, "min_hits": m.min_hits, "max_depth": m.max_depth, "keys": keys[order],
        "sums": np.concatenate([m.sums[stay], out.sums])[order],
        "counts": np.concatenate([m.counts[stay], out.counts])[order],
        "misses": np.concatenate([m.misses[stay], out.misses])[order]})


def _surfel_boxes(S: Surfels, grow: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world boxes around N rectangular surfels, grown by ``grow``."""
    half = (np.abs(S.axis1) * S.extent[:, :1] + np.abs(S.axis2) * S.extent[:, 1:2]) / 2 + grow
    return S.center - half, S.center + half


def _meets(lo: np.ndarray, hi: np.ndarray, blo: np.ndarray, bhi: np.ndarray) -> np.ndarray:
    """(N,) does box i (lo, hi) meet any of the boxes (blo, bhi)?"""
    if not len(lo) or not len(blo):
        return np.zeros(len(lo), bool)
    return np.any(np.all((lo[:, None] <= bhi[None]) & (hi[:, None] >= blo[None]), axis=-1), axis=1)


def rebuild_surfels(structure, frames: list, moved: dict[Key, np.ndarray]) -> None:
    """The global surfel map with the keyframes ``moved`` (key -> old pose) at their new poses,
    merged again where they were: the global surfels that meet a moved keyframe's surfels at
    its old pose (their boxes grown by the merge's tolerances) go, and the stored keyframes'
    surfels that meet what went (the moved keyframes' at their new poses, all of them) are
    merged in again, in arrival order. Elsewhere the map stays as it is (also what evicted
    keyframes gave, and what free space cleared)."""
    m = structure.map
    cfg = m.config
    grow = cfg.touch_tol + cfg.offset_tol
    by_key = {f.key: f for f in frames}
    old = []
    for key, T_old in moved.items():
        f = by_key[key]
        for S in (f.surfels, f.late_surfels):
            if S is not None and len(S):
                old.append(move_surfels(S, T_old @ np.linalg.inv(np.asarray(f.T_WC, np.float64))))
    if old and len(m):
        G = m.surfels()
        o_lo, o_hi = _surfel_boxes(Surfels.concat(old), grow)
        # also those a moved keyframe gave (late surfels lie on directions its own surfels may lack)
        ids = np.array([int(k[1]) for k in moved], dtype=np.int64)
        hit = _meets(*_surfel_boxes(G), o_lo, o_hi) | np.isin(np.asarray(G.keyframe, np.int64), ids)
        r_lo, r_hi = _surfel_boxes(G[hit], grow)
        m.remove(hit)
    else:
        r_lo = r_hi = np.zeros((0, 3))
    produced = m.n_produced
    for key in moved:  # fitted again at the corrected pose, on the corrected directions
        structure.extract_again(by_key[key])
    for f in frames:
        S = [x for x in (f.surfels, f.late_surfels) if x is not None and len(x)]
        if not S:
            continue
        S = Surfels.concat(S) if len(S) > 1 else S[0]
        if f.key not in moved:
            S = S[_meets(*_surfel_boxes(S), r_lo, r_hi)]
        if len(S):
            m.add(S)
    m.n_produced = produced
    structure._aligned = None  # the realigned copy of the old map


def rebuild_knowledge(intake, frames: list, timings: dict[str, float], moved: dict[Key, np.ndarray]) -> None:
    """The intake's observed space (``rebuild_observed``), measured points (all of them again,
    from ``frames``: stored ``Frame``s in arrival order, so the sums are those of a map built
    with these poses from the start, bit for bit), coverage and box (the moved keyframes'
    parts again), and the structure's global surfel map from the frames' surfels (module
    docstring, 2-3). ``moved``: key -> old pose of the keyframes re-posed."""
    t = time.perf_counter()
    intake.observed = rebuild_observed(intake, frames, moved)
    timings["observed"] = 1e3 * (time.perf_counter() - t)
    if intake.measured is not None:
        t = time.perf_counter()
        m = intake.measured
        measured = rebuild_measured(m, frames, moved)
        if hasattr(m, "version"):  # a change count readers compare: it moves on, never back
            measured.version = m.version + 1
        intake.measured = measured
        timings["measured"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    cov = intake.coverage
    cov._last = None  # (its cache of the frame last tested: keyed by the frame object, whose pose moved)
    for f in frames:
        if f.key in moved:  # (a redundancy test does not depend on the views' order)
            cov.remove(f.key)
            cov.add(f.key, f)
            intake.bounds = grow_bounds(intake.bounds, replace(f, depth=f.metres()), intake.max_depth)
    timings["coverage"] = 1e3 * (time.perf_counter() - t)
    if intake.structure is not None:
        t = time.perf_counter()
        intake.structure.follow_corrections(frames, moved)  # the Atlanta frame turns with its keyframes
        rebuild_surfels(intake.structure, frames, moved)
        intake.structure.forget_recent(moved)  # their kept points lie where the old poses put them
        timings["surfels"] = 1e3 * (time.perf_counter() - t)
