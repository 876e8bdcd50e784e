"""``aisdf view``: a live rerun view of a running stack, from the wire protocol alone.

Subscribes to ``<ns>/keyframes``, ``<ns>/map/surfels`` and ``<ns>/map/weights`` (or, from a
submap mapper, ``<ns>/map/index``: protocol 1.3; only for the map version), asks
``<ns>/query/mesh`` every ``mesh_period_s`` and logs to rerun as things arrive:

* ``world/cameras/<sensor>``: the newest keyframe's pose (Transform3D), its camera
  frustum (Pinhole) and ``.../depth`` its depth image; ``world/paths/<sensor>`` the
  camera path through every keyframe (a line strip, keyframes as points). A keyframe
  seen again (a 1.2 frontend resends until acknowledged) is logged once per
  (sensor, frame_id).
* ``world/surfels``: the surfel map as thin boxes, coloured by Atlanta direction
  (class 0: vertical normal, floors and ceilings; class k + 1: horizontal direction k,
  walls); ``world/atlanta``: the Atlanta frame as arrows in the same colours.
* ``world/mesh``: the query service's mesh, refreshed.
* ``stats/*``: keyframes, surfels, map version, training step, mesh size; ``log``:
  malformed messages (logged, counted and skipped; they never stop the viewer).

Default: spawns the rerun viewer window; ``--save FILE.rrd`` records to a file instead
(no window, no server). Only protocol messages are used (aisdf.protocol, aisdf.keys,
aisdf.transport); nothing of the mapper's internals. rerun-sdk is the optional extra
``aisdf[viewer]``.
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
import uuid
from collections import defaultdict
from pathlib import Path

import numpy as np
from pydantic import Field

from . import keys, protocol, transport
from .config import ServiceConfig, add_common_args, config_from_args, service_setup

log = logging.getLogger("aisdf.viewer")

MISSING_RERUN = "aisdf view needs rerun-sdk, the optional extra: pip install 'aisdf[viewer]'"
# Class 0: a vertical normal (floors, ceilings); class k + 1: horizontal direction k (walls).
VERTICAL_COLOR = (150, 150, 160)
HORIZONTAL_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                     (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207)]
UNKNOWN_COLOR = (0, 0, 0)


class ViewerConfig(ServiceConfig):
    """``aisdf view``: the transport settings every service has, plus what to show."""

    save: Path | None = Field(None, description="record to this .rrd file instead of spawning the viewer window")
    mesh_period_s: float = Field(5.0, ge=0, description="ask query/mesh this often (0: never)")
    mesh_resolution: float = Field(0.08, gt=0, description="marching-cubes voxel size asked for (m)")
    mesh_timeout_s: float = Field(60.0, gt=0, description="give up on a mesh request after this long")
    duration_s: float | None = Field(None, gt=0, description="stop after this long (default: until Ctrl-C/SIGTERM)")
    frustum_m: float = Field(0.3, gt=0, description="drawn depth of the camera frustum (m)")
    surfel_thickness_m: float = Field(0.01, gt=0, description="drawn thickness of a surfel (m)")
    keyframe_queue: int = Field(256, ge=1, description="keyframes waiting to be logged; beyond, new ones are dropped")


def import_rerun():
    try:
        import rerun as rr
    except ImportError:
        raise SystemExit(MISSING_RERUN) from None
    return rr


def box_quaternions(axis1: np.ndarray, axis2: np.ndarray) -> np.ndarray:
    """(N, 4) xyzw rotations taking a box's local x, y, z to (axis1, axis2, axis1 x axis2)."""
    from scipy.spatial.transform import Rotation

    a1 = axis1 / np.maximum(np.linalg.norm(axis1, axis=1, keepdims=True), 1e-12)
    a2 = axis2 - np.sum(axis2 * a1, axis=1, keepdims=True) * a1
    a2 = a2 / np.maximum(np.linalg.norm(a2, axis=1, keepdims=True), 1e-12)
    R = np.stack([a1, a2, np.cross(a1, a2)], axis=2)  # columns
    return Rotation.from_matrix(R).as_quat()


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (for shading)."""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.zeros_like(v)
    for i in range(3):
        np.add.at(n, faces[:, i], fn)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


class MapView:
    """Logs protocol messages to a rerun recording. No Zenoh here; safe from several threads."""

    def __init__(self, rec, frustum_m: float = 0.3, surfel_thickness_m: float = 0.01):
        self.rr = import_rerun()
        self.rec = rec
        self.frustum_m = frustum_m
        self.thickness = surfel_thickness_m
        self.t0 = time.monotonic()
        self.seen: set[tuple[str, int]] = set()
        self.paths: dict[str, list[tuple[float, np.ndarray]]] = defaultdict(list)
        self.surfel_key: tuple[int, int] | None = None
        self.map_key: tuple[int, int] | None = None  # newest (epoch, version) from map/weights or map/index
        self.n_classes = -1
        self.counts = {"keyframes": 0, "repeats": 0, "surfel_maps": 0, "surfels": 0, "weights": 0, "indexes": 0,
                       "meshes": 0, "mesh_version": None, "malformed": 0}
        self._lock = threading.Lock()

    def _time(self) -> None:
        self.rec.set_time("wall", duration=time.monotonic() - self.t0)

    def _scalar(self, name: str, value: float) -> None:
        self.rec.log(f"stats/{name}", self.rr.Scalars([float(value)]))

    def keyframe(self, kf: protocol.Keyframe) -> bool:
        """Log a keyframe once per (sensor, frame_id); False for a repeat."""
        rr = self.rr
        with self._lock:
            if (kf.sensor, kf.frame_id) in self.seen:
                self.counts["repeats"] += 1
                return False
            self.seen.add((kf.sensor, kf.frame_id))
            self.counts["keyframes"] += 1
            path = self.paths[kf.sensor]
            path.append((kf.stamp, kf.T_WC[:3, 3].copy()))
            path.sort(key=lambda p: p[0])
            positions = np.array([p for _, p in path])
            n = self.counts["keyframes"]
        sensor = rr.escape_entity_path_part(kf.sensor)
        H, W = kf.depth.shape
        self._time()
        cam = f"world/cameras/{sensor}"
        self.rec.log(cam, rr.Transform3D(translation=kf.T_WC[:3, 3], mat3x3=kf.T_WC[:3, :3]))
        self.rec.log(cam, rr.Pinhole(image_from_camera=kf.K, width=W, height=H, image_plane_distance=self.frustum_m))
        if kf.depth.dtype == np.uint16:
            self.rec.log(f"{cam}/depth", rr.DepthImage(kf.depth, meter=float(kf.depth_scale)))
        else:
            self.rec.log(f"{cam}/depth", rr.DepthImage(kf.depth_m(), meter=1.0))
        self.rec.log(f"world/paths/{sensor}", rr.LineStrips3D([positions], radii=0.01),
                     rr.Points3D(positions, radii=0.03))
        self._scalar("keyframes", n)
        return True

    def _annotations(self, m: int) -> None:
        """Class ids: 0 vertical, k + 1 horizontal k, m + 1 a label outside the frame."""
        if m == self.n_classes:
            return
        self.n_classes = m
        rr = self.rr
        infos = [rr.AnnotationInfo(0, "vertical normal (floor, ceiling)", VERTICAL_COLOR)]
        infos += [rr.AnnotationInfo(k + 1, f"horizontal {k} (walls)", HORIZONTAL_COLORS[k % len(HORIZONTAL_COLORS)])
                  for k in range(m)]
        infos.append(rr.AnnotationInfo(m + 1, "direction outside the Atlanta frame", UNKNOWN_COLOR))
        self.rec.log("world", rr.AnnotationContext(infos), static=True)

    def surfel_map(self, s: protocol.SurfelMap) -> bool:
        """Log a surfel map newer (by epoch, version) than the last one; False otherwise."""
        rr = self.rr
        with self._lock:
            key = (s.epoch, s.version)
            if self.surfel_key is not None and key <= self.surfel_key:
                return False
            self.surfel_key = key
            self.counts["surfel_maps"] += 1
            self.counts["surfels"] = len(s)
        m = len(s.horizontal)
        self._time()
        self._annotations(m)
        sf = s.surfels
        d = sf["direction"].astype(np.int64)
        class_ids = np.where((d >= -1) & (d < m), d + 1, m + 1)
        if len(s):
            half = np.column_stack([sf["extent"] / 2, np.full(len(s), self.thickness / 2, np.float32)])
            self.rec.log("world/surfels", rr.Boxes3D(centers=sf["center"], half_sizes=half,
                                                     quaternions=box_quaternions(sf["axis1"], sf["axis2"]),
                                                     class_ids=class_ids, fill_mode="solid"))
            origin = sf["center"].mean(axis=0)
        else:
            self.rec.log("world/surfels", rr.Clear(recursive=False))
            origin = np.zeros(3)
        vectors = np.vstack([s.vertical.reshape(1, 3), s.horizontal.reshape(-1, 3)])
        self.rec.log("world/atlanta", rr.Arrows3D(origins=np.repeat(origin[None], len(vectors), 0), vectors=vectors,
                                                  class_ids=np.arange(len(vectors)), radii=0.02))
        self._scalar("surfels", len(s))
        return True

    def _map_version(self, epoch: int, version: int, counter: str) -> bool:
        with self._lock:
            key = (epoch, version)
            if self.map_key is not None and key <= self.map_key:
                return False
            self.map_key = key
            self.counts[counter] += 1
        self._time()
        self._scalar("map_version", version)
        return True

    def weights(self, w: protocol.WeightSnapshot) -> bool:
        """A one-network map's snapshot: its version and training step."""
        if not self._map_version(w.epoch, w.version, "weights"):
            return False
        self._scalar("training_step", w.step)
        return True

    def index(self, idx: protocol.SubmapIndex) -> bool:
        """A submap mapper's index (protocol 1.3): its version and the number of submaps."""
        if not self._map_version(idx.epoch, idx.version, "indexes"):
            return False
        self._scalar("submaps", len(idx.submaps))
        return True

    def mesh(self, m: protocol.MeshReply) -> None:
        self._time()
        if len(m.vertices) and len(m.faces):
            self.rec.log("world/mesh", self.rr.Mesh3D(vertex_positions=m.vertices, triangle_indices=m.faces,
                                                      vertex_normals=vertex_normals(m.vertices, m.faces),
                                                      albedo_factor=(200, 200, 200, 255)))
        else:
            self.rec.log("world/mesh", self.rr.Clear(recursive=False))
        self._scalar("mesh_vertices", len(m.vertices))
        with self._lock:
            self.counts["meshes"] += 1
            self.counts["mesh_version"] = m.map_version

    def malformed(self, what: str, message: str) -> None:
        with self._lock:
            self.counts["malformed"] += 1
            n = self.counts["malformed"]
        if n <= 10 or n % 100 == 0:
            log.warning("skipped a malformed message on %s (%d so far): %s", what, n, message)
        self._time()
        self.rec.log("log", self.rr.TextLog(f"malformed message on {what}: {message}", level="WARN"))


