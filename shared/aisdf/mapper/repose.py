"""Pose corrections (protocol 1.11): keyframes already in the map get a new camera-to-world
pose (a SLAM system's loop closure), and what the map derived from their old pose follows.

For a batch ``{(sensor, frame_id): T_WC}`` (``aisdf.mapper.Mapper.repose``), both mappers:

1. Each stored keyframe named gets its new ``T_WC`` (the one ``Frame`` every submap's view
   shares, so training samples its rays from the new pose at once); its surfels (world
   coordinates, fitted on arrival) are moved rigidly with it. Keys the map does not hold
   (never sent, not stored because they added nothing new, evicted) are reported
   ``unknown`` and change nothing; a pose equal to the held one is ``unchanged``.
2. The intake's knowledge follows, where the moved keyframes were and are: the measured
   points of the voxels their pixels fall in (at the old pose or the new) are pooled again
   from the stored keyframes whose frusta reach them (``rebuild_measured``: the same sums, bit
   for bit, as a map built with these poses from the start); the observed space takes their
   old marks out and marks them again at the new poses (``rebuild_observed``: the same
   voxels); the coverage (the redundancy and eviction test) and the box take them again.
   What evicted keyframes (or those the one network's store dropped) gave stays, except in
   the voxels pooled again, where it is lost: their poses cannot be corrected.
3. The Atlanta frame turns with the keyframes that support it (``Structure.follow_corrections``:
   each direction by the mean rotation of the keyframes whose surfels lie on it, weighted by
   their area): a frame averaged from drifting normals is otherwise left a degree or two off,
   and the global surfels, aligned to it, with it. Then the global surfel map is merged again
   where the moved keyframes' surfels were (``rebuild_surfels``): the global surfels they had
   merged into, or that they gave, go; the moved keyframes' surfels (and the masks training
   samples by) are fitted again from their depth at the new pose on the corrected directions
   (``Structure.extract_again``); and the stored keyframes' surfels there are merged in again.
4. Networks. The submap mapper gives each corrected keyframe to the submaps it observes
   under its new pose (the rule of ``SubmapPipeline._assign``, with new pixel masks), takes
   it out of those it no longer observes, and keeps every store in arrival order. A submap
   whose keyframes changed learnt the old surface where the keyframe no longer puts it, and
   a network forgets a surface only where new rays pass. So when one of its keyframes'
   observed points moved by more than ``submap.repose_reset_m`` (95th percentile over its
   rays), by default (``submap.repose_networks: move``) one rigid motion is fitted to the
   observed points the network learnt from (``submap_pairs``, ``submap_motion``: inside its
   box at the old and the new pose); if it leaves every keyframe within ``repose_reset_m``,
   the network is moved with it (``aisdf.network.move_network``, exact: its training is
   kept, the rate goes up again as for a new keyframe, and it is published with the next
   map). Otherwise (drift that grew along the walk: a submap of a few metres holds keyframes
   minutes apart) it starts again (a fresh network with its seed and centre, new AdamW
   state), first taught the old network's field warped point by point by the correction
   (``distill_network``, ``submap.repose_distill_steps``). ``reset`` always starts again
   (no distillation), ``keep`` never does; a smaller correction keeps the network, which
   follows it within steps. A network started again, and one kept, gets the next
   ``submap.repose_steps`` steps of its submap first (``retrain_pick``, the pipeline's steps,
   not at once: the correction is answered without waiting for them) and is not published
   before it has had them: receivers keep its last snapshot meanwhile. A submap left with
   no keyframe is removed from the mapper's map (a query service keeps the snapshot it
   holds: docs/protocol.md).
   The one-network mapper keeps its network, which trains on from the corrected keyframes.

Every changed submap is published with the next map (``published_step`` reset; a fresh
network once trained), and so is every submap whose observed space or measured points the
moved keyframes touched (their rays at the old and the new pose). Costs are timed per part
(``timings_ms`` of the result; the mapper service logs them).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..codec import is_rigid
from ..geometry import backproject, transform, valid_depth
from ..network import move_network
from ..observed import ObservedSpace, pack_keys, unpack_keys
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels
from .intake import grow_bounds

MOVE_MIN_POINTS = 50  # a submap whose box holds fewer of its keyframes' points is not moved but reset
DISTIL_BATCH = 1024  # points a distillation step (distill_network)
DISTIL_LR = 1e-3
SINGLE_STEPS = 0  # the one-network mapper: training steps taken at once after a correction
FULL_SHARE = 0.25  # a batch moving more than this share of the stored keyframes pools every point again
SAME_POSE_ATOL = 1e-9  # a pose within this (every matrix entry) of the held one is unchanged

Key = tuple[str, int]


@dataclass
class ReposeResult:
    """What a correction batch did: keys moved, keys the map does not hold, keys already at
    their pose, submaps whose keyframes changed, and the time of each part (ms)."""

    reposed: list[Key] = field(default_factory=list)
    unknown: list[Key] = field(default_factory=list)
    unchanged: list[Key] = field(default_factory=list)
    submaps: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)  # submaps left with no keyframe
    reset: list[str] = field(default_factory=list)  # submaps whose network started again
    moved: list[str] = field(default_factory=list)  # submaps whose network was moved with its keyframes
    old_poses: dict = field(default_factory=dict)  # key -> the pose it had (the reposed ones)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"reposed": len(self.reposed), "unknown": [list(k) for k in self.unknown],
                "unchanged": len(self.unchanged), "submaps": list(self.submaps),
                "removed": list(self.removed), "reset": list(self.reset), "moved": list(self.moved),
                "timings_ms": {k: round(v, 2) for k, v in self.timings_ms.items()}}


def check_corrections(corrections: dict) -> dict[Key, np.ndarray]:
    """``{(sensor, frame_id): (4, 4) rigid}`` as float64 copies; ValueError (nothing changed)
    for a key or a pose that is not one."""
    out = {}
    for key, T in corrections.items():
        if not (isinstance(key, tuple) and len(key) == 2 and isinstance(key[0], str)
                and isinstance(key[1], (int, np.integer)) and not isinstance(key[1], bool)):
            raise ValueError(f"a correction's key must be (sensor, frame_id), got {key!r}")
        T = np.array(T, np.float64)
        if T.shape != (4, 4) or not is_rigid(T):
            raise ValueError(f"the pose of {key[0]}/{int(key[1])} is not a rigid 4x4 camera-to-world transform")
        out[(key[0], int(key[1]))] = T
    return out


def move_surfels(s: Surfels | None, delta: np.ndarray) -> Surfels | None:
    """The surfels moved by the rigid ``delta`` (world to world)."""
    if s is None or not len(s):
        return s
    R, t = delta[:3, :3], delta[:3, 3]
    return replace(s, center=s.center @ R.T + t, normal=s.normal @ R.T, axis1=s.axis1 @ R.T, axis2=s.axis2 @ R.T)


def set_poses(frames: dict, corrections: dict[Key, np.ndarray], result: ReposeResult) -> None:
    """New poses on the held frames (``frames``: key -> an object with ``.frame``, or a Frame)."""
    for key, T in corrections.items():
        held = frames.get(key)
        if held is None:
            result.unknown.append(key)
            continue
        f = getattr(held, "frame", held)
        old = np.asarray(f.T_WC, np.float64)
        if np.allclose(old, T, rtol=0.0, atol=SAME_POSE_ATOL):
            result.unchanged.append(key)
            continue
        f.surfels = move_surfels(f.surfels, T @ np.linalg.inv(old))
        if getattr(f, "late_surfels", None) is not None:
            f.late_surfels = move_surfels(f.late_surfels, T @ np.linalg.inv(old))
        f.T_WC = T.copy()
        result.reposed.append(key)
        result.old_poses[key] = old


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


# ----------------------------------------------------------------------------- one network


def repose_single(pipe, corrections: dict, steps: int = SINGLE_STEPS) -> ReposeResult:
    """``MappingPipeline.repose``: module docstring; the network is kept (and trained
    ``steps`` steps at once when any keyframe moved: none by default)."""
    corr = check_corrections(corrections)
    res = ReposeResult()
    t0 = time.perf_counter()
    set_poses({sf.frame.key: sf for sf in pipe.trainer.store.keyframes}, corr, res)
    res.timings_ms["poses"] = 1e3 * (time.perf_counter() - t0)
    if res.reposed:
        rebuild_knowledge(pipe.intake, [sf.frame for sf in pipe.trainer.store.keyframes], res.timings_ms,
                          res.old_poses)
        t = time.perf_counter()
        for _ in range(steps):
            pipe.step()
        res.timings_ms["train"] = 1e3 * (time.perf_counter() - t)
    res.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
    return res


# ----------------------------------------------------------------------------- submaps


def cells_seen(pipe, kf) -> dict:
    """The cells a stored keyframe joins, with their ray-point counts (``_assign``'s rule)."""
    s = pipe.sub_cfg
    pts, _ = pipe._ray_points(kf)
    counts = pipe.grid.cells_touching(pts)
    need = max(s.min_points, s.min_share * len(pts))
    seen = {c: n for c, n in counts.items() if n >= need}
    if not seen and counts:
        c = max(counts, key=counts.get)
        seen = {c: counts[c]}
    return seen


def _insert_ordered(items: list, item, rank: dict, key) -> None:
    """Insert ``item`` into ``items`` (kept in ``rank`` order of ``key(x)``)."""
    r = rank[key(item)]
    i = 0
    while i < len(items) and rank.get(key(items[i]), -1) < r:
        i += 1
    items.insert(i, item)


def fit_rigid(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """The rigid 4x4 ``T`` nearest to carrying the points ``P`` (N, 3) onto ``Q`` (least
    squares, Kabsch)."""
    p0, q0 = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - p0).T @ (Q - q0))
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, q0 - R @ p0
    return T


