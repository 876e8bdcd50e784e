"""The query engine's map: one consistent version of the mapper's field (a single network
or a set of submaps), its observed space and surfels, replaced whole, never changed in
place (``engine.QueryEngine`` swaps a new one in with one reference assignment)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..observed import ObservedGrid
from ..structure.measured import MeasuredPoints
from ..structure.surfel_types import Surfels
from ..submaps.grid import SubmapGrid


@dataclass(frozen=True)
class SubmapSnapshot:
    """One submap's newest snapshot, its network rebuilt."""

    cell: tuple[int, int, int]
    version: int  # the global map version it was published at
    step: int
    net: torch.nn.Module
    observed: ObservedGrid | None  # observed space of its extended box
    bounds: np.ndarray | None
    measured: np.ndarray | None = None  # protocol 1.4: (M, 3) measured points in its extended box
    term: int = 0  # protocol 1.14: the ownership term of the mapper shard that published it (0: one mapper)
    mapper: str | None = None  # protocol 1.14: that mapper's id

    @property
    def order(self) -> tuple[int, int]:
        """Snapshots of one cell order by (term, version)."""
        return (self.term, self.version)


@dataclass(frozen=True)
class SubmapSet:
    """The submaps of one mapper incarnation, or of the mapper shards sharing one grid
    (protocol 1.14), replaced whole, never changed in place."""

    grid: SubmapGrid
    submaps: dict  # cell -> SubmapSnapshot

    @property
    def sharded(self) -> bool:
        """Published by mapper shards (protocol 1.14): its snapshots carry terms."""
        return any(s.term for s in self.submaps.values())

    def changed_since(self, other: "SubmapSet") -> list[tuple[int, int, int]]:
        """Cells whose submap differs (added, replaced or gone) between ``other`` and this set."""
        cells = set(self.submaps) | set(other.submaps)
        return sorted(c for c in cells if self.submaps.get(c) is not other.submaps.get(c))


@dataclass(frozen=True)
class MapState:
    version: int  # WeightSnapshot.version (submaps: the newest of the index's and the snapshots'): map_version
    step: int
    net: torch.nn.Module | None  # the single network; None when the map is made of submaps
    bounds: np.ndarray | None  # (2, 3) world AABB of what was observed, when the mapper sent it
    surfels: Surfels | None
    surfel_version: int
    epoch: int = 0  # the mapper incarnation: maps order by (epoch, version)
    observed: ObservedGrid | None = None  # observed space, when the mapper sent it (protocol 1.1)
    received: float = field(default_factory=time.monotonic)  # when these weights arrived
    submaps: SubmapSet | None = None  # protocol 1.3: the map as submaps (then net is None)
    measured: MeasuredPoints | None = None  # protocol 1.4: the union of the submaps' measured points

    @property
    def order(self) -> tuple[int, int]:
        return (self.epoch, self.version)

    def with_surfels(self, surfels: Surfels | None, surfel_version: int) -> "MapState":
        return MapState(self.version, self.step, self.net, self.bounds, surfels, surfel_version, self.epoch,
                        self.observed, self.received, self.submaps, self.measured)

    @classmethod
    def of_submaps(cls, sset: "SubmapSet", version: int, epoch: int, surfels: Surfels | None, surfel_version: int,
                   align: float, received: float | None = None) -> "MapState":
        """The map of a submap set: the union of its submaps' observed space (its origin on a
        multiple of ``align``, the bake's block) and of their measured points; its bounds
        those of what was observed (else of the submaps' bounds, else of their extended boxes)."""
        subs = list(sset.submaps.values())
        observed = union_observed([s.observed for s in subs], align)
        boxes = [s.bounds for s in subs if s.bounds is not None]
        if observed is not None:  # what was seen (a submap's bounds are its whole extended box)
            bounds = observed.bounds
        elif boxes:
            bounds = np.stack([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)])
        else:  # the extended boxes of the submaps
            corners = np.concatenate([sset.grid.corners_W(s.cell, sset.grid.overlap_m) for s in subs])
            bounds = np.stack([corners.min(0), corners.max(0)])
        return cls(version, sum(s.step for s in subs), None, bounds, surfels, surfel_version, epoch, observed,
                   time.monotonic() if received is None else received, sset, union_measured(subs))

    def same_field(self, other: "MapState") -> bool:
        """Same implicit field and surfels (a bake of one is a bake of the other)."""
        if self.surfels is not other.surfels:
            return False
        if self.submaps is None or other.submaps is None:
            return self.submaps is other.submaps and self.net is other.net
        return self.submaps.grid is other.submaps.grid and not self.submaps.changed_since(other.submaps)


