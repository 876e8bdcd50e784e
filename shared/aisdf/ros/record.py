"""Write ROS recordings of a posed depth stream, with ``rosbags`` (the same library the
reader uses): rosbag2 sqlite3 (.db3), rosbag2 MCAP and ROS 1 (.bag).

:func:`write_bag` takes any frame source (``len()``, ``frame(i)`` -> dict(frame_id, stamp,
depth, K, T_WC), e.g. ``aisdf.synthetic.SyntheticSequence`` or a 7-Scenes folder from
``aisdf.datasets.open_dataset``) and records it as a robot would:

- depth on ``/camera/depth/image_rect_raw`` as ``sensor_msgs/Image`` (``16UC1`` millimetres or
  ``32FC1`` metres; optionally big-endian or with padded rows), or on
  ``/camera/depth/image_rect_raw/compressedDepth`` as ``sensor_msgs/CompressedImage`` (16-bit
  PNG, plain ``png`` or image_transport's ``compressedDepth`` with its 12-byte header);
- ``/camera/depth/camera_info`` (``sensor_msgs/CameraInfo``) with every image, recorded just
  after it;
- the TF tree ``map -> odom -> base_link -> camera_link -> camera_depth_optical_frame``:
  ``/tf_static`` (latched in ROS 1, transient-local in rosbag2) holds base_link -> camera_link
  and camera_link -> camera_depth_optical_frame (the REP-103 optical rotation, unless
  ``optical_rotation=False``: the bug the wrong-TF check must catch); ``/tf`` holds
  ``map -> odom`` at 10 Hz (constant) and ``odom -> base_link`` at ``tf_hz`` (50 Hz by default,
  phase-shifted so that no sample falls on an image stamp unless ``tf_at_images``);
- optionally ``/odom`` (``nav_msgs/Odometry``, odom -> base_link) for the pose-topic mode.

The map frame is z-up (REP-103): ``T_map_world`` places the source's world in it (for 7-Scenes
the gravity alignment of :func:`gravity_alignment`). The base_link trajectory between images
is the piecewise-geodesic one through the images' poses (linear translation, slerp rotation),
so a TF lookup between two samples of one image interval is exact; across an image stamp it is
off by at most the bound of :func:`interpolation_bound`.

The returned :class:`WrittenBag` has what a test compares against: the stamps (s) and
``T_WC`` in the map frame of every recorded image."""

from __future__ import annotations

import heapq
import io
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

FORMATS = ("sqlite3", "mcap", "ros1")
ENCODINGS = ("16UC1", "32FC1", "png", "compressedDepth")
DEPTH_TOPIC = "/camera/depth/image_rect_raw"
INFO_TOPIC = "/camera/depth/camera_info"
OPTICAL_FRAME = "camera_depth_optical_frame"
START_NS = 1_700_000_000 * 1_000_000_000

# camera_link -> optical: REP-103 (z forward, x right, y down in a x forward, y left, z up link)
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _T(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


T_BASE_LINK = _T(Rotation.from_euler("y", 5, degrees=True).as_matrix(), (0.12, 0.0, 0.45))  # base -> camera_link
T_LINK_OPTICAL = _T(R_LINK_OPTICAL, (0.0, 0.015, 0.0))  # camera_link -> optical
T_MAP_ODOM = _T(Rotation.from_euler("z", 17, degrees=True).as_matrix(), (0.4, -0.3, 0.0))


def path_for(folder: Path, fmt: str, name: str = "rec") -> Path:
    """Where a bag of that format goes: a rosbag2 folder for sqlite3/mcap, a .bag file for ROS 1."""
    return Path(folder) / (f"{name}.bag" if fmt == "ros1" else f"{name}_{fmt}")


def gravity_alignment(gravity_W) -> np.ndarray:
    """T_map_W: a rotation taking the world's gravity direction (pointing down) to -z."""
    g = np.asarray(gravity_W, dtype=np.float64).ravel()[:3]
    g = g / np.linalg.norm(g)
    R, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [g])
    return _T(R.as_matrix())