def submap_pairs(pipe, c, held: list, before: dict, after: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """What the submap ``c``'s network learnt, and where a correction put it: for each keyframe
    it held (``held``), its observed points (``SubmapPipeline._ray_points``) at the old pose and
    at the new one (the same for a keyframe not moved), those inside its extended box at both."""
    pairs = []
    for k in held:
        if k in before and k in after:
            p, q = before[k], after[k]
        elif k in pipe.frames:
            p = q = pipe._ray_points(pipe.frames[k])[0]
        else:
            continue
        inside = pipe.grid.inside(c, p) & pipe.grid.inside(c, q)  # learnt there, and still in its box
        if inside.any():
            pairs.append((p[inside], q[inside]))
    return pairs


def submap_motion(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray | None, float]:
    """How a correction moved what a submap's network learnt (``submap_pairs``): the rigid motion
    (``fit_rigid``) of all the points, and what it leaves: the largest over the keyframes of
    the 95th percentile of their points' distance from where the motion puts them (so that one
    keyframe moved far among many still is not hidden). (None, inf) with fewer than
    ``MOVE_MIN_POINTS`` points."""
    if sum(len(p) for p, _ in pairs) < MOVE_MIN_POINTS:
        return None, float("inf")
    T = fit_rigid(np.concatenate([p for p, _ in pairs]), np.concatenate([q for _, q in pairs]))
    left = max(float(np.percentile(np.linalg.norm(p @ T[:3, :3].T + T[:3, 3] - q, axis=1), 95)) for p, q in pairs)
    return T, left


def distill_network(pipe, c, net, old_net, pairs, steps: int, seed: int = 0) -> float:
    """Teaches the fresh ``net`` of submap ``c`` what ``old_net`` learnt, at the places a
    correction moved it to: a point ``x`` of the box is given ``old_net(x - d(x))``, ``d`` the
    displacement of the moved observed points nearest to ``x`` (``pairs``, inverse-distance
    weighted over 8), so a map that no one rigid motion corrects (drift that grew along the
    walk) is warped point by point. ``steps`` steps of Adam on an L1 loss, 1,024 points each,
    drawn about the observed surfaces (5 cm) and along the observed rays (15 cm). Returns the
    last steps' mean loss (m). Training then goes on from the corrected keyframes."""
    from scipy.spatial import cKDTree

    P = np.concatenate([p for p, _ in pairs])
    Q = np.concatenate([q for _, q in pairs])
    rng = np.random.default_rng(seed)
    n = steps * DISTIL_BATCH
    surf = Q[3::4] if len(Q) >= 4 else Q  # _ray_points: 4 per ray, the last on the surface
    x = np.concatenate([surf[rng.integers(len(surf), size=n // 2)] + rng.normal(0, 0.05, (n // 2, 3)),
                        Q[rng.integers(len(Q), size=n - n // 2)] + rng.normal(0, 0.15, (n - n // 2, 3))])
    x = x[pipe.grid.inside(c, x)]
    if len(x) < DISTIL_BATCH:
        return float("nan")
    rng.shuffle(x)
    dist, nn = cKDTree(Q).query(x, k=min(8, len(Q)))
    dist, nn = np.atleast_2d(dist.T).T, np.atleast_2d(nn.T).T
    w = 1.0 / np.maximum(dist, 1e-3)
    d = np.einsum("nk,nkj->nj", w / w.sum(1, keepdims=True), (Q - P)[nn])
    dev = next(net.parameters()).device
    with torch.no_grad():
        y = torch.cat([old_net(torch.as_tensor(x[i:i + 65536] - d[i:i + 65536], dtype=torch.float32, device=dev))
                       for i in range(0, len(x), 65536)])
    xt = torch.as_tensor(x, dtype=torch.float32, device=dev)
    opt = torch.optim.Adam(net.parameters(), lr=DISTIL_LR)
    losses = []
    for i in range(0, len(x) - DISTIL_BATCH + 1, DISTIL_BATCH):
        loss = (net(xt[i:i + DISTIL_BATCH]) - y[i:i + DISTIL_BATCH]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return float(np.mean(losses[-10:]))


def reset_network(pipe, sm) -> None:
    """A fresh network for the submap (its configuration: seed and encoding centre), new
    AdamW state and step count, the same keyframe store."""
    from ..mapping.trainer import Trainer

    old = sm.trainer
    tr = Trainer(old.cfg)
    pipe._attach_prior(sm.cell, tr)
    tr.store = old.store
    sm.trainer = tr


def repose_submaps(pipe, corrections: dict) -> ReposeResult:
    """``SubmapPipeline.repose``: module docstring."""
    corr = check_corrections(corrections)
    res = ReposeResult()
    t0 = time.perf_counter()
    before = {}  # ray points of the keyframes to move, at their old pose
    if pipe.grid is not None:
        before = {k: pipe._ray_points(pipe.frames[k])[0] for k in corr if k in pipe.frames}
    set_poses(pipe.frames, corr, res)
    after = {k: pipe._ray_points(pipe.frames[k])[0] for k in res.reposed} if pipe.grid is not None else {}
    # how far each keyframe's observed points moved (the 95th percentile over its sampled rays)
    moved_m = {k: float(np.percentile(np.linalg.norm(after[k] - before[k], axis=1), 95)) if len(after[k]) else 0.0
               for k in after}
    res.timings_ms["poses"] = 1e3 * (time.perf_counter() - t0)
    if not res.reposed:
        res.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
        return res
    rebuild_knowledge(pipe.intake, [sf.frame for sf in pipe.frames.values()], res.timings_ms, res.old_poses)
    changed: set = set()
    resets: set = set()  # submaps one of whose keyframes moved beyond repose_reset_m
    held_by = {c: list(sm.seen_by) for c, sm in pipe.submaps.items()}  # what each network learnt from
    if pipe.grid is not None:
        t = time.perf_counter()
        rank = {k: i for i, k in enumerate(pipe.frames)}
        waiting = {sf.frame.key for sf in pipe._waiting}
        for key in res.reposed:
            if key in waiting:
                continue
            kf = pipe.frames[key]
            far = moved_m.get(key, 0.0) > pipe.sub_cfg.repose_reset_m
            losses = {}
            for c, sm in pipe.submaps.items():
                if key in sm.seen_by:
                    old = [v for v in sm.trainer.store.keyframes if v.frame.key == key]
                    losses[c] = old[0].loss if old else None
                    sm.trainer.remove_keyframe(key)
                    sm.seen_by.remove(key)
                    changed.add(c)
                    if far:
                        resets.add(c)
            for c in cells_seen(pipe, kf):
                sm = pipe.submaps.get(c) or pipe._new_submap(c)
                view = kf.view(pipe._pixel_mask(kf, c), pipe._region(c))
                view.loss = losses.get(c)
                store = sm.trainer.store
                store.add_prepared(view)
                held = [i for i, v in enumerate(store.keyframes) if v is view]
                if held:  # back to its place in arrival order (unless the store's bound dropped it)
                    del store.keyframes[held[0]]
                    _insert_ordered(store.keyframes, view, rank, lambda v: v.frame.key)
                _insert_ordered(sm.seen_by, key, rank, lambda k: k)
                changed.add(c)
                if far:
                    resets.add(c)
        res.timings_ms["assign"] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        s = pipe.sub_cfg
        for c in sorted(changed):
            sm = pipe.submaps[c]
            if not len(sm.trainer.store):
                _remove_submap(pipe, c)
                res.removed.append(sm.id)
                continue
            pairs = submap_pairs(pipe, c, held_by.get(c, []), before, after) if c in resets else []
            if s.repose_networks == "move" and c in resets:
                T, resid = submap_motion(pairs)
                if T is not None and resid <= s.repose_reset_m:
                    if not np.allclose(T, np.eye(4), rtol=0.0, atol=SAME_POSE_ATOL):  # else what it learnt stays
                        move_network(sm.trainer.net, T)
                        sm.trainer.relearn()
                        res.moved.append(sm.id)
                    sm.published_step = -1  # at its corrected place already: published with the next map
                    continue
            if s.repose_networks in ("reset", "move") and c in resets:
                old_net = sm.trainer.net
                reset_network(pipe, sm)
                res.reset.append(sm.id)
                if s.repose_networks == "move" and s.repose_distill_steps and sum(len(p) for p, _ in pairs) >= MOVE_MIN_POINTS:
                    td = time.perf_counter()
                    distill_network(pipe, c, sm.trainer.net, old_net, pairs, s.repose_distill_steps,
                                    seed=int(sm.trainer.cfg.seed))
                    res.timings_ms["distill"] = res.timings_ms.get("distill", 0.0) + 1e3 * (time.perf_counter() - td)
            if s.repose_steps:  # trained first, a fresh network held back until then (retrain_pick)
                pipe.retraining[c] = max(pipe.retraining.get(c, 0), s.repose_steps)
            sm.published_step = -1  # published with the next map (a fresh network: once trained)
        res.timings_ms["reset"] = 1e3 * (time.perf_counter() - t)
    if pipe.grid is not None:  # submaps whose observed space or measured points moved: published again
        pts = np.concatenate(list(before.values()) + list(after.values()))
        grow = pipe.grid.overlap_m + pipe.observed.voxel + pipe.cfg.trunc_distance
        for c, sm in pipe.submaps.items():
            if c in changed or pipe.grid.inside(c, pts, grow=grow).any():
                sm.published_step = -1
    for sm in pipe.submaps.values():  # observed messages are built again from the rebuilt space
        sm.observed_key = ()
    pipe.publisher._measured_key = None
    from ..submaps.grid import cell_id

    res.submaps = [cell_id(c) for c in sorted(changed) if c in pipe.submaps]
    res.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
    return res


def retrain_pick(pipe):
    """``SubmapPipeline._pick`` while ``pipe.retraining`` owes steps: the submap owed most
    (the first id on a tie), one step less; paid up, it is published with the next map."""
    from ..submaps.grid import cell_id

    c = max(sorted(pipe.retraining, key=cell_id), key=pipe.retraining.__getitem__)
    pipe.retraining[c] -= 1
    sm = pipe.submaps[c]
    if pipe.retraining[c] <= 0:
        del pipe.retraining[c]
        sm.published_step = -1
    return sm


def _remove_submap(pipe, c) -> None:
    pipe.retraining.pop(c, None)
    del pipe.submaps[c]
    pipe._credit.pop(c, None)
    pipe._recent = [{k: n for k, n in seen.items() if k != c} for seen in pipe._recent]
    pipe._recent = [seen for seen in pipe._recent if seen]
