"""Play a live ROS 2 robot over rmw_zenoh: the built-in synthetic building, or a recording.

    python -m aisdf.ros.replay                                   # the synthetic office, 30 fps
    python -m aisdf.ros.replay --connect tcp/127.0.0.1:7447 --building atlanta --n-frames 600
    python -m aisdf.ros.replay --bag run1                        # a rosbag2 recording (.mcap/.db3)

It is a ROS 2 node (``aisdf_robot``) that follows rmw_zenoh's design (:mod:`aisdf.ros.rmw_zenoh`:
data keys with the type hash, attachments, liveliness tokens, CDR). The synthetic robot
publishes, stamped from the wall clock at its start:

* ``/camera/depth/image_rect_raw`` (``sensor_msgs/Image``, ``32FC1`` metres with NaN for no
  measurement, or ``--encoding 16UC1`` millimetres), ``header.frame_id`` =
  ``camera_depth_optical_frame``, and ``/camera/depth/camera_info`` with each image;
* ``/tf``: ``odom -> base_link`` at twice the image rate (at every image stamp and half-way
  between, slerp-interpolated), ``map -> odom`` at 5 Hz (a fixed offset: localisation);
* ``/tf_static`` (transient local, published once at start: late subscribers get it from the
  publisher's cache): ``base_link -> camera_link`` (the camera 0.2 m ahead, 0.3 m up) and
  ``camera_link -> camera_depth_optical_frame``, REP 103's optical rotation
  (quaternion x, y, z, w = -0.5, 0.5, -0.5, 0.5).

The chain ``map -> odom -> base_link -> camera_link -> camera_depth_optical_frame`` composes to
the sequence's camera pose ``T_WC`` exactly at every image stamp (``map`` = the sequence's world
frame), so a subscriber that handles TF right recovers the synthetic frames to float precision.

A rosbag2 recording is republished message by message at its recorded pace (``--rate`` to
speed it up), its CDR as recorded, ``/tf_static`` as transient local (ROS 1 bags are refused).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from . import rmw_zenoh as rz

log = logging.getLogger("aisdf.ros.replay")

DEPTH_TOPIC = "/camera/depth/image_rect_raw"
INFO_TOPIC = "/camera/depth/camera_info"
OPTICAL_FRAME = "camera_depth_optical_frame"
Q_CAMERA_LINK_OPTICAL = (-0.5, 0.5, -0.5, 0.5)  # x, y, z, w (REP 103)
T_BASE_CAMERA_LINK = np.array([[1.0, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0.3], [0, 0, 0, 1]])
T_MAP_ODOM = np.array([[0.0, -1, 0, 1.5], [1, 0, 0, -0.7], [0, 0, 1, 0.0], [0, 0, 0, 1]])  # 90 deg yaw + offset


def matrix(q_xyzw, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
    T[:3, 3] = t
    return T


T_CAMERA_LINK_OPTICAL = matrix(Q_CAMERA_LINK_OPTICAL)


class Messages:
    """Builders of the ROS 2 messages (rosbags' classes of a typestore)."""

    def __init__(self, typestore):
        self.ts = typestore
        self.t = typestore.types

    def time(self, ns: int):
        return self.t["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))

    def header(self, ns: int, frame: str):
        return self.t["std_msgs/msg/Header"](stamp=self.time(ns), frame_id=frame)

    def transform(self, ns: int, parent: str, child: str, T: np.ndarray):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        V, Q = self.t["geometry_msgs/msg/Vector3"], self.t["geometry_msgs/msg/Quaternion"]
        tf = self.t["geometry_msgs/msg/Transform"](translation=V(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                                                   rotation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3])))
        return self.t["geometry_msgs/msg/TransformStamped"](header=self.header(ns, parent), child_frame_id=child,
                                                            transform=tf)

    def tf(self, transforms):
        return self.t["tf2_msgs/msg/TFMessage"](transforms=list(transforms))

    def depth_image(self, ns: int, depth: np.ndarray, encoding: str = "32FC1"):
        H, W = depth.shape
        if encoding == "32FC1":
            data = np.where(depth > 0, depth, np.nan).astype("<f4")
        elif encoding == "16UC1":
            data = np.clip(np.round(np.nan_to_num(depth) * 1000.0), 0, 65535).astype("<u2")
        else:
            raise ValueError(f"encoding {encoding!r}: 32FC1 or 16UC1")
        return self.t["sensor_msgs/msg/Image"](header=self.header(ns, OPTICAL_FRAME), height=H, width=W,
                                               encoding=encoding, is_bigendian=0, step=W * data.itemsize,
                                               data=np.frombuffer(data.tobytes(), np.uint8))

    def camera_info(self, ns: int, K: np.ndarray, H: int, W: int):
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(ns, OPTICAL_FRAME), height=H, width=W, distortion_model="plumb_bob",
            d=np.zeros(5), k=np.asarray(K, np.float64).reshape(9), r=np.eye(3).reshape(9), p=P.reshape(12),
            binning_x=0, binning_y=0, roi=roi)