def sevenscenes_alignment(root: Path) -> np.ndarray:
    """T_map_W for the 7-Scenes folder: its gravity-direction.txt (sign checked against the
    cameras: their image 'down' axis must point roughly along gravity)."""
    from aisdf.datasets import open_dataset

    g = np.loadtxt(Path(root) / "gravity-direction.txt").ravel()[:3]
    ds = open_dataset("7scenes", root)
    down = np.mean([ds.frame(i)["T_WC"][:3, 1] for i in range(0, len(ds), max(1, len(ds) // 10))], axis=0)
    return gravity_alignment(g if g @ down > 0 else -g)


@dataclass
class WrittenBag:
    path: Path
    fmt: str
    encoding: str
    stamps: list[float] = field(default_factory=list)  # header stamps, seconds
    T_WC: list[np.ndarray] = field(default_factory=list)  # expected, in the map frame
    frame_ids: list[int] = field(default_factory=list)  # the source's frame ids
    T_map_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    tf_stamps_ns: list[int] = field(default_factory=list)  # odom -> base_link samples
    image_stamps_ns: list[int] = field(default_factory=list)


class _Trajectory:
    """Piecewise-geodesic base_link poses through the images' poses (constant before the first
    and after the last)."""

    def __init__(self):
        self.t: list[int] = []
        self.T: list[np.ndarray] = []

    def add(self, t_ns: int, T: np.ndarray) -> None:
        self.t.append(t_ns)
        self.T.append(T)

    def at(self, t_ns: int) -> np.ndarray:
        t = self.t
        if t_ns <= t[0]:
            return self.T[0]
        if t_ns >= t[-1]:
            return self.T[-1]
        i = int(np.searchsorted(t, t_ns, side="right"))
        a = (t_ns - t[i - 1]) / (t[i] - t[i - 1])
        A, B = self.T[i - 1], self.T[i]
        s = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))
        return _T(s([a]).as_matrix()[0], (1 - a) * A[:3, 3] + a * B[:3, 3])


def _typestore(fmt: str):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # rosbags' ROS 1 store lacks tf2_msgs
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


class _Msgs:
    """Message builders for one type store (ROS 1 and ROS 2 differ in Header and CameraInfo)."""

    def __init__(self, fmt: str):
        self.fmt, self.ts = fmt, _typestore(fmt)
        self.ros1 = fmt == "ros1"
        self.seq = 0

    def t(self, name):
        return self.ts.types[name]

    def time(self, ns: int):
        return self.t("builtin_interfaces/msg/Time")(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))

    def header(self, ns: int, frame: str):
        H = self.t("std_msgs/msg/Header")
        if self.ros1:
            self.seq += 1
            return H(seq=self.seq, stamp=self.time(ns), frame_id=frame)
        return H(stamp=self.time(ns), frame_id=frame)

    def transform(self, T: np.ndarray):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        V, Q = self.t("geometry_msgs/msg/Vector3"), self.t("geometry_msgs/msg/Quaternion")
        return self.t("geometry_msgs/msg/Transform")(translation=V(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                                       rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))

    def tf(self, items):
        TS = self.t("geometry_msgs/msg/TransformStamped")
        return self.t("tf2_msgs/msg/TFMessage")(transforms=[
            TS(header=self.header(ns, parent), child_frame_id=child, transform=self.transform(T))
            for parent, child, ns, T in items])

    def odometry(self, ns: int, T: np.ndarray):
        g = "geometry_msgs/msg/"
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        pose = self.t(g + "Pose")(position=self.t(g + "Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                  orientation=self.t(g + "Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]))
        V = self.t(g + "Vector3")
        return self.t("nav_msgs/msg/Odometry")(
            header=self.header(ns, "odom"), child_frame_id="base_link",
            pose=self.t(g + "PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
            twist=self.t(g + "TwistWithCovariance")(twist=self.t(g + "Twist")(linear=V(x=0.0, y=0.0, z=0.0),
                                                                              angular=V(x=0.0, y=0.0, z=0.0)),
                                                    covariance=np.zeros(36)))

    def camera_info(self, ns: int, K: np.ndarray, H: int, W: int):
        k = np.asarray(K, np.float64).reshape(9)
        P = np.zeros((3, 4))
        P[:, :3] = np.asarray(K).reshape(3, 3)
        roi = self.t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        fields = dict(zip(names, (np.zeros(5), k, np.eye(3).reshape(9), P.reshape(12))))
        return self.t("sensor_msgs/msg/CameraInfo")(
            header=self.header(ns, OPTICAL_FRAME), height=H, width=W, distortion_model="plumb_bob",
            binning_x=0, binning_y=0, roi=roi, **fields)

    def depth(self, ns: int, depth: np.ndarray, encoding: str, big_endian: bool, row_pad: int):
        H, W = depth.shape
        if encoding in ("16UC1", "32FC1"):
            if encoding == "16UC1":
                arr = np.clip(np.round(np.nan_to_num(depth) * 1000.0), 0, 65535).astype(">u2" if big_endian else "<u2")
            else:
                arr = np.nan_to_num(depth).astype(">f4" if big_endian else "<f4")
            raw = arr.view(np.uint8).reshape(H, -1)
            if row_pad:
                raw = np.concatenate([raw, np.zeros((H, row_pad), np.uint8)], axis=1)
            return "sensor_msgs/msg/Image", self.t("sensor_msgs/msg/Image")(
                header=self.header(ns, OPTICAL_FRAME), height=H, width=W, encoding=encoding,
                is_bigendian=int(big_endian), step=raw.shape[1], data=np.ascontiguousarray(raw).reshape(-1))
        from PIL import Image

        mm = np.clip(np.round(np.nan_to_num(depth) * 1000.0), 0, 65535).astype(np.uint16)
        buf = io.BytesIO()
        Image.fromarray(mm).save(buf, format="PNG")
        data, fmt = buf.getvalue(), "16UC1; png"
        if encoding == "compressedDepth":
            data, fmt = struct.pack("<iff", 0, 0.0, 0.0) + data, "16UC1; compressedDepth png"
        return "sensor_msgs/msg/CompressedImage", self.t("sensor_msgs/msg/CompressedImage")(
            header=self.header(ns, OPTICAL_FRAME), format=fmt, data=np.frombuffer(data, np.uint8))

    def serialize(self, msg, msgtype: str) -> bytes:
        return bytes(self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype))


