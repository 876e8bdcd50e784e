"""The map view of ``aisdf view``: protocol messages logged to a rerun recording.

* ``world/cameras/<sensor>``: the newest keyframe's pose (Transform3D), its camera
  frustum (Pinhole) and ``.../depth`` its depth image; ``world/paths/<sensor>`` the
  camera path through every keyframe (a line strip, keyframes as points). A keyframe
  seen again is logged once per (sensor, frame_id).
* ``world/surfels``: the surfel map as thin boxes, coloured by Atlanta direction
  (class 0: vertical normal, floors and ceilings; class k + 1: horizontal direction k,
  walls); ``world/atlanta``: the Atlanta frame as arrows in the same colours.
* ``world/mesh``: the query service's mesh.
* ``stats/*``: keyframes, surfels, map version, training step, mesh size; ``log``:
  malformed messages.

No Zenoh here (``aisdf.viewer`` follows the stack and feeds a :class:`MapView`). rerun-sdk
is the optional extra ``aisdf[viewer]``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict

import numpy as np

from . import protocol, query_messages

log = logging.getLogger("aisdf.viewer")

MISSING_RERUN = "aisdf view needs rerun-sdk, the optional extra: pip install 'aisdf[viewer]'"
# Class 0: a vertical normal (floors, ceilings); class k + 1: horizontal direction k (walls).
VERTICAL_COLOR = (150, 150, 160)
HORIZONTAL_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                     (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207)]
UNKNOWN_COLOR = (0, 0, 0)


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

    def mesh(self, m: query_messages.MeshReply) -> None:
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
