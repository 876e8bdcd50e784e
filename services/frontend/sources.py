"""Frame sources the frontend streams: the built-in synthetic buildings and every dataset
reader of ``aisdf.datasets``, and a live ROS 2 robot (``ros2``). A source has ``len()``,
``frame(i) -> dict(frame_id, stamp, depth (H,W) float32 metres, K, T_WC)``; a live source
instead has ``live = True``, ``frames(stop)`` yielding such dicts as they come, ``counts``
and ``close()``."""

from __future__ import annotations

from typing import Callable

from .config import FrontendConfig


def _synthetic(cfg: FrontendConfig):
    from aisdf.synthetic import SyntheticSequence

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
                      idle_timeout_s=r.idle_timeout_s, max_wait_s=r.max_wait_s)


SOURCES: dict[str, Callable[[FrontendConfig], object]] = {"synthetic": _synthetic, "ros2": _ros2}


def open_source(cfg: FrontendConfig):
    if cfg.source in SOURCES:
        return SOURCES[cfg.source](cfg)
    from aisdf.datasets import READERS

    if cfg.source in READERS:
        return _dataset(cfg)
    raise ValueError(f"unknown source {cfg.source!r}; choose one of {sorted(SOURCES) + sorted(READERS)}")
