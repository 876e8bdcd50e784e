"""The query engine: the latest map (network + surfels) and the answers to SDF and
mesh requests. No Zenoh here: ``main.py`` wires it to the network, tests drive it
directly.

A new map is built completely aside and then swapped in with one reference
assignment, so a request always sees one consistent map.

The baked field (``aisdf.baked``): for every new map (weights or surfels), a background
thread (``baker.Baker``) bakes the fused field over the observed space the mapper
published; the finished bake is swapped in atomically. ``fused`` requests are answered from the newest bake
(points outside it: the network of the same map, so one reply is one map version); until
a map's first bake is ready, and for ``exact`` requests or the other sources, from the
network of the newest map.

Maps are ordered by ``(epoch, version)``: a restarted mapper (a new epoch) replaces the
map of the one that crashed even though its version counter restarted lower.

Submaps (protocol 1.3): a submap mapper publishes one WeightSnapshot per changed
submap (``map/submaps/<id>``) and an index (``map/index``). The engine keeps per submap
the newest snapshot of the newest epoch (:class:`SubmapSet`); the map's implicit field is
their blend (``aisdf.submaps.field.blend``: each point from the submaps whose extended
boxes hold it, C¹ across their overlaps), its observed space the union of theirs, its
version the newest of the index's and the snapshots'. A new epoch replaces the whole set.
The bake of a new submap map (``baker.py``) reuses every sample of the previous bake
outside what changed, so a bake costs what changed, not the building. Meshes are marched
in tiles of at most ``mesh_tile``³ samples (one sample of overlap, seam vertices welded),
in either mode.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np
import torch

from .. import protocol, query_messages
from ..baked import BakeConfig
from ..collision import chomp_cost
from ..structure.fusion import DEFAULT_FUSE_RADIUS
from ..structure.surfel_types import Surfels
from ..submaps.field import blend
from .answer import predicted_mask, served_answer
from .baker import Baker, BakedMap
from .intake import MapIntake
from .mapstate import MapState, Staleness
from .meshing import tiled_marching_cubes

log = logging.getLogger(__name__)
CPU_PASS = 4096


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class QueryEngine(MapIntake):
    def __init__(self, max_points: int = 1_000_000, chunk_points: int = 65_536, device: str = "auto",
                 fuse_radius: float = DEFAULT_FUSE_RADIUS, mesh_resolution: float = 0.05, mesh_max_cells: int = 16_000_000,
                 bake: bool = True, bake_config: BakeConfig | None = None, bake_threads: int = 2,
                 bake_duty: float = 0.75, bake_nice: int = 0, mesh_tile: int = 64, surfel_tol: float = 0.001,
                 measured: bool = True, fresh_s: float = 2.0, fresh_busy: bool = False):
        self.max_points = max_points
        self.chunk_points = chunk_points
        self.device = pick_device(device)
        # Points per network pass in answers: on a CPU at most CPU_PASS (the activations of a
        # pass with gradients: ~15 MB per 2,048 points at width 128, taken by each worker; the
        # 65,536 of a GPU's pass would hold ~0.5 GB per worker), with no loss of speed.
        self._pass = chunk_points if self.device.type != "cpu" else min(chunk_points, CPU_PASS)
        self.mesh_resolution = mesh_resolution
        self.mesh_max_cells = mesh_max_cells
        if mesh_tile < 2:
            raise ValueError("mesh_tile must be at least 2 samples")
        self.mesh_tile = int(mesh_tile)
        self._index: protocol.SubmapIndex | None = None  # the newest map/index (protocol 1.3)
        self._state: MapState | None = None
        self._surfels: tuple[tuple[int, int], Surfels] | None = None
        self._lock = threading.Lock()  # serialises writers only; readers take the reference
        self.use_measured = bool(measured)  # protocol 1.4: fused answers use the submaps' measured points
        self._stale: tuple | None = None  # ((bake, newest map, added_only), Staleness): the newest pair's
        self.fresh_s = float(fresh_s)  # the bake answers alone while it trails the newest map by at most this
        self.fresh_busy = bool(fresh_busy)  # also while requests wait (else: planners first, the bake answers)
        self.held = 0  # answers from a bake trailing by more than fresh_s because requests were waiting
        self.baker = Baker(self._field, lambda: self._state, self.device, chunk_points, fuse_radius, bake_config,
                           bake_threads, bake_duty, bake_nice, surfel_tol, enabled=bake)
        self.waiting: Callable[[], int] = lambda: 0  # sdf requests waiting for a worker (the service sets it)

    @classmethod
    def from_config(cls, cfg) -> "QueryEngine":
        return cls(cfg.max_points, cfg.chunk_points, cfg.device, cfg.fuse_radius, cfg.mesh_resolution,
                   cfg.mesh_max_cells, cfg.bake,
                   BakeConfig(block=cfg.bake_block, fine=cfg.bake_fine, band=cfg.bake_band, tol=cfg.bake_tol,
                              near_surface=cfg.bake_near_surface), cfg.bake_threads, cfg.bake_duty, cfg.bake_nice,
                   cfg.mesh_tile, cfg.bake_surfel_tol, cfg.measured, cfg.fresh_s, cfg.fresh_busy)._with_layout_prior(
                       cfg.layout_prior)

    def _with_layout_prior(self, on: bool) -> "QueryEngine":
        self.baker.layout_prior = bool(on)  # 1.13 (the baker composes the fused answer for both paths)
        return self

    @property
    def fuse_radius(self) -> float:
        """Surfels within this distance count in fused answers (the baker's, one value for both)."""
        return self.baker.fuse_radius

    # ------------------------------------------------------------------ map updates

    @property
    def state(self) -> MapState | None:
        return self._state

    @property
    def baked(self) -> BakedMap | None:
        return self.baker.baked

    # ------------------------------------------------------------------ baking (baker.py)

    def bake_now(self) -> BakedMap | None:
        """Bake the newest map now (the background baker does it by itself) and swap it in."""
        return self.baker.bake_now()

    def start(self) -> None:
        """Start the background baker (no-op when baking is off)."""
        self.baker.start()

    def stop(self) -> None:
        self.baker.stop()

    def lag(self) -> dict:
        """How far answers trail the newest map (``versions``, ``behind_s``), and the bake
        (``bake_versions``, ``bake_behind_s``). A submap map's answers trail by at most
        ``fresh_s``: beyond it the regions that changed since the bake are answered from the
        newest map (1.7), except for requests answered while others wait for a worker (1.8:
        planners first, the bake answers; counted in ``held``); a one-network map's answers
        trail as its bake does."""
        bake = self.baker.lag()
        st = self._state
        fresh = st is not None and st.submaps is not None and bake["behind_s"] > self.fresh_s
        answers = {"versions": 0, "behind_s": 0.0} if fresh else bake
        return {**answers, "bake_versions": bake["versions"], "bake_behind_s": bake["behind_s"]}

    # ------------------------------------------------------------------ evaluation

    def _implicit(self, net, pts: np.ndarray, gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        sdf = np.empty(len(pts), np.float32)
        grad = np.empty((len(pts), 3), np.float32) if gradient else None
        for i in range(0, len(pts), self._pass):
            x = torch.from_numpy(np.array(pts[i:i + self._pass], dtype=np.float32)).to(self.device)
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
        for i in range(0, len(pts), self._pass):  # bounds blend's per-point bookkeeping
            f, g, _ = blend(sset.grid, evaluators, pts[i:i + self._pass], gradient)
            sdf[i:i + len(f)] = f
            if gradient:
                grad[i:i + len(f)] = g
        return sdf, grad

    def _explicit(self, surfels: Surfels, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from ..structure.surfel_map import explicit_sdf

        d, g, _ = explicit_sdf(pts.astype(np.float64), surfels)
        return d.astype(np.float32), g.astype(np.float32)

    def _network_answer(self, state: MapState, pts: np.ndarray, source: str, gradient: bool):
        has_surfels = state.surfels is not None and len(state.surfels) > 0
        if source == "explicit":
            if not has_surfels:
                raise protocol.ProtocolError("no_map", "no explicit planar map yet (no surfels published)")
            return self._explicit(state.surfels, pts)
        sdf, grad = self._field(state, pts, gradient)
        layout = self.baker.layout(state) if source == "fused" else None
        if source == "fused" and (has_surfels or state.measured is not None or layout is not None):
            d_e, g_e = self._explicit(state.surfels, pts) if has_surfels else (None, None)
            sdf, grad = served_answer(pts, sdf, grad, d_e, g_e, state.measured, self.fuse_radius, layout=layout)
        return sdf, grad

    def answer_sdf(self, req: query_messages.SdfRequest) -> query_messages.SdfReply:
        newest = self._state
        if newest is None:
            raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        if len(req.points) > self.max_points:
            raise protocol.ProtocolError("too_large", f"{len(req.points)} points exceed the limit {self.max_points}")
        pts = req.points
        bk = self.baker.baked
        if req.source == "fused" and not req.exact and bk is not None:
            state = bk.state
            sdf, grad, covered = bk.field.query(pts, req.gradient)
            trails = self._bake_trails(bk)
            if trails and not req.fresh:
                trails = False  # (1.10) the asker takes the bake as it is
            elif trails and not self.fresh_busy and self.waiting() > 0:
                # Planners first: with requests waiting, the changed regions are not evaluated
                # afresh; the bake answers, and the reply says its map's version and age.
                trails = False
                self.held += 1
            stale = self._staleness(bk, newest, added_only=not trails)
            fresh = np.zeros(len(sdf), bool) if stale is None else stale.points(np.asarray(pts))
            # Outside the bake: the network of the same map; in regions the newest map changed
            # since the bake: that map's answer.
            for where, st in ((~covered & ~fresh, bk.state), (fresh, None if stale is None else stale.answer)):
                if where.any():
                    s2, g2 = self._network_answer(st, np.asarray(pts)[where], "fused", req.gradient)
                    sdf[where] = s2
                    if req.gradient:
                        grad[where] = g2
            if stale is not None:
                # the newest map's, up to the bake's accuracy (or within fresh_s the baked map with
                # the space it lacked): version, observed space and age are that map's
                state = stale.answer
            baked = True
        else:
            state = newest
            sdf, grad = self._network_answer(state, pts, req.source, req.gradient)
            baked = False
        predicted = None
        if req.predicted:  # 1.13: where the served distance is (within the bake's tolerance) a predicted point's
            predicted = predicted_mask(self.baker.layout(state) if req.source == "fused" else None, pts, sdf,
                                       self.fuse_radius, self.baker.config.tol if baked else 0.0)
        if req.radii is not None:
            sdf = sdf - req.radii.astype(np.float32)
        coll = None
        if req.collision_epsilon is not None:
            coll = chomp_cost(sdf, req.collision_epsilon).astype(np.float32)
        observed = None
        if req.observed:
            # No observed space from the mapper (a 1.0 mapper): nothing is known to be seen.
            observed = state.observed.contains(pts) if state.observed is not None else np.zeros(len(pts), bool)
        unknown = None
        if req.unknown:  # 1.6: without observed space every point is in unknown space
            self.baker.warm_unknown = True  # the baker builds each new map's index before it answers
            unknown = (state.observed.unknown_distance(pts) if state.observed is not None
                       else np.zeros(len(pts))).astype(np.float32)
            if req.radii is not None:
                unknown = unknown - req.radii.astype(np.float32)
        return query_messages.SdfReply(state.version, sdf.astype(np.float32, copy=False),
                                       grad.astype(np.float32, copy=False) if req.gradient else None, coll, observed,
                                       baked, state.epoch, unknown, round(time.monotonic() - state.received, 3),
                                       req.box, predicted, state.surfel_version)

    def _bake_trails(self, bk: BakedMap) -> bool:
        """Does the bake trail the newest map by more than ``fresh_s`` (since the first newer
        map arrived)? With ``fresh_s`` 0: whenever a newer map arrived."""
        if self.fresh_s <= 0:
            return True
        return self.baker.lag()["behind_s"] > self.fresh_s

    def _staleness(self, bk: BakedMap, newest: MapState, added_only: bool = False) -> "Staleness | None":
        """Which points the bake ``bk`` may answer differently from ``newest`` (a submap map:
        the regions that changed since, or with ``added_only`` the submaps its map does not
        have yet; ``Staleness``), or None when the bake answers for the newest map (the same
        field), or for a one-network map (a new network changes every point: the bake
        answers, and ``map_age_s`` says how old it is)."""
        baked = bk.state
        if baked is newest or newest.submaps is None or baked.same_field(newest):
            return None
        key = (bk, newest, added_only)
        cached = self._stale
        if cached is not None and all(x is y for x, y in zip(cached[0], key)):
            return cached[1]
        st = Staleness.between(baked, newest, self.fuse_radius, added_only, bk.surfel_ref, self.baker.surfel_tol,
                               self.baker.config.block, bk.layout, None if added_only else self.baker.layout(newest))
        self._stale = (key, st)
        return st

    def answer_mesh(self, req: query_messages.MeshRequest) -> query_messages.MeshReply:
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
        return query_messages.MeshReply(state.version, verts.astype(np.float32), faces.astype(np.int32))
