"""One submap as the submap mapper holds it: its cell, its trainer, and its publication state."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..mapping.trainer import Trainer
from .grid import cell_id

Cell = tuple[int, int, int]


@dataclass
class Submap:
    cell: Cell
    trainer: Trainer
    published_step: int = -1  # trainer steps at the last publication
    version: int = 0  # map version of its newest published snapshot
    observed_key: tuple = ()  # observed-space state its cached message was built for
    observed_msg: dict | None = None
    seen_by: list = field(default_factory=list)  # keyframe keys, arrival order
    dirty_since: int | None = None  # publication count when its first unpublished step was seen
    measured_changed: bool = False  # its measured points changed (cleared) since its last publication

    @property
    def id(self) -> str:
        return cell_id(self.cell)
