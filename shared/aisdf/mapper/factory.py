"""Making a mapper by its kind (``mapper: submaps | single``) and resuming one from its
checkpoint: the one place that knows both implementations."""

from __future__ import annotations

from typing import Any

from ..submaps.config import SubmapConfig
from ..submaps.persist import CHECKPOINT_FORMAT as SUBMAPS_CHECKPOINT
from ..submaps.pipeline import SubmapPipeline
from .coverage import KeyframePolicy
from .interface import MAPPER_KINDS, Mapper
from .single import MappingPipeline


def make_mapper(kind: str = "submaps", preset: str = "auto", training: dict[str, Any] | None = None,
                atlanta: bool = True, surfel_mask: bool = True, surfel_loss: bool = True,
                surfel_bounds: bool = True, measured: bool = True,
                submaps: SubmapConfig | dict | None = None,
                keyframes: KeyframePolicy | dict | None = None) -> Mapper:
    """A new mapper of ``kind``: the preset with ``training`` overrides, the Table II switches
    (each only with ``atlanta``), ``measured``: pool the depth pixels and publish them with
    the map (for submaps, ``submaps.measured`` false turns them off too). ``submaps``: the
    submap settings (ignored by one network). ``keyframes``: which keyframes are stored
    (``aisdf.mapper.coverage``; ``max_keyframes_total`` only bounds submaps)."""
    if kind not in MAPPER_KINDS:
        raise ValueError(f"unknown mapper {kind!r} (one of {', '.join(MAPPER_KINDS)})")
    switches = dict(atlanta=atlanta, surfel_mask=surfel_mask, surfel_loss=surfel_loss, surfel_bounds=surfel_bounds)
    if kind == "single":
        return MappingPipeline.from_settings(preset, training, measured=measured, keyframes=keyframes, **switches)
    sub = submaps if isinstance(submaps, SubmapConfig) else SubmapConfig.model_validate(submaps or {})
    sub = sub.model_copy(update={"measured": sub.measured and measured})
    return SubmapPipeline.from_settings(preset, training, submaps=sub, keyframes=keyframes, **switches)


def restore_mapper(d: dict[str, Any]) -> Mapper:
    """A mapper checkpoint's mapper (``Mapper.checkpoint``), of either kind."""
    impl = SubmapPipeline if d.get("format") == SUBMAPS_CHECKPOINT else MappingPipeline
    return impl.restore(d)
