"""``aisdf-frontend``: streams a posed depth source, selects keyframes by motion and
overlap, and publishes them on ``<namespace>/keyframes``.

Reliable by default (protocol 1.2): keyframes are sent only while a mapper's liveliness
token (``status/mapper/<id>``) is there, held (bounded) while none is, and sent again
until the mapper acknowledges them on ``keyframes/ack`` (see ``outbox.py``). With mapper
shards (protocol 1.14), until every live owner it needs has acknowledged it."""

from __future__ import annotations

import argparse
import logging
import threading
import time
import uuid

import zenoh

from aisdf import keys, protocol, transport
from aisdf.config import add_common_args, config_from_args, service_setup
from aisdf.keyframes import KeyframeSelector, keyframe_message

from .config import FrontendConfig
from .outbox import KeyframeOutbox
from .sources import list_source, open_source

log = logging.getLogger("aisdf.frontend")


def to_keyframe(frame: dict, cfg: FrontendConfig) -> protocol.Keyframe:
    return keyframe_message(frame, cfg.sensor, cfg.depth_encoding)


INFO_KEY = "info/frontend"


def stream(cfg: FrontendConfig, publish, stop: threading.Event, counts: dict | None = None, correct=None) -> dict:
    """Stream the source through keyframe selection into ``publish(msg)``; returns counts
    (``counts``, updated live, when given). ``correct({frame_id: T_WC})``: where a live source
    follows map -> odom (``ros2.odom_frame``), the corrected poses of keyframes sent (1.11)."""
    src = open_source(cfg)
    selector = KeyframeSelector(cfg.keyframes)
    counts = counts if counts is not None else {}
    if getattr(src, "live", False):
        return stream_live(cfg, src, selector, publish, stop, counts, correct)
    counts.update(frames=0, keyframes=0, total=len(src))
    if hasattr(src, "counts"):  # a recording: its images that could not be placed, by reason
        counts["source"] = src.counts
    n = len(src)
    indices = range(cfg.start, n, cfg.stride)
    t0 = time.monotonic()
    stamp0 = None
    while not stop.is_set():
        for i in indices:
            if stop.is_set() or (cfg.max_frames and counts["frames"] >= cfg.max_frames):
                return counts
            frame = src.frame(i)
            stamp = float(frame["stamp"])
            stamp0 = stamp if stamp0 is None else stamp0
            if cfg.realtime:  # the sensor's rate: wait until this frame's time
                wait = (stamp - stamp0) - (time.monotonic() - t0)
                if wait > 0 and stop.wait(wait):
                    return counts
            counts["frames"] += 1
            if selector.is_keyframe(stamp, frame["depth"], frame["K"], frame["T_WC"]):
                publish(to_keyframe(frame, cfg).to_msg())
                counts["keyframes"] += 1
                log.debug("keyframe %d (%s)", frame["frame_id"], selector.last_reason)
        if not cfg.loop:
            break
    return counts


def stream_live(cfg: FrontendConfig, src, selector: KeyframeSelector, publish, stop: threading.Event,
                counts: dict, correct=None) -> dict:
    """A live source (``src.live``, e.g. ``ros2``): frames are pushed as the source assembles
    them, keyframes selected as for any source; it ends on ``stop`` (SIGINT/SIGTERM), when the
    source ends (its idle timeout) or after ``max_frames``. ``counts["source"]`` mirrors the
    source's own counters (images, skipped frames by reason, malformed messages)."""
    counts.update(frames=0, keyframes=0, total=None, source=src.counts)
    follower = getattr(src, "follower", None)  # map -> odom corrections (protocol 1.11)
    frames = src.frames(stop)
    try:
        for frame in frames:
            counts["frames"] += 1
            if selector.is_keyframe(float(frame["stamp"]), frame["depth"], frame["K"], frame["T_WC"]):
                publish(to_keyframe(frame, cfg).to_msg())
                counts["keyframes"] += 1
                log.debug("keyframe %d (%s)", frame["frame_id"], selector.last_reason)
                if follower is not None:
                    follower.track(frame["frame_id"], round(float(frame["stamp"]) * 1e9), frame["T_WC"])
            if follower is not None and correct is not None:
                moved = follower.poll()
                if moved:
                    correct(moved)
            counts["source"] = src.counts
            if cfg.max_frames and counts["frames"] >= cfg.max_frames:
                break
    finally:
        frames.close()
        counts["source"] = src.counts
        src.close()
    c = counts["source"]
    log.info("live source ended: %d images, %d frames placed, %d skipped (%s), %d malformed messages",
             c["images"], c["frames"], c["skipped"], c["skipped_reasons"] or "none",
             sum(t["malformed"] for t in c["topics"].values()))
    return counts


