"""A TF buffer (the part of ROS's tf2 that AiSDF needs), without ROS.

Interface (used by the rosbag source and the live ROS 2 source)::

    buf = TFBuffer(cache_s=30.0)                      # None: keep every sample (a pre-scanned bag)
    buf.add_tf_message(msg, static=False)             # a deserialised tf2_msgs/TFMessage (/tf or /tf_static)
    buf.set_transform(parent, child, stamp_ns, T, static=False)   # T: 4x4, child -> parent (T_parent_child)
    T = buf.lookup(target, source, stamp_ns)          # 4x4 T_target_source at that time
    ok, why = buf.can_transform(target, source, stamp_ns)

Frames form a tree: each child has one parent (the last one given). A static edge holds at any
time; a dynamic edge is a time series per (parent, child), interpolated at the asked stamp
(translation linearly, rotation by spherical linear interpolation with scipy's ``Slerp``).
A lookup walks from both frames up to their common ancestor through any number of edges.

Errors say what is wrong, in words:

- :class:`ConnectivityError`: a frame is not in the tree, or the two frames are in separate
  trees (a missing link); ``missing`` names the frame(s) concerned.
- :class:`ExtrapolationError`: the stamp lies outside a dynamic edge's samples;
  ``future`` is True when it lies after the newest sample (a live source may wait for it),
  False when before the oldest (it never will be placed).

Poses from a topic instead of TF: :func:`pose_from_message` reads ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped``, ``TransformStamped`` or ``nav_msgs/Odometry`` as an edge
``header.frame_id -> child``; :func:`parse_extrinsic` reads a fixed camera extrinsic from the
command line."""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .messages import pose_to_matrix, stamp_ns, transform_to_matrix

# camera_link (x forward, y left, z up; REP-103) -> camera_*_optical_frame (z forward, x right,
# y down; REP-103 optical). Columns: the optical axes in camera_link coordinates.
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
Q_LINK_OPTICAL = (-0.5, 0.5, -0.5, 0.5)  # the same rotation as a quaternion (x, y, z, w)


class TFError(Exception):
    """A transform cannot be looked up; the message says why."""


class ConnectivityError(TFError):
    def __init__(self, message: str, missing: tuple[str, ...] = ()):
        super().__init__(message)
        self.missing = missing


class ExtrapolationError(TFError):
    def __init__(self, message: str, parent: str, child: str, stamp_ns: int, first_ns: int, last_ns: int):
        super().__init__(message)
        self.parent, self.child, self.stamp_ns = parent, child, stamp_ns
        self.first_ns, self.last_ns = first_ns, last_ns
        self.future = stamp_ns > last_ns


def _fmt_s(ns: int) -> str:
    return f"{ns * 1e-9:.6f} s"


def _strip(frame: str) -> str:
    return frame[1:] if frame.startswith("/") else frame  # ROS 1 frames often carry a leading slash


@dataclass
class _Edge:
    parent: str
    static: bool
    T: np.ndarray | None = None  # static
    stamps: list[int] = field(default_factory=list)  # dynamic, sorted
    trans: list[np.ndarray] = field(default_factory=list)
    quats: list[np.ndarray] = field(default_factory=list)


