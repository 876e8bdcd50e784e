"""Posed depth frames from a stream of ROS messages in arrival order (a bag, or a live robot).

Interface (shared by the rosbag source, ``bag.py``, and the live ROS 2 source)::

    asm = FrameAssembler(depth_topic="/camera/depth/image_rect_raw",
                         info_topic="/camera/depth/camera_info",   # None: any CameraInfo
                         fixed_frame="map")                        # the world frame of T_WC
    for topic, msgtype, stamp_ns, msg in messages:                 # msg: a rosbags-deserialised object
        for frame in asm.feed(topic, msgtype, stamp_ns, msg):
            ...  # dict(frame_id, stamp, depth, K, T_WC), see below
    for frame in asm.flush():                                      # at the end of the stream
        ...
    asm.counts     # {"images": n, "frames": n, "skipped": n, "skipped_reasons": {reason: n}, ...}

``feed`` returns the frames that became ready (possibly none, possibly several), in image
order. A frame dict is ``frame_id`` (int: the image's index on the depth topic, counting
skipped ones, so ids are stable), ``stamp`` (float seconds, the image header's stamp),
``depth`` ((H, W) float32 metres, 0 = invalid), ``K`` ((3, 3) float64), ``T_WC`` ((4, 4)
float64, the optical camera frame -> ``fixed_frame``), and ``ref`` when ``feed`` was given one.
With ``decode_depth=False`` the frame carries ``msg``/``msgtype`` instead of ``depth`` (a bag's
pre-scan keeps only where each frame is).

Poses come from ``/tf`` + ``/tf_static`` (``tf_topics``/``static_tf_topics``): the chain from
``fixed_frame`` to the image's ``header.frame_id`` (or ``camera_frame``), interpolated at the
image's stamp; or, with ``pose_topic``, from a ``PoseStamped``/``PoseWithCovarianceStamped``/
``Odometry``/``TransformStamped`` topic composed with ``camera_extrinsic`` (``T_body_camera``;
the fixed frame is then the pose messages' ``header.frame_id`` unless named).

An image waits (held, in order) until the buffer can place it: TF samples after its stamp have
arrived, the chain is complete, a camera info is known. At most ``max_pending`` images are held
and none longer than ``max_wait_s`` of stream time; beyond, the oldest is skipped with the
reason it was waiting for. Skipped frames are counted by reason, never guessed:

- ``no_camera_info``: no CameraInfo arrived in time;
- ``stamp_outside_tf``: the stamp lies before the oldest TF sample of an edge in the chain, or
  after the newest when the stream ended / the wait ran out;
- ``missing_transform``: the chain from the fixed frame to the camera frame is incomplete;
- ``bad_image``: an encoding we do not read or an inconsistent image (the message says why).

Malformed TF/info/pose messages are counted (``bad_messages``) and logged, never raised."""

from __future__ import annotations

import logging
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from . import messages
from .tf import ConnectivityError, ExtrapolationError, TFBuffer, TFError, pose_from_message

log = logging.getLogger("aisdf.ros")

REASONS = ("no_camera_info", "stamp_outside_tf", "missing_transform", "bad_image")
REASON_WORDS = {
    "no_camera_info": "no camera info",
    "stamp_outside_tf": "stamp outside the TF buffer",
    "missing_transform": "missing transform",
    "bad_image": "unreadable image",
}
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
BODY, CAMERA = "__aisdf_pose_body__", "__aisdf_camera__"


def is_image_type(msgtype: str) -> bool:
    return msgtype in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def is_info_type(msgtype: str) -> bool:
    return msgtype == "sensor_msgs/msg/CameraInfo"


@dataclass
class _Pending:
    frame_id: int
    stamp: int
    camera_frame: str
    msgtype: str
    msg: object
    ref: object
    arrived: int
    reason: str = ""
    why: str = ""


