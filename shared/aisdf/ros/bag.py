"""ROS recordings as a frame source: ROS 1 ``.bag``, rosbag2 folders, and single rosbag2
``.db3`` (sqlite3) or ``.mcap`` files, read with ``rosbags.highlevel.AnyReader``.

::

    src = RosbagSource("run.mcap")              # topics and frames found when there is one obvious choice
    len(src); src.frame(i)                      # dict(frame_id, stamp, depth, K, T_WC), as every source
    print(src.describe())                       # what ``aisdf-frontend --source rosbag --list`` prints

Discovery (each overridden by its argument / flag):

- depth topic: the one ``sensor_msgs/Image`` or ``CompressedImage`` topic whose name contains
  "depth" (or the only image topic);
- camera info: the only ``CameraInfo`` topic, else the one whose namespace is the longest
  prefix of the depth topic;
- poses: ``/tf`` + ``/tf_static`` (``tf2_msgs/TFMessage``; a topic whose name ends in
  ``tf_static`` is static) when the bag has them, else the only pose topic
  (``PoseStamped``, ``PoseWithCovarianceStamped``, ``Odometry``, ``TransformStamped``) with
  ``camera_extrinsic`` (identity by default);
- fixed frame: the root of the TF tree that holds the depth image's frame.

The bag is pre-scanned once: a first pass reads TF, camera info and poses into a
:class:`~aisdf.ros.assemble.FrameAssembler` that keeps the whole TF history; a second pass
feeds the depth images through it (each decoded once, so that an unreadable one is skipped and
counted here, not met while streaming) and keeps, for each placed image, where it is in the bag
(time and connection), its stamp, K and pose. ``frame(i)`` reads that one message again.
Images that cannot be placed are skipped and counted (``counts``), never guessed."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from . import messages
from .assemble import TF_TYPES, FrameAssembler, is_image_type, is_info_type
from .tf import POSE_TYPES, ConnectivityError, parse_extrinsic

log = logging.getLogger("aisdf.ros.bag")


def open_reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no recording at {path}")
    if path.is_file() and path.suffix not in (".bag", ".db3", ".mcap"):
        raise ValueError(f"{path}: not a recording (a ROS 1 .bag, a rosbag2 folder, or a .db3 / .mcap file)")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise ValueError(f"{path}: a folder without metadata.yaml is not a rosbag2 recording")
    reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as e:  # rosbags raises its own error types for broken files
        raise ValueError(f"{path}: cannot read the recording: {e}") from None
    return reader


def _storage(path: Path) -> str:
    if path.suffix == ".bag":
        return "ROS 1 bag"
    if path.suffix == ".mcap" or any(path.glob("*.mcap")):
        return "rosbag2 MCAP"
    return "rosbag2 sqlite3"


def _choose(what: str, cands: list[str], flag: str) -> str:
    if len(cands) == 1:
        return cands[0]
    if not cands:
        raise ValueError(f"the recording has no {what}")
    raise ValueError(f"the recording has several {what}s ({', '.join(cands)}); name one with {flag}")


class RosbagSource:
    kind = "rosbag"

    def __init__(self, path, depth_topic: str | None = None, info_topic: str | None = None,
                 fixed_frame: str | None = None, pose_topic: str | None = None, camera_extrinsic=None,
                 camera_frame: str | None = None):
        self.path = Path(path)
        self.reader = open_reader(self.path)
        try:
            self._setup(depth_topic, info_topic, fixed_frame, pose_topic, camera_extrinsic, camera_frame)
        except BaseException:
            self.close()
            raise

    # ---- discovery ------------------------------------------------------------------------
    def _setup(self, depth_topic, info_topic, fixed_frame, pose_topic, camera_extrinsic, camera_frame):
        r = self.reader
        self.topics = {t: (info.msgtype, info.msgcount) for t, info in sorted(r.topics.items())}
        by_type = lambda pred: [t for t, (ty, _) in self.topics.items() if pred(ty or "")]  # noqa: E731
        images = by_type(is_image_type)
        if depth_topic is None:
            depth = [t for t in images if "depth" in t.lower()]
            depth_topic = _choose("depth image topic", depth or images, "--depth-topic")
        elif depth_topic not in self.topics or not is_image_type(self.topics[depth_topic][0] or ""):
            raise ValueError(f"depth topic {depth_topic!r} is not an Image/CompressedImage topic of the recording "
                             f"(image topics: {', '.join(images) or 'none'})")
        infos = by_type(is_info_type)
        if info_topic is None:
            if len(infos) > 1:
                ns = [t for t in infos if depth_topic.startswith(t.rsplit("/", 1)[0] + "/")]
                longest = max((len(t.rsplit("/", 1)[0]) for t in ns), default=-1)
                ns = [t for t in ns if len(t.rsplit("/", 1)[0]) == longest]
                infos = ns or infos
            info_topic = _choose("camera info topic", infos, "--info-topic")
        elif info_topic not in infos:
            raise ValueError(f"camera info topic {info_topic!r} is not a CameraInfo topic of the recording "
                             f"(CameraInfo topics: {', '.join(infos) or 'none'})")
        tf_topics = by_type(lambda ty: ty in TF_TYPES)
        static = [t for t in tf_topics if t.endswith("tf_static")]
        dynamic = [t for t in tf_topics if t not in static]
        T_ext = None
        if pose_topic is not None:
            if pose_topic not in self.topics or self.topics[pose_topic][0] not in POSE_TYPES:
                raise ValueError(f"pose topic {pose_topic!r} is not a pose topic of the recording (pose topics: "
                                 f"{', '.join(by_type(lambda ty: ty in POSE_TYPES)) or 'none'})")
        elif not tf_topics:
            pose_topic = _choose("pose topic (and no /tf)", by_type(lambda ty: ty in POSE_TYPES), "--pose-topic")
        if pose_topic is not None:
            T_ext = camera_extrinsic if isinstance(camera_extrinsic, np.ndarray) else parse_extrinsic(camera_extrinsic)
        elif camera_extrinsic is not None:
            raise ValueError("--camera-extrinsic goes with --pose-topic (with TF the chain gives the camera's pose)")
        self.depth_topic, self.info_topic, self.pose_topic = depth_topic, info_topic, pose_topic
        self.tf_topics, self.static_topics = dynamic, static
        self.depth_type = self.topics[depth_topic][0]
        self.camera_extrinsic = T_ext
        self.storage = _storage(self.path)

        # Pass 1: TF, camera info, poses (the whole history: cache_s=None).
        asm = FrameAssembler(depth_topic, info_topic, fixed_frame or "?", pose_topic=pose_topic,
                             camera_extrinsic=T_ext, camera_frame=camera_frame, tf_topics=dynamic,
                             static_tf_topics=static, cache_s=None, decode_depth=True, max_pending=1_000_000,
                             max_wait_s=1e9)
        if pose_topic is not None:
            asm.fixed_frame = fixed_frame  # None: the pose messages' frame
        first = [c for c in r.connections if c.topic in {info_topic, pose_topic, *tf_topics}]
        for c, t, raw in r.messages(connections=first):
            try:
                msg = r.deserialize(raw, c.msgtype)
            except Exception as e:  # a broken message is counted, the rest is read
                asm.bad_messages += 1
                log.warning("ignoring an unreadable %s message on %s: %s", c.msgtype, c.topic, e)
                continue
            asm.feed(c.topic, c.msgtype, t, msg)
        self.depth_conns = [c for c in r.connections if c.topic == depth_topic]
        first_image = next(iter(r.messages(connections=self.depth_conns)), None)
        if first_image is None:
            raise ValueError(f"depth topic {depth_topic} has no messages")
        img = r.deserialize(first_image[2], first_image[0].msgtype)
        self.camera_frame = camera_frame or img.header.frame_id
        self.image_info = self._image_info(img)
        if pose_topic is None and fixed_frame is None:
            try:
                up = asm.tf._ancestors(self.camera_frame.lstrip("/"))
            except ConnectivityError as e:
                raise ValueError(f"cannot find the fixed frame: {e}") from None
            if len(up) == 1:
                known = ", ".join(sorted(asm.tf.frames)) or "none"
                raise ValueError(f"the depth image's frame {self.camera_frame!r} is in no TF chain of the recording "
                                 f"(TF frames: {known}); name the fixed frame with --fixed-frame (frames will be "
                                 f"skipped as 'missing transform' unless the chain exists)")
            fixed_frame = up[-1]
        if pose_topic is None:
            asm.fixed_frame = fixed_frame
        self.fixed_frame = asm.fixed_frame
        # Pass 2: the images, placed (or skipped) with the complete buffer.
        self._index: list[dict] = []
        ordinal: dict[int, int] = {}
        for c, t, raw in r.messages(connections=self.depth_conns):
            k = ordinal[t] = ordinal.get(t, -1) + 1
            try:
                msg = r.deserialize(raw, c.msgtype)
            except Exception as e:
                asm.n_images += 1
                asm._skip("bad_image", f"cannot deserialise: {e}", asm.n_images - 1)
                continue
            # The whole TF history is there: what cannot be placed now never will be (flush).
            self._add(asm.feed(c.topic, c.msgtype, t, msg, ref=(t, k)) + asm.flush())
        self.assembler = asm
        if pose_topic is not None and self.fixed_frame is None:
            self.fixed_frame = asm.fixed_frame
        log.info("%s: %s", self.path, self.summary())

    def _image_info(self, img) -> str:
        if self.depth_type.endswith("CompressedImage"):
            return f"CompressedImage, format {img.format!r}"
        return f"Image {img.encoding} {img.width}x{img.height}{' big-endian' if img.is_bigendian else ''}"

    def _add(self, frames: list[dict]) -> None:
        for f in frames:
            self._index.append({"frame_id": f["frame_id"], "stamp": f["stamp"], "K": f["K"], "T_WC": f["T_WC"],
                                "ref": f["ref"], "msgtype": self.depth_type})  # the depth is read again later

    # ---- source interface -----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._index)

    def frame(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        e = self._index[i]
        t, k = e["ref"]
        for n, (c, _t, raw) in enumerate(self.reader.messages(connections=self.depth_conns, start=t, stop=t + 1)):
            if n == k:
                msg = self.reader.deserialize(raw, c.msgtype)
                depth = messages.depth_from_msg(e["msgtype"], msg)
                return {"frame_id": e["frame_id"], "stamp": e["stamp"], "depth": depth, "K": e["K"].copy(),
                        "T_WC": e["T_WC"].copy()}
        raise RuntimeError(f"frame {i}: its message at {t} ns is gone from {self.path}")

    def __getitem__(self, i: int) -> dict:
        return self.frame(i)

    def poses(self) -> np.ndarray:
        return np.stack([e["T_WC"] for e in self._index]) if self._index else np.zeros((0, 4, 4))

    @property
    def counts(self) -> dict:
        return self.assembler.counts

    def close(self) -> None:
        if getattr(self, "reader", None) is not None:
            self.reader.close()
            self.reader = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # ---- words ----------------------------------------------------------------------------
    def summary(self) -> str:
        c = self.counts
        return (f"{c['images']} depth images, {c['frames']} placed, {c['skipped']} skipped"
                + (f" ({self.assembler.describe_skips()})" if c["skipped"] else ""))

    def describe(self) -> str:
        """What was found, in words (``--list``)."""
        asm = self.assembler
        roles = {self.depth_topic: "depth", self.info_topic: "camera info", self.pose_topic: "poses"}
        roles.update({t: "TF" for t in self.tf_topics})
        roles.update({t: "static TF" for t in self.static_topics})
        lines = [f"recording: {self.path} ({self.storage})", "topics:"]
        w = max((len(t) for t in self.topics), default=0)
        for t, (ty, n) in self.topics.items():
            lines.append(f"  {t:<{w}}  {ty}  {n} messages" + (f"  <- {roles[t]}" if t in roles else ""))
        lines.append(f"depth: {self.depth_topic} ({self.image_info}), frame {self.camera_frame!r}")
        K = asm.K
        lines.append(f"camera info: {self.info_topic}" + (
            f" (fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f})" if K is not None
            else " (none received)"))
        if self.pose_topic is not None:
            lines.append(f"poses: {self.pose_topic} in frame {self.fixed_frame!r}, camera extrinsic (body -> camera):")
            lines += ["    " + " ".join(f"{v:8.4f}" for v in row) for row in self.camera_extrinsic[:3]]
        else:
            lines.append(f"poses: TF ({', '.join(self.tf_topics + self.static_topics)}), fixed frame "
                         f"{self.fixed_frame!r} -> camera frame {self.camera_frame!r}")
            try:
                chain = asm.tf.chain(self.fixed_frame, self.camera_frame)
                lines.append("  chain: " + ", ".join(f"{p} -> {c} ({'static' if s else 'dynamic'})"
                                                    for p, c, s in reversed(chain)))
            except ConnectivityError as e:
                lines.append(f"  chain: none ({e})")
            lines.append("  TF tree:")
            for p, c, s, n in asm.tf.edges():
                rng = asm.tf.time_range(p, c)
                span = f", {(rng[1] - rng[0]) * 1e-9:.2f} s, {(n - 1) / max((rng[1] - rng[0]) * 1e-9, 1e-9):.1f} Hz" \
                    if rng and n > 1 else ""
                lines.append(f"    {p} -> {c}: " + ("static" if s else f"dynamic, {n} samples{span}"))
        lines.append(f"frames: {self.summary()}")
        return "\n".join(lines)
