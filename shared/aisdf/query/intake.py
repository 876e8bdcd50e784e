"""What a query service takes in (:class:`aisdf.query.engine.QueryEngine`'s map updates): a
one-network map's weights, a submap mapper's snapshots and index (protocol 1.3), and the surfel
map, each built aside and swapped in as one new :class:`MapState` under the engine's writer lock.
Maps order by ``(epoch, version)``; a new epoch replaces the whole set (module docstring of
:mod:`aisdf.query.engine`). A mixin: the engine holds ``_lock``, ``_state``, ``_index``,
``_surfels``, ``baker``, ``device`` and ``use_measured``."""

from __future__ import annotations


import numpy as np

from .. import keys, protocol
from ..network import build_model, load_numpy_state
from ..observed import ObservedGrid
from ..structure.measured import MeasuredPoints
from ..structure.surfel_types import Surfels
from ..submaps.grid import SubmapGrid, parse_cell_id
from .mapstate import MapState, SubmapSet, SubmapSnapshot


class MapIntake:
    """The map updates of :class:`aisdf.query.engine.QueryEngine` (see the module docstring)."""

    def set_weights(self, snap: protocol.WeightSnapshot) -> bool:
        """Build the network of a snapshot and swap it in; False if it is not newer (by
        (epoch, version)). Raises ValueError on a snapshot that cannot be loaded (the old map stays)."""
        order = (snap.epoch, snap.version)
        cur = self._state
        if cur is not None and order <= cur.order:
            return False
        net, bounds, observed = self._load(snap)
        # Protocol 1.5: a one-network map's measured points (built here, outside the lock).
        measured = MeasuredPoints(snap.measured["points"]) if snap.measured is not None and self.use_measured else None
        with self._lock:
            cur = self._state
            if cur is not None and order <= cur.order:
                return False
            sv, surf = self._surfels if self._surfels else ((0, -1), None)
            if sv[0] < snap.epoch:  # surfels of an older mapper incarnation: not this map's
                surf, sv = None, (0, -1)
            self._state = MapState(snap.version, snap.step, net, bounds, surf, sv[1], snap.epoch, observed,
                                   measured=measured)
            self.baker.map_arrived(self._state)
        return True

    def _load(self, snap: protocol.WeightSnapshot):
        """(network, bounds, observed grid) of a snapshot; ValueError when it cannot be loaded."""
        net = build_model(snap.model)
        load_numpy_state(net, snap.state)
        net = net.to(self.device).eval()
        for p in net.parameters():
            p.requires_grad_(False)
        bounds = snap.model.get("bounds")
        try:
            bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3) if bounds is not None else None
        except (TypeError, ValueError):
            raise ValueError("model bounds must be 2x3 numbers") from None
        observed = None
        if snap.observed is not None:
            try:
                observed = ObservedGrid.from_msg(snap.observed)
            except protocol.ProtocolError as e:
                raise ValueError(f"observed space: {e.message}") from None
        return net, bounds, observed

    # ------------------------------------------------------------------ submaps (protocol 1.3)

    @staticmethod
    def _merges(cur: MapState | None, epoch: int, term: int, grid: SubmapGrid | None) -> bool:
        """Does a submap snapshot join the current set (else it starts a new one)? The same
        mapper incarnation, or (1.14) a shard's snapshot on the grid of a set of shards:
        shards share one grid and may publish under different epochs (the set takes the newest)."""
        if cur is None or cur.submaps is None:
            return False
        if cur.epoch == epoch:
            return True
        return bool(term) and grid is not None and cur.submaps.sharded and cur.submaps.grid.same_as(grid)

    @classmethod
    def _submap_newer(cls, cur: MapState | None, epoch: int, version: int, cell, term: int = 0,
                      grid: SubmapGrid | None = None) -> bool:
        """A submap's snapshots order by (term, version) (term 0 with one mapper) within a set;
        sets by epoch."""
        if cur is None:
            return True
        if cur.submaps is None:  # a single network: the newer map wins, as between weights
            return (epoch, version) > cur.order
        if not cls._merges(cur, epoch, term, grid):
            return epoch > cur.epoch
        held = cur.submaps.submaps.get(cell)
        return held is None or (term, version) > held.order

    def set_submap(self, snap: protocol.WeightSnapshot) -> bool:
        """Take one submap's snapshot (``map/submaps/<id>``) if it is newer than the one held
        for that cell (by (epoch, version)); a newer epoch starts a new set. False if not
        newer; ValueError on a snapshot that cannot be loaded (the map stays as it was)."""
        if not isinstance(snap.submap, dict):
            raise ValueError("not a submap snapshot (no 'submap')")
        try:
            sid = snap.submap["id"]
            cell = parse_cell_id(sid)
            grid = SubmapGrid.from_msg(snap.submap["grid"])
        except (KeyError, TypeError) as e:
            raise ValueError(f"bad submap header: {e}") from None
        term, mapper = snap.submap.get("term", 0), snap.submap.get("mapper")
        if not isinstance(term, int) or isinstance(term, bool) or term < 0:
            raise ValueError(f"submap {sid}: 'term' must be a non-negative integer")
        mapper = mapper if isinstance(mapper, str) else None
        if not self._submap_newer(self._state, snap.epoch, snap.version, cell, term, grid):
            return False
        net, bounds, observed = self._load(snap)
        with self._lock:
            cur = self._state
            if not self._submap_newer(cur, snap.epoch, snap.version, cell, term, grid):
                return False
            epoch = snap.epoch
            if self._merges(cur, snap.epoch, term, grid):
                if not cur.submaps.grid.same_as(grid):
                    raise ValueError(f"submap {sid}: its grid differs from the grid of this mapper's other submaps")
                grid, subs, version = cur.submaps.grid, dict(cur.submaps.submaps), cur.version
                epoch = max(cur.epoch, snap.epoch)  # 1.14: shards' epochs; a served map never goes back
            else:  # the first submap, or a new mapper incarnation: a new set
                subs, version = {}, snap.version
            measured = snap.measured["points"] if snap.measured is not None and self.use_measured else None
            subs[cell] = SubmapSnapshot(cell, snap.version, snap.step, net, observed, bounds, measured, term, mapper)
            idx = self._index
            if idx is not None and idx.epoch == snap.epoch and self._complete(subs, idx):
                version = max(version, idx.version)
            self._state = self._submap_state(SubmapSet(grid, subs), max(version, snap.version), epoch, cur)
            self.baker.map_arrived(self._state)
        return True

    @staticmethod
    def _complete(subs: dict, idx: protocol.SubmapIndex) -> bool:
        """Does ``subs`` hold every submap the index lists, at least at its listed version?"""
        for sid, v in idx.submaps.items():
            held = subs.get(parse_cell_id(sid))
            if held is None or held.version < v["version"]:
                return False
        return True

    def _submap_state(self, sset: SubmapSet, version: int, epoch: int, cur: MapState | None) -> MapState:
        sv, surf = self._surfels if self._surfels else ((0, -1), None)
        if sv[0] < epoch:  # surfels of an older mapper incarnation: not this map's
            surf, sv = None, (0, -1)
        return MapState.of_submaps(sset, version, epoch, surf, sv[1], self.baker.config.block)

    def set_index(self, idx: protocol.SubmapIndex) -> list[str] | None:
        """Take a ``map/index``: the ids of the submaps to get because the index lists them at
        a newer version than held (a lost sample, a late join), or None when every submap is
        wanted (no submap map yet, or a newer mapper incarnation). When everything listed is
        held, the map takes the index's version."""
        with self._lock:
            old = self._index
            if old is None or (idx.epoch, idx.version) >= (old.epoch, old.version):
                self._index = idx
            cur = self._state
            # 1.14: the index of one of the shards of the current set (their epochs may differ)
            shard = (cur is not None and cur.submaps is not None and cur.submaps.sharded
                     and cur.submaps.grid.same_as(SubmapGrid.from_msg(idx.grid)))
            if not shard and (cur is None or idx.epoch > cur.epoch
                              or (cur.submaps is None and (idx.epoch, idx.version) > cur.order)):
                return None
            if cur.submaps is None or (idx.epoch < cur.epoch and not shard):
                return []
            subs = cur.submaps.submaps
            # 1.11: a submap the mapper removed (left without keyframes by a pose correction) is
            # not in an index at least as new as its snapshot: it goes (not a shard's: each
            # shard's index lists only the submaps it owns)
            listed = {parse_cell_id(sid) for sid in idx.submaps}
            gone = [c for c, h in subs.items() if c not in listed and h.version <= idx.version and not h.term]
            if gone and idx.epoch == cur.epoch:
                subs = {c: h for c, h in subs.items() if c not in gone}
                self._state = cur = self._submap_state(SubmapSet(cur.submaps.grid, subs), cur.version, cur.epoch,
                                                       cur)
                self.baker.map_arrived(cur)
            want = [sid for sid, v in idx.submaps.items()
                    if subs.get(parse_cell_id(sid)) is None or subs[parse_cell_id(sid)].version < v["version"]]
            if not want and idx.version > cur.version:
                self._state = MapState(idx.version, cur.step, None, cur.bounds, cur.surfels, cur.surfel_version,
                                       cur.epoch, cur.observed, submaps=cur.submaps, measured=cur.measured)
                self.baker.map_arrived(self._state)
        return want

    def take(self, key: str, msg: dict):
        """One decoded map message by its key under the namespace (``map/weights``,
        ``map/submaps/<id>``, ``map/index``, ``map/surfels``), as the mapper publishes it:
        what the matching ``set_*`` returns. For in-process feeds (the benches); the service's
        subscribers call ``set_*`` themselves. ValueError for any other key."""
        if key == keys.MAP_WEIGHTS:
            return self.set_weights(protocol.WeightSnapshot.from_msg(msg))
        if key.startswith(keys.MAP_SUBMAPS + "/"):
            return self.set_submap(protocol.WeightSnapshot.from_msg(msg))
        if key == keys.MAP_INDEX:
            return self.set_index(protocol.SubmapIndex.from_msg(msg))
        if key == keys.MAP_SURFELS:
            return self.set_surfels(protocol.SurfelMap.from_msg(msg))
        raise ValueError(f"not a map key: {key!r}")

    def set_surfels(self, smap: protocol.SurfelMap) -> bool:
        order = (smap.epoch, smap.version)
        if self._surfels is not None and order <= self._surfels[0]:
            return False
        surf = Surfels.from_protocol_dict(smap.surfels)
        with self._lock:
            self._surfels = (order, surf)
            cur = self._state
            if cur is not None and cur.epoch <= smap.epoch:
                self._state = cur.with_surfels(surf, smap.version)
        self.baker.wake()
        return True