class FrameAssembler:
    def __init__(self, depth_topic: str, info_topic: str | None = None, fixed_frame: str | None = None, *,
                 pose_topic: str | None = None, camera_extrinsic: np.ndarray | None = None,
                 camera_frame: str | None = None, tf_topics=("/tf",), static_tf_topics=("/tf_static",),
                 max_pending: int = 60, max_wait_s: float = 1.0, cache_s: float | None = 30.0,
                 decode_depth: bool = True, buffer: TFBuffer | None = None):
        if pose_topic is None and not fixed_frame:
            raise ValueError("a fixed frame (the world frame of the poses) is needed with TF poses")
        self.depth_topic, self.info_topic, self.pose_topic = depth_topic, info_topic, pose_topic
        self.fixed_frame, self.camera_frame = fixed_frame, camera_frame
        self.tf_topics, self.static_tf_topics = set(tf_topics), set(static_tf_topics)
        self.max_pending, self.max_wait_ns = max(1, int(max_pending)), int(max_wait_s * 1e9)
        self.decode_depth = decode_depth
        self.tf = buffer if buffer is not None else TFBuffer(cache_s)
        if pose_topic is not None:
            T = np.eye(4) if camera_extrinsic is None else np.asarray(camera_extrinsic, np.float64)
            self.tf.set_transform(BODY, CAMERA, 0, T, static=True)
        self.K: np.ndarray | None = None
        self.image_size: tuple[int, int] | None = None
        self.pending: deque[_Pending] = deque()
        self.n_images = 0
        self.n_frames = 0
        self.skipped: Counter = Counter()
        self.skip_examples: dict[str, str] = {}
        self.bad_messages = 0
        self.last_stamp = 0  # newest stream time seen (ns)

    # ---- public ---------------------------------------------------------------------------
    @property
    def counts(self) -> dict:
        return {"images": self.n_images, "frames": self.n_frames, "skipped": sum(self.skipped.values()),
                "skipped_reasons": {r: self.skipped[r] for r in REASONS if self.skipped[r]},
                "pending": len(self.pending), "bad_messages": self.bad_messages}

    def describe_skips(self) -> str:
        if not self.skipped:
            return "no frame skipped"
        return "; ".join(f"{n} skipped: {REASON_WORDS[r]} (e.g. {self.skip_examples.get(r, '')})"
                         for r, n in self.skipped.items())

    def feed(self, topic: str, msgtype: str, stamp_ns: int, msg, ref=None) -> list[dict]:
        """One message in arrival order (``stamp_ns``: the arrival/bag time); returns the
        frames that became ready."""
        self.last_stamp = max(self.last_stamp, int(stamp_ns))
        try:
            if topic == self.depth_topic and is_image_type(msgtype):
                self._add_image(msgtype, msg, ref, int(stamp_ns))
            elif msgtype in TF_TYPES and (topic in self.tf_topics or topic in self.static_tf_topics):
                if self.pose_topic is None:
                    self.tf.add_tf_message(msg, static=topic in self.static_tf_topics)
            elif is_info_type(msgtype) and (self.info_topic is None or topic == self.info_topic):
                self.K = messages.K_from_camera_info(msg)
            elif self.pose_topic is not None and topic == self.pose_topic:
                parent, _child, stamp, T = pose_from_message(msgtype, msg, BODY)
                if self.fixed_frame is None:
                    self.fixed_frame = parent
                    log.info("poses from %s in frame %r", topic, parent)
                if parent != self.fixed_frame:
                    raise ValueError(f"pose in frame {parent!r}, the fixed frame is {self.fixed_frame!r}")
                self.tf.set_transform(parent, BODY, stamp, T)
        except (ValueError, AttributeError, TypeError) as e:
            self.bad_messages += 1
            log.warning("ignoring a malformed %s message on %s: %s", msgtype, topic, e)
        return self._resolve(final=False)

    def flush(self) -> list[dict]:
        """End of stream: place what can be, skip (and count) the rest."""
        return self._resolve(final=True)

    # ---- internals ------------------------------------------------------------------------
    def _skip(self, reason: str, why: str, frame_id: int) -> None:
        self.skipped[reason] += 1
        if reason not in self.skip_examples:
            self.skip_examples[reason] = why
            log.warning("skipping depth frame %d: %s (%s); further such frames are counted", frame_id,
                        REASON_WORDS[reason], why)
        else:
            log.debug("skipping depth frame %d: %s (%s)", frame_id, REASON_WORDS[reason], why)

    def _add_image(self, msgtype: str, msg, ref, arrived: int) -> None:
        fid = self.n_images
        self.n_images += 1
        try:
            if msgtype == "sensor_msgs/msg/Image":
                messages.check_image_encoding(msg)
            stamp = messages.header_stamp_ns(msg)
            frame = self.camera_frame or msg.header.frame_id
            if self.pose_topic is None and not frame:
                raise ValueError("depth image without header.frame_id (name the camera frame)")
        except (ValueError, AttributeError) as e:
            self._skip("bad_image", str(e), fid)
            return
        self.pending.append(_Pending(fid, stamp, frame, msgtype, msg, ref, arrived))

    def _try(self, p: _Pending) -> np.ndarray | None:
        """T_WC, or None with ``p.reason``/``p.why`` set; ExtrapolationError into the past is
        final (``p.reason`` set and ``"past"`` returned through ``p.why`` prefix)."""
        if self.K is None:
            p.reason, p.why = "no_camera_info", "no CameraInfo received yet" + (
                f" on {self.info_topic}" if self.info_topic else "")
            return None
        source = CAMERA if self.pose_topic is not None else p.camera_frame
        if self.fixed_frame is None:
            p.reason, p.why = "stamp_outside_tf", "no pose received yet"
            return None
        try:
            return self.tf.lookup(self.fixed_frame, source, p.stamp)
        except ExtrapolationError as e:
            p.reason, p.why = "stamp_outside_tf", str(e)
            if not e.future:
                p.why = "past:" + p.why
            return None
        except ConnectivityError as e:
            p.reason, p.why = "missing_transform", str(e)
            return None
        except TFError as e:  # pragma: no cover - every TFError is one of the two above
            p.reason, p.why = "missing_transform", str(e)
            return None

    def _resolve(self, final: bool) -> list[dict]:
        out = []
        while self.pending:
            p = self.pending[0]
            T = self._try(p)
            if T is not None:
                self.pending.popleft()
                f = self._frame(p, T)
                if f is not None:
                    out.append(f)
                continue
            past = p.why.startswith("past:")
            expired = (final or past or len(self.pending) > self.max_pending
                       or self.last_stamp - p.arrived > self.max_wait_ns)
            if not expired:
                break
            self.pending.popleft()
            self._skip(p.reason, p.why.removeprefix("past:"), p.frame_id)
        return out

    def _frame(self, p: _Pending, T: np.ndarray) -> dict | None:
        f = {"frame_id": p.frame_id, "stamp": p.stamp * 1e-9, "K": self.K.copy(), "T_WC": T}
        if self.decode_depth:
            try:
                f["depth"] = messages.depth_from_msg(p.msgtype, p.msg)
            except ValueError as e:
                self._skip("bad_image", str(e), p.frame_id)
                return None
        else:
            f["msg"], f["msgtype"] = p.msg, p.msgtype
        if p.ref is not None:
            f["ref"] = p.ref
        self.n_frames += 1
        return f
