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
from dataclasses import dataclass, field

import numpy as np

from ..codec import is_rigid
from ..network import move_network
from .repose_networks import MOVE_MIN_POINTS, distill_network, reset_network, submap_motion, submap_pairs
from .repose_rebuild import Key, move_surfels, rebuild_knowledge

SINGLE_STEPS = 0  # the one-network mapper: training steps taken at once after a correction
SAME_POSE_ATOL = 1e-9  # a pose within this (every matrix entry) of the held one is unchanged



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
