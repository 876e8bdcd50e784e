"""A live ROS 2 robot as a frame source, over rmw_zenoh.

:class:`Ros2Source` joins the robot's Zenoh network as a ROS 2 node (its own Zenoh session,
configured as rmw_zenoh's sessions are: peer, connected to the robot's router), subscribes to
the depth image, the camera info, ``/tf`` and ``/tf_static`` (transient local: the static
transforms published before it joined are fetched from the publishers' caches), and turns the
messages into posed frames with :class:`aisdf.ros.assemble.FrameAssembler` (the same frame
handling as the rosbag source: the chain from the fixed frame to the image's frame,
interpolated at the image's stamp; frames that cannot be placed are skipped and counted).

Before mapping, the TF chain is checked on the first frames (``tf_check``, the rosbag
source's check: the image's "down" against the fixed frame's -z, and depth consistency between
frames; a robot whose chain lacks the optical rotation is refused in words).

It is a *live* source (``live = True``): no ``len()``, no random access; ``frames(stop)``
yields frames as they are assembled and ends when ``stop`` is set, or after ``idle_timeout_s``
without a depth image (once one has arrived), or after ``max_frames`` images."""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Iterator

from . import rmw_zenoh as rz
from .assemble import FrameAssembler
from .follow import MapOdomFollower

log = logging.getLogger("aisdf.ros.live")

TF_TYPE = "tf2_msgs/msg/TFMessage"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DEPTH_TYPES = {"image": "sensor_msgs/msg/Image", "compressed": "sensor_msgs/msg/CompressedImage"}


