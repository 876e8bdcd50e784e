"""The query engine: the latest map (network + surfels) and the answers to SDF and
mesh requests. No Zenoh here: ``main.py`` wires it to the network, tests drive it
directly.

A new map is built completely aside and then swapped in with one reference
assignment, so a request always sees one consistent map.

The baked field (``aisdf.baked``): for every new map (weights or surfels), a background
thread bakes the fused field over the observed space the mapper published; the finished
bake is swapped in atomically. ``fused`` requests are answered from the newest bake
(points outside it: the network of the same map, so one reply is one map version); until
a map's first bake is ready, and for ``exact`` requests or the other sources, from the
network of the newest map.

Maps are ordered by ``(epoch, version)``: a restarted mapper (a new epoch) replaces the
map of the one that crashed even though its version counter restarted lower.

Submaps (protocol 1.3, issue 7): a submap mapper publishes one WeightSnapshot per changed
submap (``map/submaps/<id>``) and an index (``map/index``). The engine keeps per submap
the newest snapshot of the newest epoch (:class:`SubmapSet`); the map's implicit field is
their blend (``aisdf.submaps.field.blend``: each point from the submaps whose extended
boxes hold it, C¹ across their overlaps), its observed space the union of theirs, its
version the newest of the index's and the snapshots'. A new epoch replaces the whole set.
The bake of a new submap map reuses every sample of the previous bake outside the
extended boxes of the submaps that changed (and away from surfels that changed), so a
bake costs what changed, not the building. Meshes are marched in tiles of at most
``mesh_tile``³ samples (one sample of overlap, seam vertices welded), in either mode.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from aisdf import protocol
from aisdf.baked import BakeConfig, BakedField, bake
from aisdf.collision import chomp_cost
from aisdf.structure.fusion import DEFAULT_FUSE_RADIUS, fuse
from aisdf.network import build_model, load_numpy_state
from aisdf.observed import ObservedGrid
from aisdf.submaps.field import assign, blend
from aisdf.submaps.grid import SubmapGrid, parse_cell_id
from aisdf.structure.surfel_types import Surfels

from .changes import in_boxes, surfel_changes
from .mapstate import MapState, Submap, SubmapSet, union_observed
from .meshing import tiled_marching_cubes

log = logging.getLogger(__name__)
BAKE_CHUNK = 2048  # network points per pass while baking: bounds the activations (~15 MB at width 128)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@dataclass(frozen=True)
class BakedMap:
    state: MapState  # the map it was baked from (its network answers points outside the bake)
    field: BakedField
    surfel_ref: Surfels | None = None  # the surfels its samples were computed with (within bake_surfel_tol)


class QueryEngine:
    def __init__(self, max_points: int = 1_000_000, chunk_points: int = 65_536, device: str = "auto",
                 fuse_radius: float = DEFAULT_FUSE_RADIUS, mesh_resolution: float = 0.05, mesh_max_cells: int = 16_000_000,
                 bake: bool = True, bake_config: BakeConfig | None = None, bake_threads: int = 2,
                 bake_duty: float = 0.75, bake_nice: int = 10, mesh_tile: int = 64, surfel_tol: float = 0.001):
        self.max_points = max_points
        self.chunk_points = chunk_points
        self.device = pick_device(device)
        self.fuse_radius = fuse_radius
        self.mesh_resolution = mesh_resolution
        self.mesh_max_cells = mesh_max_cells
        if mesh_tile < 2:
            raise ValueError("mesh_tile must be at least 2 samples")
        self.mesh_tile = int(mesh_tile)
        self.surfel_tol = float(surfel_tol)
        self._index: protocol.SubmapIndex | None = None  # the newest map/index (protocol 1.3)
        self.bake_enabled = bake
        self.bake_config = bake_config or BakeConfig()
        self.bake_threads = bake_threads
        self.bake_duty = bake_duty
        self.bake_nice = bake_nice
        self._state: MapState | None = None
        self._surfels: tuple[tuple[int, int], Surfels] | None = None
        self._baked: BakedMap | None = None
        self._lock = threading.Lock()  # serialises writers only; readers take the reference
        self._bake_wanted = threading.Event()
        self._stop = threading.Event()
        self._baker: threading.Thread | None = None
        self.bakes = 0
        self.bake_failures = 0
        self.last_bake: dict = {}
        self._arrivals: deque = deque(maxlen=256)  # ((epoch, version), monotonic arrival) of weights

    @classmethod
    def from_config(cls, cfg) -> "QueryEngine":
        return cls(cfg.max_points, cfg.chunk_points, cfg.device, cfg.fuse_radius, cfg.mesh_resolution,
                   cfg.mesh_max_cells, cfg.bake,
                   BakeConfig(block=cfg.bake_block, fine=cfg.bake_fine, band=cfg.bake_band, tol=cfg.bake_tol,
                              near_surface=cfg.bake_near_surface), cfg.bake_threads, cfg.bake_duty, cfg.bake_nice,
                   cfg.mesh_tile, cfg.bake_surfel_tol)

    # ------------------------------------------------------------------ map updates

    @property
    def state(self) -> MapState | None:
        return self._state

    @property
    def baked(self) -> BakedMap | None:
        return self._baked

    def set_weights(self, snap: protocol.WeightSnapshot) -> bool:
        """Build the network of a snapshot and swap it in; False if it is not newer (by
        (epoch, version)). Raises ValueError on a snapshot that cannot be loaded (the old map stays)."""
        order = (snap.epoch, snap.version)
        cur = self._state
        if cur is not None and order <= cur.order:
            return False
        net, bounds, observed = self._load(snap)
        with self._lock:
            cur = self._state
            if cur is not None and order <= cur.order:
                return False
            sv, surf = self._surfels if self._surfels else ((0, -1), None)
            if sv[0] < snap.epoch:  # surfels of an older mapper incarnation: not this map's
                surf, sv = None, (0, -1)
            self._state = MapState(snap.version, snap.step, net, bounds, surf, sv[1], snap.epoch, observed)
            self._arrivals.append((order, self._state.received))
        self._bake_wanted.set()
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
    def _submap_newer(cur: MapState | None, epoch: int, version: int, cell) -> bool:
        if cur is None:
            return True
        if cur.submaps is None:  # a single network: the newer map wins, as between weights
            return (epoch, version) > cur.order
        if epoch != cur.epoch:
            return epoch > cur.epoch
        held = cur.submaps.submaps.get(cell)
        return held is None or version > held.version

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
        if not self._submap_newer(self._state, snap.epoch, snap.version, cell):
            return False
        net, bounds, observed = self._load(snap)
        with self._lock:
            cur = self._state
            if not self._submap_newer(cur, snap.epoch, snap.version, cell):
                return False
            if cur is not None and cur.submaps is not None and cur.epoch == snap.epoch:
                if not cur.submaps.grid.same_as(grid):
                    raise ValueError(f"submap {sid}: its grid differs from the grid of this mapper's other submaps")
                grid, subs, version = cur.submaps.grid, dict(cur.submaps.submaps), cur.version
            else:  # the first submap, or a new mapper incarnation: a new set
                subs, version = {}, snap.version
            subs[cell] = Submap(cell, snap.version, snap.step, net, observed, bounds)
            idx = self._index
            if idx is not None and idx.epoch == snap.epoch and self._complete(subs, idx):
                version = max(version, idx.version)
            self._state = self._submap_state(SubmapSet(grid, subs), max(version, snap.version), snap.epoch, cur)
            self._arrivals.append((self._state.order, self._state.received))
        self._bake_wanted.set()
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
        subs = list(sset.submaps.values())
        observed = union_observed([s.observed for s in subs], self.bake_config.block)
        boxes = [s.bounds for s in subs if s.bounds is not None]
        if observed is not None:  # what was seen (a submap's bounds are its whole extended box)
            bounds = observed.bounds
        elif boxes:
            bounds = np.stack([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)])
        else:  # the extended boxes of the submaps
            corners = np.concatenate([sset.grid.corners_W(s.cell, sset.grid.overlap_m) for s in subs])
            bounds = np.stack([corners.min(0), corners.max(0)])
        sv, surf = self._surfels if self._surfels else ((0, -1), None)
        if sv[0] < epoch:  # surfels of an older mapper incarnation: not this map's
            surf, sv = None, (0, -1)
        return MapState(version, sum(s.step for s in subs), None, bounds, surf, sv[1], epoch, observed,
                        submaps=sset)

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
            if cur is None or idx.epoch > cur.epoch or (cur.submaps is None and (idx.epoch, idx.version) > cur.order):
                return None
            if cur.submaps is None or idx.epoch < cur.epoch:
                return []
            subs = cur.submaps.submaps
            want = [sid for sid, v in idx.submaps.items()
                    if subs.get(parse_cell_id(sid)) is None or subs[parse_cell_id(sid)].version < v["version"]]
            if not want and idx.version > cur.version:
                self._state = MapState(idx.version, cur.step, None, cur.bounds, cur.surfels, cur.surfel_version,
                                       cur.epoch, cur.observed, submaps=cur.submaps)
                self._arrivals.append((self._state.order, self._state.received))
                self._bake_wanted.set()
        return want

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
        self._bake_wanted.set()
        return True

    # ------------------------------------------------------------------ baking

    def fused_fn(self, state: MapState, chunk: int | None = None):
        """points (M, 3) -> (sdf, grad) of the fused field of ``state`` (what ``fused``
        answers), in bounded memory: the network in chunks of ``chunk`` points, the
        surfels in chunks of candidate pairs."""
        from aisdf.structure.surfel_map import ExplicitSdf

        chunk = chunk or (BAKE_CHUNK if self.device.type == "cpu" else self.chunk_points)  # on a GPU: big batches
        explicit = ExplicitSdf(state.surfels, chunk_pairs=131_072) if state.surfels is not None and len(
            state.surfels) else None

        def fn(pts: np.ndarray):
            sdf = np.empty(len(pts), np.float32)
            grad = np.empty((len(pts), 3), np.float32)

            def one(i: int) -> None:
                sdf[i:i + chunk], grad[i:i + chunk] = self._field(state, pts[i:i + chunk], True)

            starts = range(0, len(pts), chunk)
            if self.bake_threads > 1 and self.device.type == "cpu" and len(starts) > 1:
                # torch releases the GIL inside its ops: chunks run side by side.
                with ThreadPoolExecutor(self.bake_threads, thread_name_prefix="bake",
                                        initializer=self._lower_priority if self._on_baker() else None) as ex:
                    list(ex.map(one, starts))
            else:
                for i in starts:
                    one(i)
            if explicit is not None:
                d_e, g_e, _ = explicit(pts.astype(np.float64))
                sdf, grad, _ = fuse(sdf, grad, d_e.astype(np.float32), g_e.astype(np.float32), self.fuse_radius)
            return sdf, grad

        return fn

    def bake_now(self) -> BakedMap | None:
        """Bake the newest map (if it has observed space and is not baked yet) and swap it in."""
        st = self._state
        if st is None or st.observed is None:
            return self._baked
        cur = self._baked
        if cur is not None and cur.state.same_field(st):
            # Nothing to evaluate (the index's version moved on): the same bake answers for it.
            if cur.state.order != st.order or cur.state.surfel_version != st.surfel_version:
                with self._lock:
                    if self._baked is cur:
                        self._baked = BakedMap(st, cur.field)
            return self._baked
        t = time.perf_counter()
        dirty, ref = self._dirty(cur, st) if cur is not None else (None, st.surfels)
        previous = cur.field if dirty is not None else None
        if dirty is None:
            ref = st.surfels
        fld = bake(self.fused_fn(st), st.observed, self.bake_config, previous=previous, dirty=dirty)
        with self._lock:
            cur = self._baked
            if cur is None or cur.state.order <= st.order:
                self._baked = BakedMap(st, fld, ref)
        self.bakes += 1
        self.last_bake = {**fld.stats, "wall_s": round(time.perf_counter() - t, 3), "version": st.version,
                          "epoch": st.epoch}
        log.info("baked map version %d: %d blocks (%d fine), %d evaluations (%d reused), %.2f s, %.1f MB",
                 st.version, fld.stats["blocks"], fld.stats["fine_blocks"], fld.stats["evaluations"],
                 fld.stats["reused"], self.last_bake["wall_s"], fld.nbytes / 1e6)
        return self._baked

    def _dirty(self, baked: BakedMap, new: MapState):
        """Where the fused field of ``new`` may differ from the samples of ``baked``: (a
        function of world points (M, 3) -> (M,) bool, or None when it may differ everywhere
        (a new network, a new mapper incarnation or grid); the new surfel reference). The
        blend at a point depends only on the submaps whose extended boxes hold it; the fused
        answer only on surfels within ``fuse_radius`` (surfels that moved less than
        ``surfel_tol``, as all do a little when the Atlanta frame is refined, count as unchanged)."""
        old = baked.state
        if (old.submaps is None) != (new.submaps is None) or old.epoch != new.epoch:
            return None, new.surfels
        if new.submaps is None:
            if old.net is not new.net:
                return None, new.surfels
            changed, grid, cells = [], None, None
        else:
            if not old.submaps.grid.same_as(new.submaps.grid):
                return None, new.surfels
            changed, grid, cells = new.submaps.changed_since(old.submaps), new.submaps.grid, set(new.submaps.submaps)
        boxes, ref = surfel_changes(baked.surfel_ref, new.surfels, self.surfel_tol)
        grow = self.fuse_radius + 0.05

        def dirty(points: np.ndarray) -> np.ndarray:
            d = in_boxes(points, boxes, grow)
            if grid is not None:
                covered = np.zeros(len(points), bool)
                for idx in assign(grid, cells, points).values():
                    covered[idx] = True
                d |= ~covered  # answered by the nearest submap: depends on the whole set
                for idx in assign(grid, changed, points).values():
                    d[idx] = True
            return d

        return dirty, ref

    def _lower_priority(self) -> None:
        """Bake with a lower CPU priority (Linux nice is per thread): a mapper or the answers
        on the same machine go first, the bake takes what is left."""
        if self.bake_nice and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.bake_nice)
            except OSError as e:  # not permitted, or not Linux: bake at normal priority
                log.debug("could not lower the baker's priority: %s", e)

    def _bake_loop(self) -> None:
        self._lower_priority()
        while not self._stop.is_set():
            if not self._bake_wanted.wait(0.5):
                continue
            self._bake_wanted.clear()
            t = time.monotonic()
            try:
                self.bake_now()
            except Exception:  # noqa: BLE001 - keep answering from the last good bake / the network
                self.bake_failures += 1
                log.exception("bake failed; answers keep coming from the previous bake or the network")
            # Bake at most bake_duty of the time: with weights every second, rest a third of
            # the bake's time (at 0.75), leaving some of the machine to the mapper and the answers.
            took = time.monotonic() - t
            self._stop.wait(took * (1.0 / self.bake_duty - 1.0))

    def start(self) -> None:
        """Start the background baker (no-op when baking is off)."""
        if self.bake_enabled and self._baker is None:
            self._baker = threading.Thread(target=self._bake_loop, name="baker", daemon=True)
            self._baker.start()

    def stop(self) -> None:
        self._stop.set()
        if self._baker is not None:
            self._baker.join(timeout=30)

    def _on_baker(self) -> bool:
        return self._baker is not None and threading.current_thread() is self._baker

    def lag(self) -> dict:
        """How far answers trail the newest weights, now: ``versions`` behind, and ``behind_s``:
        seconds since the first weights newer than the answering ones arrived (0 when the
        newest map answers)."""
        st, bk = self._state, self._baked
        if st is None:
            return {"versions": 0, "behind_s": 0.0}
        if bk is None or bk.state.order >= st.order:
            return {"versions": 0, "behind_s": 0.0}
        newer = [(o, t) for o, t in list(self._arrivals) if o > bk.state.order]
        first = min(t for _, t in newer) if newer else st.received
        return {"versions": len(newer), "behind_s": round(time.monotonic() - first, 3)}

    # ------------------------------------------------------------------ evaluation

    def _implicit(self, net, pts: np.ndarray, gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        sdf = np.empty(len(pts), np.float32)
        grad = np.empty((len(pts), 3), np.float32) if gradient else None
        for i in range(0, len(pts), self.chunk_points):
            x = torch.from_numpy(np.array(pts[i:i + self.chunk_points], dtype=np.float32)).to(self.device)
            if gradient:
                with torch.enable_grad():
                    x.requires_grad_(True)
                    f = net(x).reshape(-1)
                    (g,) = torch.autograd.grad(f.sum(), x)
                grad[i:i + len(x)] = g.detach().cpu().numpy()
            else:
                with torch.inference_mode():
                    f = net(x).reshape(-1)
            sdf[i:i + len(x)] = f.detach().cpu().numpy()
        return sdf, grad

    def _field(self, state: MapState, pts: np.ndarray, gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The map's implicit field: its network, or the blend of its submaps."""
        if state.submaps is None:
            return self._implicit(state.net, pts, gradient)
        sset = state.submaps
        evaluators = {c: (lambda q, g, net=sm.net: self._implicit(net, q, g)) for c, sm in sset.submaps.items()}
        pts = np.asarray(pts).reshape(-1, 3)
        sdf = np.empty(len(pts), np.float32)
        grad = np.empty((len(pts), 3), np.float32) if gradient else None
        for i in range(0, len(pts), self.chunk_points):  # bounds blend's per-point bookkeeping
            f, g, _ = blend(sset.grid, evaluators, pts[i:i + self.chunk_points], gradient)
            sdf[i:i + len(f)] = f
            if gradient:
                grad[i:i + len(f)] = g
        return sdf, grad

    def _explicit(self, surfels: Surfels, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from aisdf.structure.surfel_map import explicit_sdf

        d, g, _ = explicit_sdf(pts.astype(np.float64), surfels)
        return d.astype(np.float32), g.astype(np.float32)

    def _network_answer(self, state: MapState, pts: np.ndarray, source: str, gradient: bool):
        has_surfels = state.surfels is not None and len(state.surfels) > 0
        if source == "explicit":
            if not has_surfels:
                raise protocol.ProtocolError("no_map", "no explicit planar map yet (no surfels published)")
            return self._explicit(state.surfels, pts)
        sdf, grad = self._field(state, pts, gradient)
        if source == "fused" and has_surfels:
            d_e, g_e = self._explicit(state.surfels, pts)
            sdf, grad, _ = fuse(sdf, grad, d_e, g_e, self.fuse_radius)
        return sdf, grad

    def answer_sdf(self, req: protocol.SdfRequest) -> protocol.SdfReply:
        newest = self._state
        if newest is None:
            raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        if len(req.points) > self.max_points:
            raise protocol.ProtocolError("too_large", f"{len(req.points)} points exceed the limit {self.max_points}")
        pts = req.points
        bk = self._baked
        if req.source == "fused" and not req.exact and bk is not None:
            state = bk.state
            sdf, grad, covered = bk.field.query(pts, req.gradient)
            if not covered.all():  # outside the bake: the network of the same map
                out = ~covered
                s2, g2 = self._network_answer(state, np.asarray(pts)[out], "fused", req.gradient)
                sdf[out] = s2
                if req.gradient:
                    grad[out] = g2
            baked = True
        else:
            state = newest
            sdf, grad = self._network_answer(state, pts, req.source, req.gradient)
            baked = False
        if req.radii is not None:
            sdf = sdf - req.radii.astype(np.float32)
        coll = None
        if req.collision_epsilon is not None:
            coll = chomp_cost(sdf, req.collision_epsilon).astype(np.float32)
        observed = None
        if req.observed:
            # No observed space from the mapper (a 1.0 mapper): nothing is known to be seen.
            observed = state.observed.contains(pts) if state.observed is not None else np.zeros(len(pts), bool)
        return protocol.SdfReply(state.version, sdf.astype(np.float32, copy=False),
                                 grad.astype(np.float32, copy=False) if req.gradient else None, coll, observed,
                                 baked, state.epoch)

    def answer_mesh(self, req: protocol.MeshRequest) -> protocol.MeshReply:
        state = self._state
        if state is None:
            raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        if state.bounds is None:
            raise protocol.ProtocolError("no_map", "the map carries no bounds yet (no keyframe observed)")
        res = req.resolution or self.mesh_resolution
        lo, hi = state.bounds[0] - 2 * res, state.bounds[1] + 2 * res
        n = np.maximum(np.ceil((hi - lo) / res).astype(int) + 1, 2)
        if int(np.prod(n)) > self.mesh_max_cells:
            raise protocol.ProtocolError(
                "too_large", f"resolution {res} m needs a {n[0]}x{n[1]}x{n[2]} grid, above {self.mesh_max_cells} cells; "
                "ask for a coarser resolution")
        verts, faces = tiled_marching_cubes(lambda p: self._field(state, p, False)[0], lo, res, n, self.mesh_tile)
        return protocol.MeshReply(state.version, verts.astype(np.float32), faces.astype(np.int32))