def synthetic_events(seq, t0_ns: int, n_frames: int | None = None, map_odom_hz: float = 5.0):
    """The synthetic robot's messages in stamp order: ``(stamp_ns, kind, payload)`` with kind
    ``tf`` (list of (parent, child, T)) or ``image`` (the frame index). At equal stamps the
    transforms come first, as a robot's TF precedes (or accompanies) its images."""
    n = len(seq) if n_frames is None else min(n_frames, len(seq))
    fps = seq.fps
    T_base_opt = T_BASE_CAMERA_LINK @ T_CAMERA_LINK_OPTICAL
    T_odom_map = np.linalg.inv(T_MAP_ODOM)

    def odom_base(T_WC):
        return T_odom_map @ T_WC @ np.linalg.inv(T_base_opt)

    def ns(t_s: float) -> int:
        return t0_ns + int(round(t_s * 1e9))

    events = []
    poses = [seq.poses[i] for i in range(n)]
    for i in range(n):
        events.append((ns(i / fps), 0, "tf", [("odom", "base_link", odom_base(poses[i]))]))
        events.append((ns(i / fps), 2, "image", i))
        if i + 1 < n:  # half-way sample: slerp rotation, linear translation (TF's interpolation)
            A, B = odom_base(poses[i]), odom_base(poses[i + 1])
            M = np.eye(4)
            M[:3, :3] = Slerp([0, 1], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))([0.5]).as_matrix()[0]
            M[:3, 3] = 0.5 * (A[:3, 3] + B[:3, 3])
            events.append((ns((i + 0.5) / fps), 0, "tf", [("odom", "base_link", M)]))
    duration = (n - 1) / fps
    k, period = 0, 1.0 / map_odom_hz
    while True:  # map -> odom from before the first image to after the last one
        t = k * period
        events.append((ns(t), 1, "tf", [("map", "odom", T_MAP_ODOM)]))
        if t >= duration:
            break
        k += 1
    events.sort(key=lambda e: (e[0], e[1]))
    return [(s, kind, payload) for s, _o, kind, payload in events]