class TFBuffer:
    def __init__(self, cache_s: float | None = 30.0):
        self.cache_ns = None if cache_s is None else int(cache_s * 1e9)
        self._edges: dict[str, _Edge] = {}  # child -> edge to its parent

    # ---- filling --------------------------------------------------------------------------
    def set_transform(self, parent: str, child: str, stamp: int, T: np.ndarray, static: bool = False) -> None:
        parent, child = _strip(str(parent)), _strip(str(child))
        if not parent or not child:
            raise ValueError(f"transform with an empty frame name ({parent!r} -> {child!r})")
        if parent == child:
            raise ValueError(f"transform from frame {child!r} to itself")
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"transform {parent} -> {child} is not a finite 4x4 matrix")
        edge = self._edges.get(child)
        if static:
            self._edges[child] = _Edge(parent, True, T=T.copy())
            return
        if edge is None or edge.static or edge.parent != parent:
            edge = self._edges[child] = _Edge(parent, False)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        i = bisect.bisect_left(edge.stamps, stamp)
        if i < len(edge.stamps) and edge.stamps[i] == stamp:  # same stamp again: the newer one wins
            edge.trans[i], edge.quats[i] = T[:3, 3].copy(), q
        else:
            edge.stamps.insert(i, int(stamp))
            edge.trans.insert(i, T[:3, 3].copy())
            edge.quats.insert(i, q)
        if self.cache_ns is not None:
            cut = bisect.bisect_left(edge.stamps, edge.stamps[-1] - self.cache_ns)
            if cut > 0:
                del edge.stamps[:cut], edge.trans[:cut], edge.quats[:cut]

    def add_transform_stamped(self, ts, static: bool = False) -> None:
        """A deserialised ``geometry_msgs/TransformStamped``."""
        self.set_transform(ts.header.frame_id, ts.child_frame_id, stamp_ns(ts.header.stamp),
                           transform_to_matrix(ts.transform), static)

    def add_tf_message(self, msg, static: bool = False) -> int:
        """A deserialised ``tf2_msgs/TFMessage``; returns how many transforms it held.
        A malformed transform raises ``ValueError`` after the valid ones are stored."""
        bad = []
        for ts in msg.transforms:
            try:
                self.add_transform_stamped(ts, static)
            except ValueError as e:
                bad.append(str(e))
        if bad:
            raise ValueError("; ".join(bad))
        return len(msg.transforms)

    # ---- queries --------------------------------------------------------------------------
    @property
    def frames(self) -> set[str]:
        out = set(self._edges)
        out.update(e.parent for e in self._edges.values())
        return out

    def edges(self) -> list[tuple[str, str, bool, int]]:
        """(parent, child, static, number of samples) for every edge."""
        return [(e.parent, c, e.static, 1 if e.static else len(e.stamps)) for c, e in sorted(self._edges.items())]

    def time_range(self, parent: str, child: str) -> tuple[int, int] | None:
        """First and last stamp of a dynamic edge (None for a static or unknown edge)."""
        e = self._edges.get(_strip(child))
        if e is None or e.static or e.parent != _strip(parent) or not e.stamps:
            return None
        return e.stamps[0], e.stamps[-1]

    def chain(self, target: str, source: str) -> list[tuple[str, str, bool]]:
        """The edges (parent, child, static) between two frames; raises ConnectivityError."""
        target, source = _strip(target), _strip(source)
        known = self.frames
        missing = tuple(f for f in (target, source) if f not in known)
        if missing:
            raise ConnectivityError(
                f"frame{'s' if len(missing) > 1 else ''} {', '.join(repr(m) for m in missing)} "
                f"{'are' if len(missing) > 1 else 'is'} not in the TF tree (known frames: "
                f"{', '.join(sorted(known)) or 'none'})", missing)
        up_s, up_t = self._ancestors(source), self._ancestors(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise ConnectivityError(
                f"no TF chain between {target!r} and {source!r}: {target!r} hangs under {up_t[-1]!r} and "
                f"{source!r} under {up_s[-1]!r}, and no transform links the two trees", (up_t[-1], up_s[-1]))
        edges = []
        for path in (up_s[: up_s.index(common)], up_t[: up_t.index(common)]):
            for child in path:
                e = self._edges[child]
                edges.append((e.parent, child, e.static))
        return edges

    def _ancestors(self, frame: str) -> list[str]:
        out, seen = [frame], {frame}
        while out[-1] in self._edges:
            p = self._edges[out[-1]].parent
            if p in seen:
                raise ConnectivityError(f"the TF tree has a loop through {p!r}", (p,))
            out.append(p)
            seen.add(p)
        return out

    def _edge_at(self, child: str, stamp: int) -> np.ndarray:
        e = self._edges[child]
        if e.static:
            return e.T
        s = e.stamps
        if not s or stamp < s[0] or stamp > s[-1]:
            first, last = (s[0], s[-1]) if s else (0, -1)
            where = "after the newest" if stamp > last else "before the oldest"
            raise ExtrapolationError(
                f"stamp {_fmt_s(stamp)} is {where} transform {e.parent} -> {child} in the TF buffer "
                f"(it holds {_fmt_s(first)} .. {_fmt_s(last)})", e.parent, child, stamp, first, last)
        i = bisect.bisect_left(s, stamp)
        T = np.eye(4)
        if s[i] == stamp:
            T[:3, :3] = Rotation.from_quat(e.quats[i]).as_matrix()
            T[:3, 3] = e.trans[i]
            return T
        t0, t1 = s[i - 1], s[i]
        a = (stamp - t0) / (t1 - t0)
        slerp = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([e.quats[i - 1], e.quats[i]])))
        T[:3, :3] = slerp([a]).as_matrix()[0]
        T[:3, 3] = (1 - a) * e.trans[i - 1] + a * e.trans[i]
        return T

    def _to_root(self, frame: str, stop: str, stamp: int) -> np.ndarray:
        T = np.eye(4)
        while frame != stop:
            T = self._edge_at(frame, stamp) @ T
            frame = self._edges[frame].parent
        return T

    def lookup(self, target: str, source: str, stamp: int) -> np.ndarray:
        """4x4 ``T_target_source`` (maps points in ``source`` to ``target``) at ``stamp`` (ns)."""
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4)
        self.chain(target, source)  # raises with the missing link
        up_t = set(self._ancestors(target))
        common = next(f for f in self._ancestors(source) if f in up_t)
        T_c_s = self._to_root(source, common, stamp)
        T_c_t = self._to_root(target, common, stamp)
        return np.linalg.solve(T_c_t, T_c_s)

    def can_transform(self, target: str, source: str, stamp: int) -> tuple[bool, str]:
        try:
            self.lookup(target, source, stamp)
        except TFError as e:
            return False, str(e)
        return True, ""