def blueprint(rr):
    import rerun.blueprint as rrb

    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="map"),
        rrb.Vertical(rrb.Spatial2DView(origin="world/cameras", name="depth"),
                     rrb.TimeSeriesView(origin="stats", name="stats"), rrb.TextLogView(origin="log", name="log")),
        column_shares=[3, 1]))


class LiveViewer:
    """Zenoh wiring: subscriptions feed a worker thread that logs; another thread asks for meshes."""

    DECODERS = {keys.KEYFRAMES: protocol.Keyframe, keys.MAP_SURFELS: protocol.SurfelMap,
                keys.MAP_WEIGHTS: protocol.WeightSnapshot, keys.MAP_INDEX: protocol.SubmapIndex}
    LATEST = (keys.MAP_SURFELS, keys.MAP_WEIGHTS, keys.MAP_INDEX)  # only the newest of each waits

    def __init__(self, session, view: MapView, namespace: str = keys.DEFAULT_NAMESPACE,
                 mesh_period_s: float = 5.0, mesh_resolution: float = 0.08, mesh_timeout_s: float = 60.0,
                 keyframe_queue: int = 256):
        self.session = session
        self.view = view
        self.ns = keys.validate_namespace(namespace)
        self.mesh_period_s = mesh_period_s
        self.mesh_resolution = mesh_resolution
        self.mesh_timeout_s = mesh_timeout_s
        self.keyframes: queue.Queue = queue.Queue(maxsize=keyframe_queue)
        self.latest: dict[str, object] = {}  # LATEST keys: only the newest waits
        self.dropped = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._decls: list = []
        self._threads = [threading.Thread(target=self._work, name="viewer-log", daemon=True)]
        if mesh_period_s > 0:
            self._threads.append(threading.Thread(target=self._meshes, name="viewer-mesh", daemon=True))

    def start(self) -> "LiveViewer":
        for name in (keys.KEYFRAMES, *self.LATEST):
            self._decls.append(self.session.declare_subscriber(
                keys.key(self.ns, name), lambda s, name=name: self._on_sample(name, s)))
        # Subscribed: say so (the demo and the tests wait for this token before starting a frontend).
        self._decls.append(self.session.liveliness().declare_token(
            keys.status_key(self.ns, "viewer", uuid.uuid4().hex[:8])))
        for t in self._threads:
            t.start()
        for name in self.LATEST:  # the latest map at once, not at the next publication
            for reply in self.session.get(keys.key(self.ns, name), timeout=2.0):
                if reply.ok is not None:
                    self._offer(name, transport.payload_bytes(reply.ok.payload))
        return self

    def _on_sample(self, name: str, sample) -> None:
        self._offer(name, transport.payload_bytes(sample.payload))

    def _offer(self, name: str, raw: bytes) -> None:
        """Decode on arrival (a malformed message is counted and skipped here); queue for logging."""
        try:
            msg = self.DECODERS[name].from_msg(protocol.unpack(raw))
        except protocol.ProtocolError as e:
            self.view.malformed(name, e.message)
            return
        except Exception as e:  # noqa: BLE001 - never let a message break the subscription
            self.view.malformed(name, f"{type(e).__name__}: {e}")
            return
        with self._cond:
            if name == keys.KEYFRAMES:
                try:
                    self.keyframes.put_nowait(msg)
                except queue.Full:
                    self.dropped += 1
                    log.warning("keyframe queue full (%d): dropped one (%d so far)", self.keyframes.maxsize,
                                self.dropped)
            else:  # only the newest map waits: (epoch, version) order, as the protocol says
                held = self.latest.get(name)
                if held is None or (msg.epoch, msg.version) > (held.epoch, held.version):
                    self.latest[name] = msg
            self._cond.notify()

    def _log(self, name: str, msg) -> None:
        try:
            {keys.KEYFRAMES: self.view.keyframe, keys.MAP_SURFELS: self.view.surfel_map,
             keys.MAP_WEIGHTS: self.view.weights, keys.MAP_INDEX: self.view.index}[name](msg)
        except Exception as e:  # noqa: BLE001 - a message that decodes but cannot be drawn is skipped too
            log.exception("could not log a message on %s", name)
            self.view.malformed(name, f"{type(e).__name__}: {e}")

    def _drain(self) -> bool:
        did = False
        while True:
            try:
                kf = self.keyframes.get_nowait()
            except queue.Empty:
                break
            self._log(keys.KEYFRAMES, kf)
            did = True
        for name in self.LATEST:
            with self._cond:
                msg = self.latest.pop(name, None)
            if msg is not None:
                self._log(name, msg)
                did = True
        return did

    def _work(self) -> None:
        while not self._stop.is_set():
            if not self._drain():
                with self._cond:
                    self._cond.wait(0.2)
        self._drain()  # what arrived before the stop is still recorded

    def _meshes(self) -> None:
        key = keys.key(self.ns, keys.QUERY_MESH)
        request = protocol.MeshRequest(self.mesh_resolution).to_msg()
        while not self._stop.is_set():
            t = time.monotonic()
            asked = False
            v = self.view
            if v.counts["meshes"] == 0 or v.map_key is None or v.map_key[1] != v.counts["mesh_version"]:
                asked = True
                try:
                    reply = protocol.MeshReply.from_msg(transport.query(self.session, key, request,
                                                                        self.mesh_timeout_s))
                    v.mesh(reply)
                    log.info("mesh of map v%d: %d vertices, %d faces", reply.map_version, len(reply.vertices),
                             len(reply.faces))
                except protocol.ProtocolError as e:
                    if e.code in ("no_map", "busy"):
                        log.info("no mesh yet: %s", e.message)
                    else:
                        v.malformed(keys.QUERY_MESH, f"{e.code}: {e.message}")
                except TimeoutError as e:
                    log.info("no mesh: %s", e)
                except Exception as e:  # noqa: BLE001 - e.g. the session closing under a request at shutdown
                    if not self._stop.is_set():
                        log.warning("mesh request failed: %s", e)
            # A mesh at most every period, and never more often than every 2x the last one's time:
            # meshes take at most half of the query service's mesh worker on a busy machine.
            took = time.monotonic() - t if asked else 0.0
            self._stop.wait(max(self.mesh_period_s - took, took))

    def close(self, timeout: float = 5.0) -> None:
        """Stop taking messages, record what is queued, stop the threads."""
        for d in self._decls:
            d.undeclare()
        self._decls.clear()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout)


