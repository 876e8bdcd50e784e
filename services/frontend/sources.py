"""Frame sources the frontend streams: the built-in synthetic buildings and every dataset
reader of ``aisdf.datasets``, ROS recordings (``rosbag``) and a live ROS 2 robot (``ros2``).
A source has ``len()``,
``frame(i) -> dict(frame_id, stamp, depth (H,W) float32 metres, K, T_WC)``; a live source
instead has ``live = True``, ``frames(stop)`` yielding such dicts as they come, ``counts``
and ``close()``."""

from __future__ import annotations

from typing import Callable

from .config import FrontendConfig


def _synthetic(cfg: FrontendConfig):
    from aisdf.synthetic import SyntheticSequence

    if cfg.change:
        from aisdf.synthetic.changes import ChangingSequence

        return ChangingSequence(building=cfg.building, change=cfg.change, n_frames=cfg.n_frames, H=cfg.height,
                                W=cfg.width, fps=cfg.fps, noise=cfg.noise, seed=cfg.seed, pause_s=cfg.change_pause_s)
    return SyntheticSequence(building=cfg.building, n_frames=cfg.n_frames, H=cfg.height, W=cfg.width,
                             fps=cfg.fps, noise=cfg.noise, seed=cfg.seed)


def _dataset(cfg: FrontendConfig):
    from aisdf.datasets import open_dataset

    if cfg.path is None:
        raise ValueError(f"source {cfg.source!r} needs --path to the dataset folder")
    return open_dataset(cfg.source, cfg.path)


def _ros2(cfg: FrontendConfig):
    """A live ROS 2 robot over rmw_zenoh: ``live = True``, ``frames(stop)`` (no ``len()``)."""
    from aisdf.ros.live import Ros2Source

    r = cfg.ros2
    return Ros2Source(depth_topic=r.depth_topic, info_topic=r.info_topic, fixed_frame=r.fixed_frame,
                      camera_frame=r.camera_frame, tf_topic=r.tf_topic, tf_static_topic=r.tf_static_topic,
                      depth_type=r.depth_type, domain_id=r.domain_id, distro=r.distro, connect=r.connect,
                      zenoh_config=str(r.zenoh_config) if r.zenoh_config else None, node_name=r.node_name,
                      idle_timeout_s=r.idle_timeout_s, max_wait_s=r.max_wait_s, tf_check=r.tf_check,
                      tf_check_window=r.tf_check_window, odom_frame=r.odom_frame, follow_mode=r.follow_mode,
                      follow_keyframes=r.follow_keyframes, follow_min_m=r.follow_min_m,
                      follow_min_deg=r.follow_min_deg)


def open_rosbag(cfg: FrontendConfig):
    """A ROS 1 bag or rosbag2 recording (``aisdf.ros.bag.RosbagSource``), without the TF check."""
    from aisdf.ros.bag import RosbagSource

    if cfg.path is None:
        raise ValueError("source 'rosbag' needs --path to the recording (.bag, rosbag2 folder, .db3 or .mcap)")
    r = cfg.rosbag
    return RosbagSource(cfg.path, depth_topic=r.depth_topic, info_topic=r.info_topic, fixed_frame=r.fixed_frame,
                        pose_topic=r.pose_topic, camera_extrinsic=r.camera_extrinsic, camera_frame=r.camera_frame)


def _rosbag(cfg: FrontendConfig):
    """The recording, refused when no frame can be placed or its TF chain fails the check."""
    import logging

    from aisdf.ros.check import check_source

    src = open_rosbag(cfg)
    log = logging.getLogger("aisdf.frontend")
    if len(src) == 0:
        src.close()
        raise ValueError(f"no frame of {cfg.path} can be placed: {src.summary()}")
    if src.counts["skipped"]:
        log.warning("%s: %s", cfg.path, src.summary())
    if cfg.rosbag.tf_check:
        verdict = check_source(src)
        if not verdict.ok:
            src.close()
            raise ValueError(f"refusing to map {cfg.path}: {verdict} (fix the recording's TF or name the right "
                             f"frames; --no-tf-check maps it anyway)")
        log.info("%s", verdict)
    else:
        log.warning("TF check of %s skipped (--no-tf-check)", cfg.path)
    return src


SOURCES: dict[str, Callable[[FrontendConfig], object]] = {"synthetic": _synthetic, "ros2": _ros2, "rosbag": _rosbag}


def open_source(cfg: FrontendConfig):
    if cfg.source in SOURCES:
        return SOURCES[cfg.source](cfg)
    from aisdf.datasets import READERS

    if cfg.source in READERS:
        return _dataset(cfg)
    raise ValueError(f"unknown source {cfg.source!r}; choose one of {sorted(SOURCES) + sorted(READERS)}")


def list_source(cfg: FrontendConfig) -> str:
    """``--list``: what a recording holds and the TF check's verdict, in words."""
    if cfg.source != "rosbag":
        raise ValueError("--list describes a recording: use it with --source rosbag --path BAG")
    from aisdf.ros.check import check_source

    with open_rosbag(cfg) as src:
        text = src.describe()
        if len(src):
            text += "\n" + str(check_source(src))
        else:
            text += "\nTF check: not run, no frame could be placed"
    return text
