"""Frame sources the frontend streams: the built-in synthetic buildings and every dataset
reader of ``aisdf.datasets``. A source has ``len()``, ``frame(i) -> dict(frame_id, stamp,
depth (H,W) float32 metres, K, T_WC)``."""

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


SOURCES: dict[str, Callable[[FrontendConfig], object]] = {"synthetic": _synthetic}


def open_source(cfg: FrontendConfig):
    if cfg.source in SOURCES:
        return SOURCES[cfg.source](cfg)
    from aisdf.datasets import READERS

    if cfg.source in READERS:
        return _dataset(cfg)
    raise ValueError(f"unknown source {cfg.source!r}; choose one of {sorted(SOURCES) + sorted(READERS)}")