# ---- poses from a topic --------------------------------------------------------------------

POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")


def pose_from_message(msgtype: str, msg, child_default: str = "pose_body") -> tuple[str, str, int, np.ndarray]:
    """(parent, child, stamp ns, T_parent_child) from a pose message. PoseStamped and
    PoseWithCovarianceStamped have no child frame: ``child_default`` names it."""
    parent = _strip(msg.header.frame_id)
    if not parent:
        raise ValueError(f"{msgtype} message without header.frame_id")
    stamp = stamp_ns(msg.header.stamp)
    if msgtype.endswith("Odometry"):
        return parent, _strip(msg.child_frame_id) or child_default, stamp, pose_to_matrix(msg.pose.pose)
    if msgtype.endswith("PoseWithCovarianceStamped"):
        return parent, child_default, stamp, pose_to_matrix(msg.pose.pose)
    if msgtype.endswith("PoseStamped"):
        return parent, child_default, stamp, pose_to_matrix(msg.pose)
    if msgtype.endswith("TransformStamped"):
        return parent, _strip(msg.child_frame_id) or child_default, stamp, transform_to_matrix(msg.transform)
    raise ValueError(f"{msgtype} is not a pose type ({', '.join(POSE_TYPES)})")


def parse_extrinsic(text: str | None) -> np.ndarray:
    """The camera's pose in the pose topic's body frame, ``T_body_camera`` (the camera frame
    being the depth image's optical frame: z forward, x right, y down).

    ``text``: 7 numbers ``x y z qx qy qz qw``; 6 numbers ``x y z yaw pitch roll`` (radians,
    as ROS's static_transform_publisher); 16 numbers (a row-major 4x4); the word ``optical``
    (no offset, the REP-103 body -> optical rotation), optionally followed by ``x y z`` of the
    offset. None or empty: identity (the pose topic gives the optical frame's pose)."""
    if text is None or not str(text).strip():
        return np.eye(4)
    parts = str(text).replace(",", " ").split()
    T = np.eye(4)
    if parts[0].lower() == "optical":
        T[:3, :3] = R_LINK_OPTICAL
        rest = parts[1:]
        if rest and len(rest) != 3:
            raise ValueError(f"camera extrinsic 'optical' takes an optional x y z offset, got {len(rest)} numbers")
        if rest:
            T[:3, 3] = [float(v) for v in rest]
        return T
    try:
        v = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"camera extrinsic {text!r}: numbers expected (x y z qx qy qz qw, x y z yaw pitch roll, "
                         f"16 numbers of a 4x4, or 'optical [x y z]')") from None
    if len(v) == 7:
        if np.linalg.norm(v[3:]) < 1e-9:
            raise ValueError(f"camera extrinsic {text!r}: zero quaternion")
        T[:3, :3] = Rotation.from_quat(v[3:]).as_matrix()
        T[:3, 3] = v[:3]
    elif len(v) == 6:
        T[:3, :3] = Rotation.from_euler("ZYX", v[3:]).as_matrix()
        T[:3, 3] = v[:3]
    elif len(v) == 16:
        T = np.asarray(v, dtype=np.float64).reshape(4, 4)
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"camera extrinsic {text!r}: not a rigid 4x4 transform")
    else:
        raise ValueError(f"camera extrinsic {text!r}: {len(v)} numbers; 7 (x y z qx qy qz qw), 6 "
                         f"(x y z yaw pitch roll) or 16 (4x4) expected")
    return T
