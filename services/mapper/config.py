"""Mapper service configuration (defaults here; file, AISDF_* environment, command line)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from aisdf.config import Model, ServiceConfig
from aisdf.mapper.coverage import KeyframePolicy
from aisdf.submaps.config import SubmapConfig


class ClusterConfig(Model):
    """Mapper shards (protocol 1.14): several mappers in one namespace share the map's regions."""

    enabled: bool = Field(False, description="share the map with the other mappers of the namespace that have it on "
                          "(each trains the regions it ranks first for, keeps the keyframes of those it ranks "
                          "second for); off: this mapper maps everything alone, as in 1.11")
    mapper_id: str | None = Field(None, description="this mapper's stable id (its liveliness token "
                                  "status/mapper/<id> and its rank in every region); default: the host name and, with "
                                  "a checkpoint directory, a hash of its absolute path (stable across restarts), else "
                                  "the host name and the process id")
    region_cells: int = Field(2, ge=1, description="a region is this many x this many submap cells (one layer)")
    replicas: int = Field(2, ge=1, le=3, description="owners per region: rank 1 trains, ranks 2.. keep the keyframes")
    start_wait_s: float = Field(1.5, gt=0, description="at start, how long to wait for the members and the map's frame")
    slots: bool = Field(False, description="with a checkpoint directory several mappers share (docker compose --scale "
                        "mapper=N): claim its first free slot-<n> subdirectory (locked while this mapper runs) for "
                        "this mapper's state, and the id mapper-<n> unless mapper_id is set")

    @field_validator("mapper_id")
    @classmethod
    def _id(cls, v):
        if v is not None and (not v or any(c in v for c in "/*$?#@ ")):
            raise ValueError(f"mapper_id {v!r}: a non-empty key chunk without / * $ ? # @ or spaces")
        return v


class MapperConfig(ServiceConfig):
    """Settings of ``aisdf-mapper``."""

    LEGACY_KEYS: ClassVar[tuple[str, ...]] = ("submaps",)  # before ``mapper`` (files, AISDF_SUBMAPS)

    preset: Literal["auto", "paper", "cpu"] = Field(
        "auto", description="training preset: paper = iSDF's numbers exactly; cpu = tuned for a 2-core CPU; "
        "auto = paper with CUDA, else cpu")
    training: dict[str, Any] = Field(
        default_factory=dict, description="overrides of the preset's training fields, e.g. {rays_per_frame: 150}")
    atlanta: bool = Field(True, description="estimate the Atlanta frame and surfels, publish map/surfels")
    surfel_mask: bool = Field(True, description="Table II switch: sample iSDF rays off surfels, points on surfels")
    surfel_loss: bool = Field(True, description="Table II switch: the surfel loss on surfel points")
    surfel_bounds: bool = Field(True, description="beyond the paper: the global surfel map also bounds the "
                                "training samples' distances (training.surfel_bounds; docs/experiments/scaling-notes.md, Surfel bounds)")
    mapper: Literal["submaps", "single"] = Field(
        "submaps", description="submaps: one network per submap (protocol 1.3: map/submaps/<id> and map/index, only "
        "what changed each period); single: one network for the whole map (map/weights)")
    submap: SubmapConfig = Field(default_factory=SubmapConfig, description="submap cells and step sharing")
    keyframes: KeyframePolicy = Field(default_factory=KeyframePolicy, description="keyframes that add nothing new "
                                      "are acknowledged but not stored; the submap mapper stores at most "
                                      "keyframes.max_keyframes_total")
    measured: bool = Field(True, description="pool the keyframes' depth pixels into 10 cm voxels and publish the "
                           "points with the map, for the query service's fused answers (protocol 1.4 with submaps, "
                           "1.5 with one network); false = no points (submap.measured: false also turns them off "
                           "for submaps, as in 1.4)")
    queue_max: int = Field(16, ge=1, description="keyframes waiting to be trained on; the oldest is dropped beyond")
    snapshot_period_s: float = Field(1.0, gt=0, description="how often weights (and surfels) are published")
    checkpoint_dir: Path | None = Field(None, description="where the map is checkpointed and resumed from")
    checkpoint_period_s: float = Field(30.0, gt=0, description="how often the checkpoint is written")
    torch_threads: int | None = Field(None, ge=1, description="torch CPU threads; None keeps torch's default")
    idle_sleep_s: float = Field(0.05, gt=0, description="sleep when there is nothing to train on")
    cluster: ClusterConfig = Field(default_factory=ClusterConfig, description="mapper shards (protocol 1.14)")

    @model_validator(mode="before")
    @classmethod
    def _submaps_switch(cls, data: Any) -> Any:
        """Configuration files written before ``mapper`` said ``submaps: true | false``; it
        still reads (``submaps: false`` is ``mapper: single``)."""
        if isinstance(data, dict) and "submaps" in data:
            data = dict(data)
            flag = data.pop("submaps")
            if isinstance(flag, str):
                flag = flag.strip().lower() in ("1", "true", "yes", "on")
            data.setdefault("mapper", "submaps" if flag else "single")
        return data
