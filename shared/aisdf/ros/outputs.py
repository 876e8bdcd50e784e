"""``aisdf ros2``: the map for ROS 2, over rmw_zenoh: a node (``aisdf`` by default) publishing

* ``/aisdf/occupancy_grid`` (``nav_msgs/OccupancyGrid``, reliable, transient local, depth 1,
  as Nav2's map server): the height band above the floor sliced from the SDF
  (:mod:`aisdf.ros.slices`), refreshed at ``rate_hz`` where the map changed;
* ``/aisdf/esdf_pointcloud`` (``sensor_msgs/PointCloud2``): the same slice's clearance per
  observed column, ``x y z intensity`` as nvblox's ``static_esdf_pointcloud``;
* ``/aisdf/surfels`` (``visualization_msgs/MarkerArray``, transient local): one cube per
  planar surfel, coloured by Atlanta direction, whenever the surfel map changes;
* ``/aisdf/mesh`` (``visualization_msgs/Marker``, triangle list, transient local): the zero
  level set every ``mesh_period_s`` (30 s) while the map changes, on its own thread;

and serving the ROS 2 services of :mod:`aisdf.ros.outputs_services` (the distance window,
save and load). :mod:`aisdf.ros.outputs_main` runs both as ``aisdf ros2``. It is a client of the AiSDF protocol like any planner: it asks the query
service (``query/sdf``, ``query/mesh``) and follows ``map/surfels`` and ``map/index``.

**Where the map changed.** The grid is kept in tiles of ``tile`` x ``tile`` columns anchored
in the ground plane. Each tick a one-point request tells the map version; when it moved, the
tiles a changed submap's extended box (from ``map/index``, grown by ``fuse_margin_m``) covers
are sampled again, and new tiles as the map grows. With a one-network map, a new mapper
incarnation or a moved floor every tile is; and every ``full_refresh_s`` all of them, for
what the index does not show (surfels and measured points near a changed submap).
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
from pydantic import Field
from scipy import ndimage

from .. import keys, protocol, query_messages, transport
from ..config import ServiceConfig
from ..submaps.grid import SubmapGrid, parse_cell_id
from . import outmsgs, slices
from . import rmw_zenoh as rz

log = logging.getLogger("aisdf.ros.outputs")
COARSE = 2  # the coarse pass samples every other column (10 cm at 5 cm cells: the observed voxels)
CHUNK = 500_000  # points per request (the query service refuses more than max_points, 1,000,000 by default)


class Ros2OutputsConfig(ServiceConfig):
    """Settings of ``aisdf ros2``."""

    ros_connect: list[str] = Field(default_factory=lambda: [rz.DEFAULT_ROUTER],
                                   description="Zenoh router(s) of the ROS 2 network (rmw_zenoh's default)")
    ros_zenoh_config: Path | None = Field(None, description="Zenoh session file for the ROS side "
                                          "(as ZENOH_SESSION_CONFIG_URI)")
    domain_id: int = Field(default_factory=rz.domain_from_env, ge=0, le=232, description="ROS_DOMAIN_ID")
    distro: str = Field("jazzy", description="ROS 2 distribution: message definitions and type hashes")
    node_name: str = Field("aisdf", description="the node's name; topics are /<node>/... under the namespace")
    ros_namespace: str = Field("/", description="the node's namespace")
    frame_id: str = Field("map", description="the fixed frame of the keyframes' poses (the messages' frame)")
    resolution: float = Field(0.05, gt=0, description="grid cell (m)")
    band: tuple[float, float] = Field((0.1, 1.0), description="heights above the floor sliced (m)")
    robot_radius: float = Field(0.2, ge=0, description="occupied where the clearance is below this (m)")
    floor_height: float | None = Field(None, description="the floor's height along up; None: from the surfels")
    up: tuple[float, float, float] | None = Field(None, description="the world's up direction; None: +z when the "
                                                  "Atlanta vertical is within 30 degrees of z, else from the surfels")
    rate_hz: float = Field(1.0, gt=0, description="how often the grid and the slice are refreshed")
    tile: int = Field(64, ge=4, multiple_of=2, description="columns per tile side (tiles are re-sampled where the map changed)")
    fuse_margin_m: float = Field(0.3, ge=0, description="a changed submap's box grown by this (fused answers)")
    full_refresh_s: float = Field(30.0, gt=0, description="every tile re-sampled at least this often")
    mesh_period_s: float = Field(30.0, gt=0, description="how often the mesh is published while the map changes "
                                 "(on its own thread: a floor's takes seconds)")
    mesh_resolution: float = Field(0.1, gt=0, description="the mesh's marching-cubes resolution (m)")
    map_dir: Path = Field(Path("maps"), description="where /aisdf/save_map writes and /aisdf/load_map reads")
    timeout_s: float = Field(30.0, gt=0, description="timeout of requests to the query service")


class MapOutputs:
    """The node's work, on an open AiSDF session and a :class:`rz.Node`."""

    def __init__(self, cfg: Ros2OutputsConfig, session, node: rz.Node):
        self.cfg, self.session, self.node, self.ts = cfg, session, node, node.typestore
        latched = rz.QoS(durability=rz.TRANSIENT_LOCAL, depth=1)
        base = cfg.node_name
        self.pub_grid = node.create_publisher(f"{base}/occupancy_grid", "nav_msgs/msg/OccupancyGrid", latched)
        self.pub_cloud = node.create_publisher(f"{base}/esdf_pointcloud", "sensor_msgs/msg/PointCloud2",
                                               rz.QoS(depth=1))
        self.pub_surfels = node.create_publisher(f"{base}/surfels", "visualization_msgs/msg/MarkerArray", latched)
        self.pub_mesh = node.create_publisher(f"{base}/mesh", "visualization_msgs/msg/Marker", latched)
        self._lock = threading.Lock()
        self.surfel_map: protocol.SurfelMap | None = None
        self.index: protocol.SubmapIndex | None = None
        self._index_seen: dict[str, int] = {}  # submap id -> version at the last grid
        self.ground: slices.Ground | None = None
        self.tiles: dict[tuple[int, int], slices.Slice] = {}
        self.version: tuple | None = None  # (epoch, version) of the last grid's map, and its surfel map's
        self._surfels_sent: tuple[int, int] | None = None
        self._mesh_sent: tuple[int, int] | None = None
        self._last_full = self._last_mesh = 0.0
        self.counts = {"grids": 0, "tiles": 0, "clouds": 0, "surfel_maps": 0, "meshes": 0, "errors": 0}
        self.last_grid: np.ndarray | None = None
        self.took: dict[str, float] = {}  # seconds the last publication of each took
        self.mesh_times: list[float] = []  # seconds each mesh of the mesh thread took
        self.baked: tuple | None = None  # (epoch, version, surfel version) the bake answers for, at the last tick
        self._decls = [self._follow(keys.MAP_SURFELS, self._on_surfels), self._follow(keys.MAP_INDEX, self._on_index)]

    # ------------------------------------------------------------------ following the map

    def _follow(self, name: str, fn):
        def cb(sample):
            try:
                fn(protocol.unpack(transport.payload_bytes(sample.payload)))
            except (protocol.ProtocolError, ValueError, KeyError, TypeError) as e:
                log.warning("skipping a malformed message on %s: %s", name, e)

        return self.session.declare_subscriber(keys.key(self.cfg.namespace, name), cb)

    def _on_surfels(self, msg) -> None:
        sm = protocol.SurfelMap.from_msg(msg)
        with self._lock:
            if self.surfel_map is None or (sm.epoch, sm.version) >= (self.surfel_map.epoch, self.surfel_map.version):
                self.surfel_map = sm

    def _on_index(self, msg) -> None:
        idx = protocol.SubmapIndex.from_msg(msg)
        with self._lock:
            if self.index is None or (idx.epoch, idx.version) >= (self.index.epoch, self.index.version):
                self.index = idx

    def _catch_up(self) -> None:
        """A late joiner: the latest surfel map and index with a get."""
        for name, fn in ((keys.MAP_SURFELS, self._on_surfels), (keys.MAP_INDEX, self._on_index)):
            msg = transport.get_latest(self.session, keys.key(self.cfg.namespace, name), timeout=1.0)
            if msg is not None:
                try:
                    fn(msg)
                except (protocol.ProtocolError, ValueError, KeyError, TypeError) as e:
                    log.warning("skipping a malformed %s: %s", name, e)

    def _ask(self, req: query_messages.SdfRequest) -> query_messages.SdfReply:
        msg = transport.query(self.session, keys.key(self.cfg.namespace, keys.QUERY_SDF), req.to_msg(),
                              self.cfg.timeout_s)
        return query_messages.SdfReply.from_msg(msg)

    def _sample(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sdf, observed) at grid points ``g``, from the bake as it is (protocol 1.10's fresh:
        false: a grid a few seconds old costs the query service a lookup per sample instead of
        the newest networks' evaluation), in requests of at most ``CHUNK`` points."""
        pts = self.ground.to_world(g).astype(np.float32)
        sdf, obs = [], []
        for i in range(0, len(pts), CHUNK):
            rep = self._ask(query_messages.SdfRequest(pts[i:i + CHUNK], observed=True, fresh=False))
            sdf.append(rep.sdf)
            obs.append(rep.observed)
        return np.concatenate(sdf), np.concatenate(obs)

    # ------------------------------------------------------------------ the grid

    def _tile_range(self) -> tuple[np.ndarray, np.ndarray] | None:
        ext = slices.surfel_extent(self.ground, self.surfel_map.surfels)
        if ext is None:
            return None
        span = self.cfg.tile * self.cfg.resolution
        return np.floor(ext[0] / span).astype(int), np.floor(ext[1] / span).astype(int)

    def _changed_tiles(self, idx: protocol.SubmapIndex | None) -> set[tuple[int, int]]:
        """Tiles a submap whose version moved since the last grid covers."""
        if idx is None:
            return set()
        grid = SubmapGrid.from_msg(idx.grid)
        span = self.cfg.tile * self.cfg.resolution
        out: set[tuple[int, int]] = set()
        for sid, meta in idx.submaps.items():
            if self._index_seen.get(sid) == int(meta["version"]):
                continue
            g = self.ground.to_grid(grid.corners_W(parse_cell_id(sid), grow=grid.overlap_m + self.cfg.fuse_margin_m))
            lo, hi = np.floor(g[:, :2].min(0) / span).astype(int), np.floor(g[:, :2].max(0) / span).astype(int)
            out.update((i, j) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1))
        return out

    def sample_tile(self, t: tuple[int, int]) -> slices.Slice:
        """The band over one tile's columns, from the query service: a coarse pass (every
        ``COARSE``-th column, every height) finds the observed columns, then one request
        samples the columns within a coarse cell of them at every height. Columns far from
        observed space are unobserved without asking (the bake does not cover them: each of
        their samples would cost a network evaluation)."""
        cfg, T = self.cfg, self.cfg.tile
        levels = slices.band_levels(cfg.band, cfg.resolution)
        cols = np.stack(np.meshgrid(t[0] * T + np.arange(T), t[1] * T + np.arange(T), indexing="ij"), -1)
        C = COARSE
        coarse = cols[C // 2::C, C // 2::C]
        lv = levels
        g = np.concatenate([np.repeat(coarse.reshape(-1, 2) * cfg.resolution, len(lv), 0),
                            np.tile(lv, coarse.shape[0] * coarse.shape[1])[:, None]], axis=1)
        _, coarse_seen = self._sample(g)
        seen = ndimage.binary_dilation(coarse_seen.reshape(*coarse.shape[:2], len(lv)).any(-1),
                                       structure=np.ones((3, 3), bool))
        want = np.repeat(np.repeat(seen, C, 0), C, 1)[:T, :T]
        obstacle, observed = np.zeros((T, T), bool), np.zeros((T, T), bool)
        if not want.any():
            return slices.Slice(obstacle, observed)
        ij = cols[want]
        g = np.concatenate([np.repeat(ij * cfg.resolution, len(levels), 0),
                            np.tile(levels, len(ij))[:, None]], axis=1)
        sdf, obs = self._sample(g)
        sl = slices.slice_columns(sdf.reshape(len(ij), len(levels)), obs.reshape(len(ij), len(levels)), cfg.resolution)
        obstacle[want], observed[want] = sl.obstacle, sl.observed
        return slices.Slice(obstacle, observed)

    def probe(self) -> tuple:
        """(epoch, version, surfel version) of the map behind the bake's answers (one point,
        fresh: false). The surfel version (protocol 1.19; None from an older query service)
        moves on its own when surfels that reached this node before the query service are
        baked under the same map version."""
        rep = self._ask(query_messages.SdfRequest(np.zeros((1, 3), np.float32), fresh=False))
        return rep.map_epoch, rep.map_version, rep.surfel_version

    def refresh_grid(self, now: float, baked: tuple) -> bool:
        """Re-sample what changed and publish the grid and the slice; True when published.
        ``baked``: the (epoch, version, surfel version) the bake answers for (:meth:`probe`)."""
        with self._lock:
            smap, idx = self.surfel_map, self.index
        if smap is None:
            return False
        ground = slices.ground_from_surfels(smap.vertical, smap.surfels, self.cfg.floor_height, self.cfg.up)
        if ground.height is None:
            log.info("no floor in the surfel map yet: no occupancy grid")
            return False
        # a new surfel map changes fused answers near the surfels that moved: it counts as a
        # change, left to the submaps that changed with it and to the periodic refresh
        version = (*baked, smap.epoch, smap.version)
        moved = (self.ground is None or not np.allclose(ground.R, self.ground.R, atol=1e-3)
                 or abs(ground.height - self.ground.height) > self.cfg.resolution / 2)
        epoch = self.version is None or version[0] != self.version[0]
        if moved or epoch:
            self.ground, self.tiles, self._index_seen = ground, {}, {}
        rng = self._tile_range()
        if rng is None:
            return False
        lo, hi = rng
        wanted = {(a, b) for a in range(lo[0], hi[0] + 1) for b in range(lo[1], hi[1] + 1)}
        new = version != self.version
        if moved or (new and (epoch or idx is None or now - self._last_full >= self.cfg.full_refresh_s)):
            dirty = wanted  # everything: a new incarnation, one network, the floor moved, or the periodic refresh
            self._last_full = now
        else:
            dirty = (wanted - set(self.tiles)) | (self._changed_tiles(idx) & wanted if new else set())
        if not dirty and not new:
            return False
        for t in sorted(dirty):
            self.tiles[t] = self.sample_tile(t)
        self.counts["tiles"] += len(dirty)
        # The submaps count as sampled only once the bake answers for the index's map: until
        # then the tiles held the bake's older values, and its catching up re-samples them.
        # (The same for the surfel map this node holds: their fused answers near moved surfels.)
        surfels_baked = len(baked) < 3 or baked[2] is None or baked[2] >= smap.version
        if idx is not None and idx.epoch == baked[0] and baked[1] >= idx.version and surfels_baked:
            self._index_seen = {sid: int(m["version"]) for sid, m in idx.submaps.items()}
        self.version = version
        self.publish_grid(lo, hi)
        return True

    def assemble(self, lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(obstacle, observed, origin_xy) over tiles lo..hi (missing tiles: unobserved)."""
        T = self.cfg.tile
        nx, ny = (hi[0] - lo[0] + 1) * T, (hi[1] - lo[1] + 1) * T
        obstacle, observed = np.zeros((nx, ny), bool), np.zeros((nx, ny), bool)
        for (a, b), s in self.tiles.items():
            if lo[0] <= a <= hi[0] and lo[1] <= b <= hi[1]:
                x, y = (a - lo[0]) * T, (b - lo[1]) * T
                obstacle[x:x + T, y:y + T], observed[x:x + T, y:y + T] = s.obstacle, s.observed
        return obstacle, observed, np.array([lo[0] * T, lo[1] * T]) * self.cfg.resolution

    def publish_grid(self, lo, hi) -> None:
        cfg = self.cfg
        obstacle, observed, origin = self.assemble(lo, hi)
        grid, clear = slices.occupancy(obstacle, observed, cfg.resolution, cfg.robot_radius)
        stamp = time.time_ns()
        self.pub_grid.publish(outmsgs.occupancy_grid(self.ts, grid, self.ground, origin, cfg.resolution,
                                                     cfg.frame_id, stamp))
        self.last_grid = grid
        self.counts["grids"] += 1
        ij = np.argwhere(observed)
        g = np.concatenate([origin + ij * cfg.resolution, np.full((len(ij), 1), cfg.band[0])], axis=1)
        d = np.minimum(clear[observed], 1e3)
        self.pub_cloud.publish(outmsgs.distance_cloud(self.ts, self.ground.to_world(g), d, cfg.frame_id, stamp))
        self.counts["clouds"] += 1

    # ------------------------------------------------------------------ surfels and mesh

    def publish_surfels(self) -> bool:
        with self._lock:
            sm = self.surfel_map
        if sm is None or self._surfels_sent == (sm.epoch, sm.version):
            return False
        self.pub_surfels.publish(outmsgs.surfel_markers(self.ts, sm.surfels, self.cfg.frame_id, time.time_ns()))
        self._surfels_sent = (sm.epoch, sm.version)
        self.counts["surfel_maps"] += 1
        return True

    def publish_mesh(self, now: float, baked: tuple) -> bool:
        if baked == self._mesh_sent or now - self._last_mesh < self.cfg.mesh_period_s:
            return False
        msg = transport.query(self.session, keys.key(self.cfg.namespace, keys.QUERY_MESH),
                              query_messages.MeshRequest(self.cfg.mesh_resolution).to_msg(), max(60.0, self.cfg.timeout_s))
        rep = query_messages.MeshReply.from_msg(msg)
        self.pub_mesh.publish(outmsgs.mesh_marker(self.ts, rep.vertices, rep.faces, self.cfg.frame_id, time.time_ns()))
        self._mesh_sent, self._last_mesh = baked, now
        self.counts["meshes"] += 1
        return True

    def tick(self, now: float | None = None, mesh: bool = True) -> None:
        """One round: surfels, the grid and the slice where the map changed, and (``mesh``) the
        mesh when due. Errors (no map yet, a busy or absent query service) are logged; the next
        tick retries."""
        now = time.monotonic() if now is None else now
        steps = [("surfels", self.publish_surfels), ("map", self._probe_now),
                 ("grid", lambda: self.refresh_grid(now, self.baked))]
        if mesh:
            steps.append(("mesh", lambda: self.publish_mesh(now, self.baked)))
        for name, step in steps:
            t = time.monotonic()
            try:
                if step():
                    self.took[name] = time.monotonic() - t
            except protocol.ProtocolError as e:
                (log.info if e.code in ("no_map", "busy") else log.warning)(
                    "the query service answered %s: %s", e.code, e.message)
                if name in ("surfels", "map"):
                    break
            except TimeoutError as e:
                log.warning("no answer from the query service: %s", e)
                break
            except Exception:  # noqa: BLE001 - the node goes on
                self.counts["errors"] += 1
                log.exception("publishing the map for ROS 2 failed")

    def _probe_now(self) -> None:
        self.baked = self.probe()

    def mesh_loop(self, stop: threading.Event) -> None:
        """The mesh on its own thread (marching a floor takes longer than a grid's period)."""
        while not stop.wait(1.0):
            if self.baked is None:
                continue
            t = time.monotonic()
            try:
                if self.publish_mesh(t, self.baked):
                    self.took["mesh"] = time.monotonic() - t
                    self.mesh_times.append(self.took["mesh"])
            except (protocol.ProtocolError, TimeoutError) as e:
                log.warning("no mesh from the query service: %s", e)
            except Exception:  # noqa: BLE001 - the node goes on
                self.counts["errors"] += 1
                log.exception("publishing the mesh failed")

    def run(self, stop: threading.Event) -> None:
        self._catch_up()
        mesher = threading.Thread(target=self.mesh_loop, args=(stop,), name="mesh", daemon=True)
        mesher.start()
        period = 1.0 / self.cfg.rate_hz
        while not stop.is_set():
            t0 = time.monotonic()
            self.tick(t0, mesh=False)
            stop.wait(max(0.0, period - (time.monotonic() - t0)))
        mesher.join(max(60.0, self.cfg.timeout_s) + 5)

    def close(self) -> None:
        for d in self._decls:
            d.undeclare()
        self._decls = []