class ReliableSender:
    """Zenoh wiring of the outbox: a liveliness subscriber on the mappers' tokens
    (``status/mapper/*``), a subscriber on ``keyframes/ack`` and a thread that puts what
    the outbox says is due."""

    def __init__(self, cfg: FrontendConfig, session):
        self.cfg, self.session = cfg, session
        self.key = keys.key(cfg.namespace, keys.KEYFRAMES)
        self.outbox = KeyframeOutbox(cfg.hold_max, cfg.send_window, cfg.resend_period_s)
        self.lock = threading.Lock()
        self.mappers: set[str] = set()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sender", daemon=True)
        self._decls = [
            session.declare_subscriber(keys.key(cfg.namespace, keys.KEYFRAMES_ACK), self._on_ack),
            session.liveliness().declare_subscriber(keys.status_key(cfg.namespace, "mapper", "*"), self._on_token,
                                                    history=True),
        ]
        self._thread.start()

    def _on_token(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.mappers.add(name)
            else:
                self.mappers.discard(name)
            present = bool(self.mappers)
            self.outbox.set_members(self.mappers)
            pending = self.outbox.pending
        log.info("mapper %s %s; %d keyframes unacknowledged%s", name,
                 "is up" if sample.kind == zenoh.SampleKind.PUT else "left", pending,
                 "" if present else f" (holding up to {self.cfg.hold_max} until a mapper is there)")
        self._wake.set()

    def _on_ack(self, sample) -> None:
        try:
            msg = protocol.unpack(transport.payload_bytes(sample.payload))
            ack = protocol.KeyframeAck.from_msg(msg)
        except protocol.ProtocolError as e:
            log.warning("ignoring malformed acknowledgement: %s", e.message)
            return
        if ack.sensor != self.cfg.sensor:
            return
        try:
            shard = _shard_fields(msg, len(ack.frame_ids))
        except ValueError as e:
            log.warning("ignoring malformed acknowledgement: %s", e)
            return
        with self.lock:
            self.outbox.ack(ack.frame_ids, ack.rejected, *shard)
        self._wake.set()

    def add(self, msg: dict) -> None:
        with self.lock:
            if not self.outbox.mapper_present and not self.outbox.pending:
                log.info("no mapper under '%s' yet: holding keyframes (up to %d)", self.cfg.namespace,
                         self.cfg.hold_max)
            self.outbox.add(int(msg["frame_id"]), protocol.pack(msg))
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            with self.lock:
                batch = self.outbox.due()
            for _fid, payload in batch:
                self.session.put(self.key, payload, encoding=transport.ENCODING)

    def counts(self) -> dict:
        with self.lock:
            return {**self.outbox.counts, "pending": self.outbox.pending, "mappers": len(self.mappers)}

    def drain(self, timeout: float, stop: threading.Event) -> bool:
        """Wait until every keyframe is acknowledged (True), ``timeout`` passes or ``stop``."""
        end = time.monotonic() + timeout
        while self.outbox.pending and not stop.is_set() and time.monotonic() < end:
            stop.wait(0.1)
        return not self.outbox.pending

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
        for d in self._decls:
            d.undeclare()


def _shard_fields(msg: dict, n: int) -> tuple:
    """(mapper, touched, held) of an acknowledgement (1.14: a mapper shard's), or the 1.11
    mapper's (no id: it holds everything). ValueError when they are malformed."""
    mapper = msg.get("mapper")
    if mapper is None:
        return ()
    touched, held = msg.get("touched"), msg.get("held")
    if not isinstance(mapper, str) or not mapper or not isinstance(touched, list) or not isinstance(held, list) \
            or len(touched) != n or len(held) != n:
        raise ValueError("'mapper' must be an id with 'touched' and 'held' lists, one per frame id")
    for t in touched:
        if t is not None and not (isinstance(t, list) and all(isinstance(r, str) for r in t)):
            raise ValueError("'touched' entries must be lists of region ids or nil")
    for h in held:
        if h != "*" and not (isinstance(h, list) and all(isinstance(r, str) for r in h)):
            raise ValueError("'held' entries must be lists of region ids or '*'")
    return mapper, touched, held


def main(cfg: FrontendConfig, stop: threading.Event | None = None) -> dict:
    stop = stop or threading.Event()
    with transport.open_session(cfg.zenoh) as session:
        token = session.liveliness().declare_token(keys.status_key(cfg.namespace, "frontend", uuid.uuid4().hex[:8]))
        counts: dict = {"frames": 0, "keyframes": 0, "done": False}
        key = keys.key(cfg.namespace, keys.KEYFRAMES)
        sender = ReliableSender(cfg, session) if cfg.reliable else None
        info = transport.serve(session, keys.key(cfg.namespace, INFO_KEY),
                               lambda _req: {"v": 1, **counts, **(sender.counts() if sender else {})}, allow_empty=True)
        log.info("frontend streaming %s to %s", cfg.source if cfg.source != "synthetic" else
                 f"synthetic '{cfg.building}'" + (f" ({cfg.change})" if cfg.change else ""), key)
        fixer = None
        if cfg.source == "ros2" and cfg.ros2.odom_frame:  # protocol 1.11: map -> odom corrections
            from aisdf.ros.follow import CorrectionSender

            fixer = CorrectionSender(session, cfg.namespace, cfg.sensor)
        try:
            stream(cfg, sender.add if sender else (lambda msg: transport.put(session, key, msg)), stop, counts,
                   None if fixer is None else fixer.submit)
            if sender and not cfg.linger:  # lingering, the sender keeps resending until stopped
                log.info("source done: %d frames, %d keyframes; waiting up to %.0f s for %d acknowledgements",
                         counts["frames"], counts["keyframes"], cfg.drain_timeout_s, sender.outbox.pending)
                sender.drain(cfg.drain_timeout_s, stop)
            counts["done"] = True
            c = sender.counts() if sender else {}
            log.info("done: %d frames, %d keyframes%s", counts["frames"], counts["keyframes"],
                     f"; {c['acked']} acknowledged, {c['rejected']} rejected by the mapper, {c['dropped']} dropped "
                     f"while held, {c['pending']} never acknowledged; {c['sent']} sent, {c['resent']} resent"
                     if sender else " (sent once each, unacknowledged)")
            time.sleep(0.2)  # let the last put leave
            if cfg.linger:
                stop.wait()
        finally:
            if fixer is not None:
                fixer.close()
            if sender:
                sender.close()
            info.undeclare()
            token.undeclare()
    return counts


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="aisdf-frontend",
        description="AiSDF frontend: streams posed depth (the built-in synthetic building by default, or a "
        "dataset folder), selects keyframes by motion and overlap, publishes them on <namespace>/keyframes.",
    )
    add_common_args(p)
    p.add_argument("--source", help="synthetic (default), ros2 (a live robot over rmw_zenoh) or a dataset kind: "
                   "generic, 7scenes, tum, icl, ...")
    p.add_argument("--path", help="dataset folder")
    p.add_argument("--building", help="synthetic building (office, manhattan, atlanta, stairs, floor)")
    p.add_argument("--fast", action="store_true", help="as fast as possible instead of the sensor's rate")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    r = p.add_argument_group("live ROS 2 robot (--source ros2, over rmw_zenoh; any ros2.* field with --set)",
                             "Loop closures: --set ros2.odom_frame=odom re-poses the keyframes sent when map -> odom "
                             "moves by over 1 cm or 0.5 deg (protocol 1.11); a SLAM node may instead send its poses "
                             "with aisdf.poses.send_corrections (docs/ros.md).")
    r.add_argument("--ros-connect", action="append", metavar="ENDPOINT",
                   help="the robot's Zenoh router (repeatable; default tcp/localhost:7447)")
    r.add_argument("--ros-zenoh-config", metavar="FILE", help="Zenoh session file for the ROS side "
                   "(default $ZENOH_SESSION_CONFIG_URI)")
    r.add_argument("--ros-domain-id", type=int, help="ROS_DOMAIN_ID (default $ROS_DOMAIN_ID or 0)")
    r.add_argument("--ros-distro", help="humble, jazzy (default), ...: message definitions and type hashes")
    r.add_argument("--ros-depth-topic", help="depth image topic (default /camera/depth/image_rect_raw)")
    r.add_argument("--ros-info-topic", help="camera info topic (default /camera/depth/camera_info)")
    r.add_argument("--ros-fixed-frame", help="world frame of the poses (default map)")
    r.add_argument("--ros-idle-timeout", type=float, metavar="S",
                   help="end after S seconds without a depth image (default: run until stopped)")
    r.add_argument("--ros-no-tf-check", action="store_true", help="map without checking the TF chain first")
    b = p.add_argument_group("ROS recording (--source rosbag --path BAG: ROS 1 .bag, rosbag2 folder, .db3 or "
                             ".mcap; any rosbag.* field with --set)")
    b.add_argument("--list", action="store_true", help="print the recording's topics, frames, TF tree and the TF "
                   "check's verdict, and exit")
    b.add_argument("--depth-topic", help="depth image topic (default: the one depth image topic)")
    b.add_argument("--info-topic", help="camera info topic (default: the one beside the depth topic)")
    b.add_argument("--fixed-frame", help="world frame (default: root of the TF tree holding the image's frame)")
    b.add_argument("--pose-topic", help="PoseStamped/Odometry topic instead of /tf")
    b.add_argument("--camera-extrinsic", metavar="POSE", help="with --pose-topic: the camera's pose in the body "
                   "frame, 'x y z qx qy qz qw' (or 'x y z yaw pitch roll', 16 numbers, 'optical [x y z]')")
    b.add_argument("--camera-frame", help="camera frame instead of the images' header.frame_id")
    b.add_argument("--no-tf-check", action="store_true", help="map the recording even when the TF check fails")
    args = p.parse_args(argv)
    cfg = config_from_args(FrontendConfig, args, {"source": args.source, "path": args.path,
                                                  "building": args.building, "max_frames": args.max_frames,
                                                  "realtime": False if args.fast else None,
                                                  "ros2.connect": args.ros_connect,
                                                  "ros2.zenoh_config": args.ros_zenoh_config,
                                                  "ros2.domain_id": args.ros_domain_id,
                                                  "ros2.distro": args.ros_distro,
                                                  "ros2.depth_topic": args.ros_depth_topic,
                                                  "ros2.info_topic": args.ros_info_topic,
                                                  "ros2.fixed_frame": args.ros_fixed_frame,
                                                  "ros2.idle_timeout_s": args.ros_idle_timeout,
                                                  "ros2.tf_check": False if args.ros_no_tf_check else None,
                                                  "rosbag.depth_topic": args.depth_topic,
                                                  "rosbag.info_topic": args.info_topic,
                                                  "rosbag.fixed_frame": args.fixed_frame,
                                                  "rosbag.pose_topic": args.pose_topic,
                                                  "rosbag.camera_extrinsic": args.camera_extrinsic,
                                                  "rosbag.camera_frame": args.camera_frame,
                                                  "rosbag.tf_check": False if args.no_tf_check else None})
    if args.list:
        try:
            print(list_source(cfg))
        except (ValueError, FileNotFoundError) as e:
            raise SystemExit(f"aisdf-frontend: {e}") from None
        return
    stop = service_setup(cfg, "frontend")
    try:
        main(cfg, stop)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"aisdf-frontend: {e}") from None


if __name__ == "__main__":
    cli()