class Ros2Source:
    live = True

    def __init__(self, *, depth_topic: str = "/camera/depth/image_rect_raw",
                 info_topic: str = "/camera/depth/camera_info", fixed_frame: str = "map",
                 camera_frame: str | None = None, tf_topic: str = "/tf", tf_static_topic: str = "/tf_static",
                 depth_type: str = "image", domain_id: int = 0, distro: str = "jazzy",
                 connect: list[str] | None = None, zenoh_config: str | None = None,
                 node_name: str = "aisdf_frontend", node_namespace: str = "/", idle_timeout_s: float | None = None,
                 max_wait_s: float = 1.0, queue_max: int = 2000, tf_check: bool = True, tf_check_window: int = 90,
                 session=None, odom_frame: str | None = None, follow_mode: str = "stamp",
                 follow_keyframes: int = 5000, follow_min_m: float = 0.01, follow_min_deg: float = 0.5):
        if depth_type not in DEPTH_TYPES:
            raise ValueError(f"depth_type {depth_type!r}: choose one of {sorted(DEPTH_TYPES)}")
        self.depth_topic = rz.qualify(depth_topic)
        self.info_topic = rz.qualify(info_topic)
        self.tf_topic, self.tf_static_topic = rz.qualify(tf_topic), rz.qualify(tf_static_topic)
        self.depth_msgtype = DEPTH_TYPES[depth_type]
        self.idle_timeout_s = idle_timeout_s
        self.tf_check, self.tf_check_window = tf_check, max(2, int(tf_check_window))
        self.tf_verdict = None
        self.assembler = FrameAssembler(self.depth_topic, self.info_topic, fixed_frame, camera_frame=camera_frame,
                                        tf_topics=(self.tf_topic,), static_tf_topics=(self.tf_static_topic,),
                                        max_wait_s=max_wait_s)
        # protocol 1.11: with an odom frame, the keyframes sent follow map -> odom corrections (follow.py)
        self.follower = None if not odom_frame else MapOdomFollower(
            self.assembler.tf, fixed_frame, odom_frame, mode=follow_mode, max_keyframes=follow_keyframes,
            min_m=follow_min_m, min_deg=follow_min_deg)
        self._queue: queue.Queue = queue.Queue(maxsize=queue_max)
        self.dropped = 0  # messages lost because the frame loop fell behind by queue_max
        self._own_session = session is None
        self.session = session if session is not None else rz.open_ros_session(connect, zenoh_config)
        try:
            self.node = rz.Node(self.session, node_name, node_namespace, domain_id, distro)
            sub = self.node.create_subscription
            self.subs = {
                "depth": sub(self.depth_topic, self.depth_msgtype, self._cb(self.depth_topic, self.depth_msgtype),
                             rz.QoS(depth=10)),
                "info": sub(self.info_topic, INFO_TYPE, self._cb(self.info_topic, INFO_TYPE), rz.QoS(depth=10)),
                "tf": sub(self.tf_topic, TF_TYPE, self._cb(self.tf_topic, TF_TYPE), rz.TF_QOS),
                "tf_static": sub(self.tf_static_topic, TF_TYPE, self._cb(self.tf_static_topic, TF_TYPE),
                                 rz.TF_STATIC_LISTENER_QOS),
            }
        except Exception:
            self.close()
            raise
        log.info("ROS 2 node %s on domain %d (%s keys): depth %s (%s), camera info %s, TF %s + %s, fixed frame %r",
                 node_name, domain_id, distro, self.depth_topic, self.depth_msgtype, self.info_topic, self.tf_topic,
                 self.tf_static_topic, fixed_frame)

    def _cb(self, topic: str, msgtype: str):
        def on_message(msg, info: rz.MessageInfo) -> None:
            try:
                self._queue.put_nowait((topic, msgtype, info.received_ns, msg))
            except queue.Full:
                self.dropped += 1
                if self.dropped == 1 or self.dropped % 100 == 0:
                    log.warning("frame loop behind: %d ROS messages dropped so far", self.dropped)
        return on_message

    @property
    def counts(self) -> dict:
        subs = {name: {"received": s.counts.received, "malformed": s.counts.malformed}
                for name, s in getattr(self, "subs", {}).items()}
        return {**self.assembler.counts, "queue_dropped": self.dropped, "topics": subs,
                **({"follow": dict(self.follower.counts)} if self.follower is not None else {}),
                "tf_check": None if self.tf_verdict is None else str(self.tf_verdict)}

    def frames(self, stop: threading.Event, max_frames: int | None = None) -> Iterator[dict]:
        """Posed frames as they are assembled, until ``stop``, the idle timeout or ``max_frames``.
        With ``tf_check`` the first ``tf_check_window`` frames are held and checked
        (:func:`aisdf.ros.check.check_frames`: gravity and depth consistency) before any is
        yielded; a failed check raises ``ValueError`` with the verdict in words."""
        if not self.tf_check:
            yield from self._frames(stop, max_frames)
            return
        from .check import check_frames, sample_indices

        held: list[dict] = []
        frames = self._frames(stop, max_frames)
        try:
            for f in frames:
                if self.tf_verdict is not None:
                    yield f
                    continue
                held.append(f)
                if len(held) >= self.tf_check_window:
                    yield from self._checked(held, check_frames, sample_indices)
                    held = []
            if self.tf_verdict is None and held:
                yield from self._checked(held, check_frames, sample_indices)
        finally:
            frames.close()

    def _checked(self, held: list[dict], check_frames, sample_indices) -> Iterator[dict]:
        self.tf_verdict = check_frames([held[i] for i in sample_indices(len(held), 12, len(held))])
        if not self.tf_verdict.ok:
            raise ValueError(f"refusing to map the live robot's frames (fixed frame {self.assembler.fixed_frame!r}): "
                             f"{self.tf_verdict} (fix the robot's TF or name the right frames; "
                             f"--ros-no-tf-check maps it anyway)")
        log.info("%s", self.tf_verdict)
        yield from held

    def _frames(self, stop: threading.Event, max_frames: int | None = None) -> Iterator[dict]:
        last_image = None
        n_images = 0
        while not stop.is_set():
            try:
                topic, msgtype, recv_ns, msg = self._queue.get(timeout=0.1)
            except queue.Empty:
                if (self.idle_timeout_s is not None and last_image is not None
                        and time.monotonic() - last_image > self.idle_timeout_s):
                    log.info("no depth image for %.1f s: the live source ends", self.idle_timeout_s)
                    break
                continue
            if topic == self.depth_topic:
                last_image = time.monotonic()
                n_images += 1
            yield from self.assembler.feed(topic, msgtype, recv_ns, msg)
            if max_frames and n_images >= max_frames:
                break
        yield from self.assembler.flush()

    def close(self) -> None:
        node = getattr(self, "node", None)
        if node is not None:
            node.close()
            self.node = None
        if self._own_session and self.session is not None:
            self.session.close()
            self.session = None
