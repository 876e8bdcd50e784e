"""ROS 2 messages of the map, built as ``rosbags`` message objects (serialised to CDR by the
node's typestore): ``nav_msgs/OccupancyGrid``, ``sensor_msgs/PointCloud2`` (x y z and the
distance, as nvblox's ESDF slice), ``visualization_msgs/MarkerArray`` (one cube per surfel)
and ``visualization_msgs/Marker`` (a triangle list of the mesh).

:func:`make` fills every field a message has in the typestore's distribution (Marker grew
fields between Humble and Jazzy) with its zero value, so the builders name only what they set.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .slices import Ground

_NUMPY = {"bool": "?", "byte": "u1", "char": "u1", "octet": "u1", "uint8": "u1", "int8": "i1", "uint16": "<u2",
          "int16": "<i2", "uint32": "<u4", "int32": "<i4", "uint64": "<u8", "int64": "<i8", "float32": "<f4",
          "float64": "<f8"}
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
# one colour per Atlanta direction: horizontal surfaces (-1), then each wall direction
SURFACE_RGBA = (0.55, 0.55, 0.55, 0.9)
WALL_RGBA = ((0.90, 0.35, 0.25, 0.9), (0.25, 0.55, 0.90, 0.9), (0.35, 0.75, 0.35, 0.9), (0.90, 0.75, 0.20, 0.9),
             (0.65, 0.40, 0.85, 0.9), (0.20, 0.80, 0.80, 0.9))


def _default(ts, node):
    nt, det = node
    kind = int(nt)
    if kind == 1:  # BASE
        name = det[0]
        return "" if name == "string" else (False if name == "bool" else (0.0 if name.startswith("float") else 0))
    if kind == 2:  # NAME
        return make(ts, det)
    (sub, n) = det
    if int(sub[0]) == 1 and sub[1][0] in _NUMPY:
        return np.zeros(n if kind == 3 else 0, dtype=_NUMPY[sub[1][0]])
    return [_default(ts, sub) for _ in range(n)] if kind == 3 else []


def make(ts, msgtype: str, **values):
    """A ``msgtype`` message of typestore ``ts``: ``values``, and zeros for the rest."""
    _, fields = ts.fielddefs[msgtype]
    names = {name for name, _ in fields}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"{msgtype} has no field(s) {sorted(unknown)}")
    return ts.types[msgtype](**{name: values[name] if name in values else _default(ts, node)
                                for name, node in fields})


def header(ts, frame_id: str, stamp_ns: int):
    t = make(ts, "builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000),
             nanosec=int(stamp_ns % 1_000_000_000))
    return make(ts, "std_msgs/msg/Header", stamp=t, frame_id=frame_id)


def pose(ts, position, R=None):
    q = Rotation.from_matrix(np.eye(3) if R is None else R).as_quat()  # x y z w
    return make(ts, "geometry_msgs/msg/Pose",
                position=make(ts, "geometry_msgs/msg/Point", x=float(position[0]), y=float(position[1]),
                              z=float(position[2])),
                orientation=make(ts, "geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                 w=float(q[3])))


def occupancy_grid(ts, grid: np.ndarray, ground: Ground, origin_xy, resolution: float, frame_id: str,
                   stamp_ns: int):
    """``grid`` (nx, ny) int8 of columns whose centres are ``origin_xy + resolution * (i, j)`` in the
    ground's plane, at the floor's height. The message's origin is cell (0, 0)'s corner and its
    data row-major from it (x fastest)."""
    nx, ny = grid.shape
    corner = ground.to_world(np.array([[origin_xy[0] - resolution / 2, origin_xy[1] - resolution / 2, 0.0]]))[0]
    info = make(ts, "nav_msgs/msg/MapMetaData", map_load_time=header(ts, "", stamp_ns).stamp,
                resolution=float(resolution), width=int(nx), height=int(ny), origin=pose(ts, corner, ground.R))
    return make(ts, "nav_msgs/msg/OccupancyGrid", header=header(ts, frame_id, stamp_ns), info=info,
                data=np.ascontiguousarray(grid.T).reshape(-1).astype(np.int8))


def distance_cloud(ts, points: np.ndarray, distance: np.ndarray, frame_id: str, stamp_ns: int,
                   field: str = "intensity"):
    """An unordered ``PointCloud2`` of float32 x, y, z and the distance (named ``intensity`` as
    nvblox's ESDF slice, so RViz colours by it)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    data = np.concatenate([pts, np.asarray(distance, np.float32).reshape(-1, 1)], axis=1)
    fields = [make(ts, "sensor_msgs/msg/PointField", name=n, offset=4 * i, datatype=FLOAT32, count=1)
              for i, n in enumerate(("x", "y", "z", field))]
    return make(ts, "sensor_msgs/msg/PointCloud2", header=header(ts, frame_id, stamp_ns), height=1,
                width=len(pts), fields=fields, is_bigendian=False, point_step=16, row_step=16 * len(pts),
                data=np.ascontiguousarray(data).view(np.uint8).reshape(-1), is_dense=True)


def _rgba(ts, c):
    return make(ts, "std_msgs/msg/ColorRGBA", r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))


