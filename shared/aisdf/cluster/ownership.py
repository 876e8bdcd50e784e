"""Who owns which region of the map (protocol 1.14): a pure rule every mapper, front end and
test computes alike from the live mapper ids, with no coordination.

* A *region* is a block of ``region_cells`` x ``region_cells`` submap cells in the
  horizontal plane (one layer vertically): cell ``(i, j, k)`` is in region
  ``(i // n, j // n, k)``; its id is ``"a_b_c"`` like a cell id.
* The owners of a region are the live mapper ids ranked by rendezvous (highest random
  weight) hashing: ``score(m, r) = blake2b(m + "\\0" + r)`` as a 64-bit integer, highest
  first, ties broken by the id. Rank 1 trains and publishes the region's submaps; rank 2
  (a replica) stores the keyframes touching it (and pools their points) but does not train.
  The hash is blake2b (never Python's salted ``hash``), so every process agrees; when a
  member joins or leaves only the regions where it is (or becomes) rank 1 or 2 change.
* The global surfel map is published by the rank-1 owner of the pseudo-region ``surfels``.
* A keyframe is acknowledged for its front end once every owner it needs (ranks 1 and 2 of
  every region it touches, among the live members) has acknowledged holding it
  (``satisfied``); an acknowledgement without a mapper id (a 1.11 mapper) counts alone.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping

ALL = "*"  # an acknowledgement that holds the keyframe for every region (before the grid, or no cluster)
LEGACY = ""  # the mapper id of an acknowledgement that names none (a 1.11 mapper)
SURFELS = "surfels"  # pseudo-region whose rank-1 owner publishes map/surfels


def region_of(cell, region_cells: int = 2) -> tuple[int, int, int]:
    """The region holding a submap cell ``(i, j, k)``."""
    n = int(region_cells)
    if n < 1:
        raise ValueError("region_cells must be at least 1")
    i, j, k = (int(v) for v in cell)
    return (i // n, j // n, k)


def region_id(region) -> str:
    a, b, c = (int(v) for v in region)
    return f"{a}_{b}_{c}"


def score(member: str, region: str) -> int:
    """Rendezvous weight of ``member`` for ``region`` (a region id or pseudo-region): stable
    across processes, machines and Python versions."""
    h = hashlib.blake2b(f"{member}\0{region}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "big")


def ranked(region: str, members: Iterable[str]) -> list[str]:
    """The members ordered for ``region``: rank 1 first."""
    return sorted(set(members), key=lambda m: (-score(m, region), m))


def owners(region: str, members: Iterable[str], replicas: int = 2) -> list[str]:
    """Ranks 1 .. ``replicas`` of ``region`` among ``members`` (fewer when fewer members)."""
    return ranked(region, members)[:max(1, int(replicas))]


def rank(member: str, region: str, members: Iterable[str]) -> int:
    """1-based rank of ``member`` for ``region`` (0 when it is not a member)."""
    r = ranked(region, members)
    return r.index(member) + 1 if member in r else 0


def surfel_owner(members: Iterable[str]) -> str | None:
    r = ranked(SURFELS, members)
    return r[0] if r else None


def needed_acks(touched: Iterable[str], members: Iterable[str], replicas: int = 2) -> set[tuple[str, str]]:
    """(mapper, region) pairs that must have acknowledged a keyframe touching ``touched``."""
    members = list(members)
    return {(m, r) for r in touched for m in owners(r, members, replicas)}


def satisfied(touched: Iterable[str] | None, acks: Mapping[str, object], members: Iterable[str],
              replicas: int = 2) -> bool:
    """Is a keyframe safely in the map? ``acks``: mapper id -> the regions it holds the
    keyframe for (a set of region ids, or ``ALL``); ``touched``: the regions the keyframe
    touches as the acknowledgements said (None: not known, every acknowledgement so far held
    it whole). A legacy acknowledgement (id ``LEGACY``) suffices alone, as in 1.11. With
    ``touched`` known: every needed (mapper, region) pair acknowledged; unknown: every live
    member acknowledged. Never with no live member that acknowledged."""
    if LEGACY in acks:
        return True
    members = set(members)
    live = {m: h for m, h in acks.items() if m in members}
    if not live:
        return False
    if touched is None:
        return members <= set(live)
    for m, r in needed_acks(touched, members, replicas):
        held = live.get(m)
        if held is None or (held != ALL and r not in held):
            return False
    return True