@dataclass(frozen=True)
class Staleness:
    """Where a bake of the map ``baked`` may answer differently from the newer map ``newest``,
    and the map those points are answered from (``answer``). A point's answer changed where
    it lies in the extended box of a submap that changed (the blend at a point depends only
    on the submaps whose boxes hold it), where no submap holds it and its nearest submap (in
    either map) changed, where a changed measured point lies within the fusion radius and no
    farther than the nearest measured point (the answer depends on them through the nearest),
    and where a surfel that moved more than the bake's tolerance is within the fusion radius
    and no farther than the nearest unchanged one (``changes.surfel_dirty``); everywhere when
    the two maps are of different mapper incarnations or grids.

    ``added_only``: only the submaps the bake's map does not have (space mapped for the first
    time); ``answer`` is then the bake's map with those submaps added (its version the
    bake's), else the newest map."""

    baked: MapState
    newest: MapState
    answer: MapState
    everywhere: bool = False
    changed: tuple = ()
    moved: MeasuredPoints | None = None
    radius: float = 0.0
    added_only: bool = False
    surfels_moved: object = None  # points -> bool (changes.surfel_dirty), or None
    layout_moved: MeasuredPoints | None = None  # predicted layout points that moved (changes.layout_changes)
    layout: MeasuredPoints | None = None  # the answer's predicted layout points

    @classmethod
    def between(cls, baked: MapState, newest: MapState, radius: float, added_only: bool = False,
                surfel_ref: Surfels | None = None, surfel_tol: float = 0.0, align: float = 0.2,
                baked_layout: MeasuredPoints | None = None,
                newest_layout: MeasuredPoints | None = None) -> "Staleness":
        from .changes import layout_changes, measured_changes, surfel_dirty

        a, b = baked.submaps, newest.submaps
        if a is None or b is None or baked.epoch != newest.epoch or not a.grid.same_as(b.grid):
            return cls(baked, newest, newest, everywhere=True, added_only=added_only)
        changed = tuple(c for c in b.changed_since(a) if not added_only or c not in a.submaps)
        if added_only:
            if not changed:
                return cls(baked, newest, baked, added_only=True)
            subs = {**a.submaps, **{c: b.submaps[c] for c in changed}}
            answer = MapState.of_submaps(SubmapSet(b.grid, subs), baked.version, baked.epoch, newest.surfels,
                                         newest.surfel_version, align, baked.received)
            moved_surfels = None  # the new space's surfels come with it; elsewhere the bake's map answers
        else:
            answer = newest
            moved_surfels = surfel_dirty(surfel_ref, newest.surfels, surfel_tol, radius + 0.05)[0]
        # The newest surfels' predicted layout (1.13) may move far from any surfel that moved
        # (planes extended until they meet): where a moved predicted point is the nearest, the
        # answer changed (the baker's own rule for what a re-bake re-evaluates).
        moved_layout = None if added_only else layout_changes(baked_layout, newest_layout)
        return cls(baked, newest, answer, False, changed, measured_changes(a, answer.submaps, changed), radius,
                   added_only, moved_surfels, moved_layout, newest_layout)

    def points(self, pts: np.ndarray) -> np.ndarray:
        """(N,) bool: the points to answer from ``answer``."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        if self.everywhere:
            return np.ones(len(pts), bool)
        from .answer import FLOOR_SUPPORT
        from .changes import measured_dirty, submaps_changed_at

        out = np.zeros(len(pts), bool)
        if self.changed:
            new, old = self.answer.submaps, self.baked.submaps
            out = submaps_changed_at(new.grid, set(new.submaps), set(old.submaps), self.changed, pts)
        if self.surfels_moved is not None and (~out).any():
            rest = np.flatnonzero(~out)
            out[rest] = self.surfels_moved(pts[rest])
        if self.moved is not None and (~out).any():
            rest = np.flatnonzero(~out)
            out[rest] = measured_dirty(self.moved, self.answer.measured, pts[rest], self.radius,
                                       support=FLOOR_SUPPORT)  # (1.15's floor: a surfel's support)
        if self.layout_moved is not None and (~out).any():
            rest = np.flatnonzero(~out)
            out[rest] = measured_dirty(self.layout_moved, self.layout, pts[rest], self.radius + 0.05)
        return out


def union_observed(grids: list[ObservedGrid], align: float) -> ObservedGrid | None:
    """One grid holding every voxel any of ``grids`` holds (their union), its origin on a
    multiple of ``align`` (the bake's block, so that successive unions share the bake's
    lattice). Grids on the same voxel lattice are pasted; others are resampled at the
    union's voxel centres."""
    grids = [g for g in grids if g is not None]
    if not grids:
        return None
    voxel = min(g.voxel for g in grids)
    lo = np.min([g.origin for g in grids], axis=0)
    hi = np.max([g.bounds[1] for g in grids], axis=0)
    step = align if align > 0 and abs(align / voxel - round(align / voxel)) < 1e-6 else voxel
    origin = np.floor(lo / step + 1e-9) * step
    shape = np.maximum(np.ceil((hi - origin) / voxel - 1e-6).astype(np.int64), 1)
    occ = np.zeros(tuple(shape), bool)
    for g in grids:
        off = (g.origin - origin) / voxel
        ioff = np.round(off).astype(np.int64)
        if abs(g.voxel - voxel) < 1e-9 * voxel and np.abs(off - ioff).max() < 1e-6:
            sl = tuple(slice(ioff[a], ioff[a] + g.occ.shape[a]) for a in range(3))
            occ[sl] |= g.occ
        else:  # another lattice: the union's voxels whose centres it holds
            a = np.maximum(np.floor((g.origin - origin) / voxel).astype(np.int64), 0)
            b = np.minimum(np.ceil((g.bounds[1] - origin) / voxel).astype(np.int64), shape)
            idx = np.stack(np.meshgrid(*[np.arange(a[k], b[k]) for k in range(3)], indexing="ij"), -1).reshape(-1, 3)
            hit = g.contains(origin + (idx + 0.5) * voxel)
            occ[tuple(idx[hit].T)] = True
    return ObservedGrid(origin, voxel, occ)


def union_measured(submaps) -> MeasuredPoints | None:
    """The measured points of all ``submaps`` that carry some, or None when none does. A
    point in an overlap comes from each submap holding it, equal bit for bit when they were
    published from the same pool: such copies are kept once (the same distances, and a
    search among a third fewer points, on the floor). It runs at every snapshot's arrival, so
    the copies are found on the rows' bytes (one 1-d sort; ``np.unique(axis=0)`` took 3x
    longer), and the first of each is kept, in the order held."""
    held = [s.measured for s in submaps if s.measured is not None]
    if not held:
        return None
    pts = np.ascontiguousarray(np.concatenate(held))
    rows = pts.view(np.dtype((np.void, pts.dtype.itemsize * pts.shape[1]))).ravel()
    return MeasuredPoints(pts[np.sort(np.unique(rows, return_index=True)[1])])