def surfel_markers(ts, surfels: dict, frame_id: str, stamp_ns: int, thickness: float = 0.01, ns: str = "surfels"):
    """A ``MarkerArray``: DELETEALL, then one CUBE per surfel (its rectangle, ``thickness`` thick),
    coloured by Atlanta direction."""
    h = header(ts, frame_id, stamp_ns)
    out = [make(ts, "visualization_msgs/msg/Marker", header=h, ns=ns, action=3)]
    c = np.asarray(surfels.get("center", np.zeros((0, 3))), np.float64)
    if len(c):
        a1, a2 = np.asarray(surfels["axis1"], np.float64), np.asarray(surfels["axis2"], np.float64)
        n = np.cross(a1, a2)
        R = np.stack([a1, a2, n / np.linalg.norm(n, axis=1, keepdims=True)], axis=2)
        R = Rotation.from_matrix(R).as_matrix()  # the nearest rotations (float32 axes are not exactly orthonormal)
        ext, d = np.asarray(surfels["extent"], np.float64), np.asarray(surfels["direction"])
        for i in range(len(c)):
            col = SURFACE_RGBA if d[i] < 0 else WALL_RGBA[int(d[i]) % len(WALL_RGBA)]
            out.append(make(ts, "visualization_msgs/msg/Marker", header=h, ns=ns, id=i + 1, type=1, action=0,
                            pose=pose(ts, c[i], R[i]),
                            scale=make(ts, "geometry_msgs/msg/Vector3", x=float(ext[i, 0]), y=float(ext[i, 1]),
                                       z=float(thickness)), color=_rgba(ts, col)))
    return make(ts, "visualization_msgs/msg/MarkerArray", markers=out)


def mesh_marker(ts, vertices: np.ndarray, faces: np.ndarray, frame_id: str, stamp_ns: int, ns: str = "mesh",
                rgba=(0.8, 0.8, 0.8, 1.0)):
    """A ``TRIANGLE_LIST`` marker: three points per face."""
    P = make(ts, "geometry_msgs/msg/Point").__class__
    tri = np.asarray(vertices, np.float64)[np.asarray(faces).reshape(-1)]
    pts = [P(x=float(x), y=float(y), z=float(z)) for x, y, z in tri.tolist()]
    return make(ts, "visualization_msgs/msg/Marker", header=header(ts, frame_id, stamp_ns), ns=ns, id=0, type=11,
                action=0, pose=pose(ts, (0.0, 0.0, 0.0)),
                scale=make(ts, "geometry_msgs/msg/Vector3", x=1.0, y=1.0, z=1.0), color=_rgba(ts, rgba),
                points=pts)