class SyntheticRobot:
    """Publishes a :class:`aisdf.synthetic.SyntheticSequence` as a ROS 2 robot on a session."""

    def __init__(self, session, seq, domain_id: int = 0, distro: str = "jazzy", encoding: str = "32FC1",
                 node_name: str = "aisdf_robot", optical_rotation: bool = True):
        self.seq, self.encoding = seq, encoding
        self.optical_rotation = optical_rotation  # False: a broken robot whose TF lacks it (tests)
        self.node = rz.Node(session, node_name, "/", domain_id, distro)
        self.msgs = Messages(self.node.typestore)
        self.pub_depth = self.node.create_publisher(DEPTH_TOPIC, "sensor_msgs/msg/Image", rz.QoS(depth=10))
        self.pub_info = self.node.create_publisher(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", rz.QoS(depth=10))
        self.pub_tf = self.node.create_publisher("/tf", "tf2_msgs/msg/TFMessage", rz.TF_QOS)
        self.pub_static = self.node.create_publisher("/tf_static", "tf2_msgs/msg/TFMessage", rz.TF_STATIC_QOS)
        self.published = {"images": 0, "tf": 0}

    def publish_static(self, t0_ns: int) -> None:
        m = self.msgs
        self.pub_static.publish(m.tf([m.transform(t0_ns, "base_link", "camera_link", T_BASE_CAMERA_LINK),
                                      m.transform(t0_ns, "camera_link", OPTICAL_FRAME,
                                                  T_CAMERA_LINK_OPTICAL if self.optical_rotation else np.eye(4))]))

    def run(self, stop: threading.Event, n_frames: int | None = None, rate: float = 1.0,
            t0_ns: int | None = None, garbage_after: int | None = None) -> dict:
        """Publish at ``rate`` times the sensor's pace (0 = as fast as possible) until done or
        ``stop``. ``garbage_after``: after that many images, also put one malformed payload on
        the depth key (tests: a subscriber must drop it and go on)."""
        t0_ns = time.time_ns() if t0_ns is None else t0_ns
        self.publish_static(t0_ns)
        events = synthetic_events(self.seq, t0_ns, n_frames)
        m = self.msgs
        start = time.monotonic()
        for stamp, kind, payload in events:
            if stop.is_set():
                break
            if rate > 0:
                wait = (stamp - t0_ns) * 1e-9 / rate - (time.monotonic() - start)
                if wait > 0 and stop.wait(wait):
                    break
            if kind == "tf":
                self.pub_tf.publish(m.tf([m.transform(stamp, p, c, T) for p, c, T in payload]))
                self.published["tf"] += 1
            else:
                f = self.seq.frame(payload)
                H, W = f["depth"].shape
                self.pub_info.publish(m.camera_info(stamp, f["K"], H, W))
                self.pub_depth.publish(m.depth_image(stamp, f["depth"], self.encoding))
                self.published["images"] += 1
                if garbage_after is not None and self.published["images"] == garbage_after:
                    self.pub_depth.publish_raw(b"\x00\x01\x00\x00not a depth image")
        self.published["t0_ns"] = t0_ns
        return self.published

    def close(self) -> None:
        self.node.close()


def replay_bag(session, path, stop: threading.Event, domain_id: int = 0, distro: str = "jazzy",
               rate: float = 1.0, topics: list[str] | None = None) -> dict:
    """Republish a rosbag2 recording's messages (their CDR as recorded) at ``rate`` times their
    recorded pace (0: as fast as possible); ``/tf_static`` as transient local. ROS 1 bags are
    refused: their messages (e.g. a Header with ``seq``) are not ROS 2 messages."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader

    if Path(path).suffix == ".bag":
        raise ValueError(f"{path}: a ROS 1 bag; only rosbag2 recordings (.mcap, .db3) can be replayed as ROS 2")
    node = rz.Node(session, "aisdf_bag_player", "/", domain_id, distro)
    pubs: dict = {}
    n = 0
    try:
        with AnyReader([Path(path)], default_typestore=node.typestore) as reader:
            conns = [c for c in reader.connections if not topics or c.topic in topics]
            start, first = time.monotonic(), None
            for conn, t_ns, raw in reader.messages(connections=conns):
                if stop.is_set():
                    break
                first = t_ns if first is None else first
                if rate > 0:
                    wait = (t_ns - first) * 1e-9 / rate - (time.monotonic() - start)
                    if wait > 0 and stop.wait(wait):
                        break
                key = (conn.topic, conn.msgtype)
                if key not in pubs:
                    qos = rz.TF_STATIC_QOS if conn.topic == "/tf_static" else rz.QoS(depth=10)
                    pubs[key] = node.create_publisher(conn.topic, conn.msgtype, qos)
                pubs[key].publish_raw(raw)
                n += 1
    finally:
        node.close()
    return {"messages": n, "topics": sorted(t for t, _ in pubs)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m aisdf.ros.replay", description=__doc__.split("\n\n")[0])
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help=f"Zenoh router of the ROS 2 network (repeatable; default {rz.DEFAULT_ROUTER})")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh session configuration (as ZENOH_SESSION_CONFIG_URI)")
    p.add_argument("--domain-id", type=int, default=rz.domain_from_env(),
                   help="ROS_DOMAIN_ID (default $ROS_DOMAIN_ID or 0)")
    p.add_argument("--distro", default="jazzy", choices=sorted(rz.TYPESTORES),
                   help="message definitions and key form (humble: TypeHashNotSupported)")
    p.add_argument("--bag", help="replay this recording instead of the synthetic robot")
    p.add_argument("--building", default="office")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--n-frames", type=int, default=900)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--no-noise", action="store_true", help="exact depth (no Kinect noise model)")
    p.add_argument("--world-frame", default="tilted", choices=["tilted", "identity"],
                   help="the building's world (= map) frame: tilted (as the frontend's synthetic source) or "
                   "identity (z up, as REP 105 asks of map)")
    p.add_argument("--encoding", default="32FC1", choices=["32FC1", "16UC1"])
    p.add_argument("--rate", type=float, default=1.0, help="times the sensor's pace (0: as fast as possible)")
    p.add_argument("--wait-subscriber", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds for subscriptions to the depth, camera info and /tf topics")
    p.add_argument("--garbage-after", type=int, help=argparse.SUPPRESS)
    p.add_argument("--no-optical-rotation", action="store_true",
                   help="a broken robot: /tf_static without the camera_link -> optical rotation (tests)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s replay %(levelname)s %(message)s")
    from aisdf.config import stop_event

    stop = stop_event("replay")
    session = rz.open_ros_session(args.connect, args.zenoh_config)
    try:
        if args.bag:
            try:
                out = replay_bag(session, args.bag, stop, args.domain_id, args.distro, args.rate)
            except Exception as e:  # noqa: BLE001 - a bad recording: say why, exit 2
                log.error("cannot replay %s: %s: %s", args.bag, type(e).__name__, e)
                return 2
            log.info("replayed %d messages on %s", out["messages"], ", ".join(out["topics"]))
            return 0
        from aisdf.synthetic import SyntheticSequence

        seq = SyntheticSequence(building=args.building, n_frames=args.n_frames, H=args.height, W=args.width,
                                fps=args.fps, noise=not args.no_noise, seed=args.seed, world_frame=args.world_frame)
        robot = SyntheticRobot(session, seq, args.domain_id, args.distro, args.encoding,
                               optical_rotation=not args.no_optical_rotation)
        try:
            if args.wait_subscriber > 0:  # a subscriber to images, camera info and /tf
                end, wanted = time.monotonic() + args.wait_subscriber, {DEPTH_TOPIC, INFO_TOPIC, "/tf"}
                while not stop.is_set() and time.monotonic() < end and not wanted <= {
                        e.topic for e in rz.discover(session, args.domain_id, timeout=0.5)
                        if e.kind == rz.SUBSCRIPTION}:
                    time.sleep(0.2)
            log.info("publishing the synthetic %r building (%d frames, %.0f fps x %.1f) on domain %d",
                     args.building, len(seq), args.fps, args.rate, args.domain_id)
            out = robot.run(stop, rate=args.rate, garbage_after=args.garbage_after)
            log.info("published %d images and %d TF messages", out["images"], out["tf"])
            time.sleep(0.5)  # let the last messages leave
        finally:
            robot.close()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