class _Out:
    """One writer over the three formats, fed (bag time, topic, msgtype, msg) in any order
    within a horizon: ``flush(upto)`` writes everything recorded before ``upto`` in time order."""

    def __init__(self, path: Path, fmt: str, msgs: _Msgs):
        self.fmt, self.msgs = fmt, msgs
        self.conns: dict[str, object] = {}
        self.heap: list = []
        self.n = 0
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.w = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer(path, version=9, storage_plugin=plugin)
        self.w.open()

    def conn(self, topic: str, msgtype: str, latched: bool = False):
        if topic not in self.conns:
            if self.fmt == "ros1":
                self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.msgs.ts,
                                                          latching=1 if latched else None)
            else:
                qos = ()
                if latched:
                    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                                    QosTime)

                    zero = QosTime(sec=0, nsec=0)
                    qos = (Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                               zero, zero, QosLiveliness.AUTOMATIC, zero, False),)
                self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.msgs.ts,
                                                          offered_qos_profiles=qos)
        return self.conns[topic]

    def put(self, bag_ns: int, topic: str, msgtype: str, msg, latched: bool = False) -> None:
        c = self.conn(topic, msgtype, latched)
        self.n += 1
        heapq.heappush(self.heap, (bag_ns, self.n, c, self.msgs.serialize(msg, msgtype)))

    def flush(self, upto: int | None = None) -> None:
        while self.heap and (upto is None or self.heap[0][0] < upto):
            bag_ns, _, c, data = heapq.heappop(self.heap)
            self.w.write(c, bag_ns, data)

    def close(self) -> None:
        self.flush()
        self.w.close()


