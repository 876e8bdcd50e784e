"""The submap mapper's whole-map bound on keyframes (``keyframes.max_keyframes_total``,
:mod:`aisdf.mapper.coverage`): beyond it, the stored keyframe best covered by the others is
removed from every submap's training store and from the map's keyframes. What the map
learnt from it stays: networks, measured points, observed space, surfels and box."""

from __future__ import annotations

KEEP_NEWEST = 2  # the newest keyframes (the replay window's first two) are never evicted


def evictable(pipe) -> list[tuple[str, int]]:
    """Keys that may go, oldest first: not the newest two, not waiting for the grid, and not
    the last keyframe of any submap's store."""
    keys = list(pipe.frames)[:-KEEP_NEWEST]
    keep = {k.frame.key for k in pipe._waiting}
    keep |= {sm.trainer.store.keyframes[0].frame.key for sm in pipe.submaps.values() if len(sm.trainer.store) == 1}
    return [k for k in keys if k not in keep]


def evict(pipe, key: tuple[str, int]) -> None:
    """Remove one keyframe from every submap and from the map's keyframes."""
    for sm in pipe.submaps.values():
        sm.trainer.remove_keyframe(key)
        if key in sm.seen_by:
            sm.seen_by.remove(key)
    del pipe.frames[key]
    pipe.intake.coverage.remove(key)
    pipe.evicted += 1


def bound(pipe) -> list[tuple[str, int]]:
    """Evict until the map holds at most ``max_keyframes_total`` keyframes; the evicted keys."""
    out = []
    limit = pipe.kf_policy.max_keyframes_total
    while len(pipe.frames) > limit:
        key = pipe.intake.coverage.most_redundant(evictable(pipe))
        if key is None:
            break
        evict(pipe, key)
        out.append(key)
    return out
