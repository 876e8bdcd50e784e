"""The mapper interface: what the mapper service, the benchmarks and the tests may use of a
mapper, and all they use. Two implementations: one network for the whole map
(:class:`aisdf.mapper.single.MappingPipeline`, ``mapper: single``) and one network per
submap (:class:`aisdf.submaps.pipeline.SubmapPipeline`, ``mapper: submaps``, the default).

    mapper = make_mapper("submaps", preset="cpu")       # aisdf.mapper.factory
    mapper.add_keyframe(keyframe)      # protocol.Keyframe (the wire's) or mapping.Frame
    mapper.step()                      # one training step
    mapper.map_messages(version)       # [(key under the namespace, payload)] to publish
    restore_mapper(mapper.checkpoint())

Arrays in, arrays out, messages as bytes: no Zenoh and no files here.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from .. import protocol
from ..mapping.config import TrainingConfig
from ..mapping.frames import Frame
from ..observed import ObservedSpace
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels

MAPPER_KINDS: tuple[str, ...] = ("submaps", "single")  # the first is the default


@runtime_checkable
class Mapper(Protocol):
    """A map learnt from keyframes. Every method is called from one thread at a time."""

    kind: str  # one of MAPPER_KINDS
    atlanta_on: bool  # the Atlanta frame and surfels are estimated

    @property
    def cfg(self) -> TrainingConfig:
        """The training configuration (of every network; a submap's differs only in its centre)."""

    @property
    def steps(self) -> int:
        """Training steps taken."""

    @property
    def n_keyframes(self) -> int:
        """Keyframes in the map."""

    @property
    def ready(self) -> bool:
        """Can ``step`` train (a keyframe, and for submaps a grid, is there)?"""

    @property
    def observed(self) -> ObservedSpace:
        """The space the keyframes observed."""

    @property
    def measured(self) -> MeasuredSurface | None:
        """The keyframes' depth pixels pooled in 10 cm voxels (None: the mapper pools none)."""

    def describe(self) -> str:
        """One line for logs: the mapper's kind and main settings."""

    def add_keyframe(self, kf: protocol.Keyframe | Frame) -> bool:
        """Add a keyframe: True when stored; False when it adds nothing new (``coverage``: not
        stored, counted in ``stats()["redundant"]``; it is in the map's knowledge all the same,
        and the service acknowledges it). Raises ValueError and changes nothing for one that
        cannot be used: a duplicate (sensor, frame_id), too few valid depth pixels, a bad mask."""

    def keyframe_keys(self) -> list[tuple[str, int]]:
        """(sensor, frame_id) of every keyframe in the map, in arrival order."""

    def step(self) -> dict:
        """One training step; its loss and timings."""

    def stats(self) -> dict:
        """Mean per-module timings (ms) over recent steps and keyframes, and counters
        (``redundant``: keyframes not stored; submaps: ``evicted``)."""

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """(N,) the map's implicit SDF (the networks alone) at (N, 3) world points."""

    def surfels(self) -> Surfels | None:
        """The global surfel map (None without the Atlanta structure)."""

    def measured_points(self) -> np.ndarray:
        """(M, 3) the measured points the map's messages carry (none without pooling)."""

    def surfel_map(self, version: int) -> protocol.SurfelMap | None:
        """The ``map/surfels`` message (None without structure or an Atlanta frame yet)."""

    def map_messages(self, version: int, changed_only: bool = True, epoch: int = 0,
                     mark: bool = True) -> list[tuple[str, bytes]]:
        """What the mapper publishes for map ``version``: (key under the namespace, payload).
        ``changed_only``: only what changed since the last publication; ``mark`` False:
        nothing is recorded as published (what a publication would cost)."""

    def repose(self, corrections: dict) -> dict:
        """Protocol 1.11: new camera-to-world poses ``{(sensor, frame_id): (4, 4)}`` for stored
        keyframes; the map follows (``aisdf.mapper.repose``). Returns ``reposed`` (count),
        ``unknown`` (keys not held), ``unchanged``, ``submaps`` (ids retrained) and ``timings_ms``.
        ValueError (and nothing changed) for a key or a pose that is not one."""

    def memory(self) -> dict[str, int]:
        """Bytes held, by part: keyframes, model (weights and AdamW moments), observed, measured."""

    def checkpoint(self) -> dict:
        """Everything to resume (plain types and numpy arrays); ``factory.restore_mapper`` reads it."""

    @classmethod
    def restore(cls, d: dict[str, Any]) -> "Mapper":
        """The mapper of ``checkpoint()``."""