def write_bag(path, source, fmt: str = "mcap", *, encoding: str = "16UC1", T_map_world=None,
              tf_hz: float = 50.0, tf_phase_s: float = 0.0071, tf_at_images: bool = False,
              optical_rotation: bool = True, tf_first_frame: int = 0, tf_last_frame: int | None = None,
              odom_topic: bool = False, big_endian: bool = False, row_pad: int = 0, max_frames: int | None = None,
              stride: int = 1, start_ns: int = START_NS, no_static: bool = False,
              second_camera: bool = False) -> WrittenBag:
    """Record ``source`` (frames ``0, stride, ...``, at most ``max_frames``) into ``path``.

    ``tf_first_frame``/``tf_last_frame``: odom -> base_link samples exist only from just after
    the image before ``tf_first_frame`` to just before the image after ``tf_last_frame``
    (recorded frames' indices): the images outside cannot be placed (stamp outside the TF
    buffer). ``no_static``: no ``/tf_static`` at all (every frame misses a transform).
    ``second_camera``: the same depth also on ``/camera/aligned_depth_to_color/image_raw`` with
    its own camera info (two depth topics: discovery must ask which)."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: one of {FORMATS}")
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding {encoding!r}: one of {ENCODINGS}")
    path = Path(path)
    T_mw = np.eye(4) if T_map_world is None else np.asarray(T_map_world, np.float64)
    T_base_opt = T_BASE_LINK @ T_LINK_OPTICAL
    T_link_opt_written = T_LINK_OPTICAL if optical_rotation else _T(None, T_LINK_OPTICAL[:3, 3])
    indices = list(range(0, len(source), stride))[:max_frames]
    msgs = _Msgs(fmt)
    out = _Out(path, fmt, msgs)
    wb = WrittenBag(path, fmt, encoding, T_map_world=T_mw)
    depth_topic = DEPTH_TOPIC if encoding in ("16UC1", "32FC1") else DEPTH_TOPIC + "/compressedDepth"
    traj = _Trajectory()
    period = int(round(1e9 / tf_hz))
    phase = int(round(tf_phase_s * 1e9))
    next_tf = None  # next odom -> base_link sample time
    next_map = None  # next map -> odom sample time (10 Hz)
    pending_image = None
    T_odom_map = np.linalg.inv(T_MAP_ODOM)
    lo_ns = float("inf") if tf_first_frame > 0 else None  # odom->base samples kept within (lo, hi)
    hi_ns = None

    def emit_tf_until(t_end: int) -> None:
        nonlocal next_tf, next_map
        while next_tf <= t_end:
            if (lo_ns is None or next_tf > lo_ns) and (hi_ns is None or next_tf < hi_ns):
                T = traj.at(next_tf)
                out.put(next_tf + 1_000_000, "/tf", "tf2_msgs/msg/TFMessage",
                        msgs.tf([("odom", "base_link", next_tf, T)]))
                wb.tf_stamps_ns.append(next_tf)
                if odom_topic:
                    out.put(next_tf + 1_500_000, "/odom", "nav_msgs/msg/Odometry", msgs.odometry(next_tf, T))
            next_tf += period
        while next_map <= t_end:
            out.put(next_map + 800_000, "/tf", "tf2_msgs/msg/TFMessage",
                    msgs.tf([("map", "odom", next_map, T_MAP_ODOM)]))
            next_map += 100_000_000

    for n, i in enumerate(indices):
        f = source.frame(i)
        t_ns = start_ns + int(round(float(f["stamp"]) * 1e9))
        T_map_C = T_mw @ np.asarray(f["T_WC"], np.float64)
        T_odom_base = T_odom_map @ T_map_C @ np.linalg.inv(T_base_opt)
        if n == 0:
            next_tf = t_ns - 100_000_000 + (0 if tf_at_images else phase)
            next_map = t_ns - 100_000_000
            if not no_static:
                out.put(t_ns - 150_000_000, "/tf_static", "tf2_msgs/msg/TFMessage",
                        msgs.tf([("base_link", "camera_link", t_ns - 150_000_000, T_BASE_LINK),
                                 ("camera_link", OPTICAL_FRAME, t_ns - 150_000_000, T_link_opt_written)]),
                        latched=True)
        if n == tf_first_frame and n > 0:
            lo_ns = traj.t[-1]
        if tf_last_frame is not None and n == tf_last_frame + 1:
            hi_ns = t_ns
        traj.add(t_ns, T_odom_base)
        # TF samples up to this image's stamp are known now (the trajectory reaches it).
        emit_tf_until(t_ns - 1)
        if tf_at_images and (lo_ns is None or t_ns > lo_ns) and (hi_ns is None or t_ns < hi_ns):
            out.put(t_ns + 1_000_000, "/tf", "tf2_msgs/msg/TFMessage",
                    msgs.tf([("odom", "base_link", t_ns, T_odom_base)]))
            wb.tf_stamps_ns.append(t_ns)
            if odom_topic:
                out.put(t_ns + 1_500_000, "/odom", "nav_msgs/msg/Odometry", msgs.odometry(t_ns, T_odom_base))
        if pending_image is not None:
            out.put(*pending_image)
        depth = np.asarray(f["depth"], np.float32)
        msgtype, msg = msgs.depth(t_ns, depth, encoding, big_endian, row_pad)
        out.put(t_ns + 4_000_000, INFO_TOPIC, "sensor_msgs/msg/CameraInfo",
                msgs.camera_info(t_ns, f["K"], *depth.shape))
        pending_image = (t_ns + 3_000_000, depth_topic, msgtype, msg)
        if second_camera:
            ns2 = "/camera/aligned_depth_to_color"
            out.put(t_ns + 3_500_000, ns2 + "/image_raw", *msgs.depth(t_ns, depth, encoding, big_endian, row_pad))
            out.put(t_ns + 4_500_000, ns2 + "/camera_info", "sensor_msgs/msg/CameraInfo",
                    msgs.camera_info(t_ns, f["K"], *depth.shape))
        out.flush(t_ns)
        wb.stamps.append(t_ns * 1e-9)
        wb.image_stamps_ns.append(t_ns)
        wb.T_WC.append(T_map_C)
        wb.frame_ids.append(int(f["frame_id"]))
    if pending_image is not None:
        out.put(*pending_image)
    emit_tf_until(wb.image_stamps_ns[-1] + 100_000_000)
    out.close()
    return wb


def interpolation_bound(wb: WrittenBag) -> tuple[np.ndarray, np.ndarray]:
    """Per image: an upper bound on the error (metres, radians) of the camera pose interpolated
    from the odom -> base_link samples around its stamp, against the recorded pose.

    Within one image interval the samples lie on one geodesic segment (exact). Across image k,
    interpolating between samples at ``a < t_k < b`` replaces the corner of the piecewise-linear
    path by its chord: translation error <= |v_after - v_before| * (t_k - a)(b - t_k)/(b - a),
    rotation error <= |w_after - w_before| * the same factor (first order), and the camera's
    offset from base_link adds |rotation error| * |offset|."""
    T_bo = T_BASE_LINK @ T_LINK_OPTICAL
    lever = float(np.linalg.norm(T_bo[:3, 3]))
    ts = np.asarray(wb.tf_stamps_ns)
    stamps = np.asarray(wb.image_stamps_ns)
    T_b = [np.linalg.inv(T_MAP_ODOM) @ T @ np.linalg.inv(T_bo) for T in wb.T_WC]
    et, er = np.zeros(len(stamps)), np.zeros(len(stamps))
    zero = np.zeros(3)
    for k, t in enumerate(stamps):
        j = np.searchsorted(ts, t)
        if np.any(ts == t) or j == 0 or j >= len(ts):
            continue
        a, b = ts[j - 1], ts[j]
        f = (t - a) * (b - t) / (b - a) * 1e-9
        v0 = w0 = v1 = w1 = zero  # the trajectory is constant before the first and after the last image
        if k > 0:
            dt0 = (stamps[k] - stamps[k - 1]) * 1e-9
            v0 = (T_b[k][:3, 3] - T_b[k - 1][:3, 3]) / dt0
            w0 = Rotation.from_matrix(T_b[k - 1][:3, :3].T @ T_b[k][:3, :3]).as_rotvec() / dt0
        if k < len(stamps) - 1:
            dt1 = (stamps[k + 1] - stamps[k]) * 1e-9
            v1 = (T_b[k + 1][:3, 3] - T_b[k][:3, 3]) / dt1
            w1 = Rotation.from_matrix(T_b[k][:3, :3].T @ T_b[k + 1][:3, :3]).as_rotvec() / dt1
        er[k] = np.linalg.norm(T_b[k][:3, :3] @ (w1 - w0)) * f
        et[k] = np.linalg.norm(v1 - v0) * f + er[k] * lever
    return et, er