def summary_line(view: MapView, dropped: int, save: Path | None) -> str:
    c = view.counts
    where = f"; wrote {save}" if save else ""
    return (f"viewer: {c['keyframes']} keyframes ({c['repeats']} repeats skipped, {dropped} dropped), "
            f"{c['surfel_maps']} surfel maps (last: {c['surfels']} surfels), {c['weights']} weight snapshots, "
            f"{c['indexes']} submap indexes, {c['meshes']} meshes, {c['malformed']} malformed messages skipped{where}")


def run(cfg: ViewerConfig, stop: threading.Event | None = None) -> dict:
    """Run until ``stop`` is set (or ``cfg.duration_s``); returns the counters."""
    rr = import_rerun()
    stop = stop or threading.Event()
    rec = rr.RecordingStream("aisdf", recording_id=f"aisdf-{cfg.namespace}-{uuid.uuid4().hex[:8]}")
    if cfg.save:
        Path(cfg.save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(cfg.save), default_blueprint=blueprint(rr))
    else:
        try:
            rec.spawn(default_blueprint=blueprint(rr))
        except Exception as e:  # noqa: BLE001
            raise SystemExit(f"could not start the rerun viewer ({e}); record with --save FILE.rrd instead") from None
    view = MapView(rec, cfg.frustum_m, cfg.surfel_thickness_m)
    session = transport.open_session(cfg.zenoh)
    viewer = None
    try:
        viewer = LiveViewer(session, view, cfg.namespace, cfg.mesh_period_s, cfg.mesh_resolution,
                            cfg.mesh_timeout_s, cfg.keyframe_queue).start()
        log.info("viewing namespace %s%s", cfg.namespace, f", recording to {cfg.save}" if cfg.save else "")
        end = time.monotonic() + cfg.duration_s if cfg.duration_s else None
        while not stop.wait(0.5):
            if end is not None and time.monotonic() >= end:
                break
    finally:
        if viewer is not None:
            viewer.close()
        rec.flush(timeout_sec=30.0)
        rec.disconnect()
        session.close()
    print(summary_line(view, viewer.dropped if viewer else 0, cfg.save), flush=True)
    return dict(view.counts, dropped=viewer.dropped if viewer else 0)


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    add_common_args(p)
    p.add_argument("--save", metavar="FILE.rrd", help="record to this file instead of spawning the viewer window")
    p.add_argument("--mesh-period", type=float, metavar="S",
                   help="ask query/mesh every S seconds (default 5; 0: never)")
    p.add_argument("--mesh-resolution", type=float, metavar="M", help="mesh voxel size in metres (default 0.08)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C/SIGTERM)")
    return p


def main(args: argparse.Namespace) -> None:
    cfg = config_from_args(ViewerConfig, args, {"save": args.save, "mesh_period_s": args.mesh_period,
                                                "mesh_resolution": args.mesh_resolution,
                                                "duration_s": args.duration})
    import_rerun()  # a clear message before anything starts when the extra is missing
    stop = service_setup(cfg, "viewer")
    logging.getLogger().setLevel(cfg.log_level)  # the umbrella command configured logging already
    run(cfg, stop)
