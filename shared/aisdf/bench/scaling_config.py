"""The configuration of ``aisdf bench scaling`` (``scaling.py``): what is walked, how, and
the profiles (``full``, ``quick``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from ..config import Model, deep_merge

# mapper kind -> its label in the tables
LABELS: dict[str, str] = {"single": "single network", "submaps": "submaps"}


def make(kind: str, preset: str, training: dict):
    """A new mapper of ``kind`` as the bench walks it (the Atlanta structure on)."""
    from ..mapper.factory import make_mapper

    return make_mapper(kind, preset, training, atlanta=True)


class ScalingConfig(Model):
    scenes: list[str] = Field(default_factory=lambda: ["office", "floor"], description="synthetic buildings")
    mappers: list[str] = Field(default_factory=lambda: ["single", "submaps"], description="mapper kinds walked "
                               "(aisdf.mapper.MAPPER_KINDS)")
    keyframes: int = Field(200, ge=2, description="keyframes per walk")
    period_s: float = Field(1.0, gt=0, description="wall seconds between keyframes (and per publication)")
    tail_s: float = Field(60.0, ge=0, description="training after the walk (wall seconds)")
    after_visit_s: float = Field(5.0, ge=0, description="a room is scored this long after the camera leaves it")
    preset: str = Field("cpu", description="training preset")
    training: dict[str, Any] = Field(default_factory=dict, description="TrainingConfig overrides")
    H: int = Field(120, ge=8)
    W: int = Field(160, ge=8)
    noise: bool = Field(True, description="Kinect-like depth noise")
    n_points: int = Field(200_000, ge=100, description="whole-map evaluation points")
    n_room_points: int = Field(20_000, ge=50, description="evaluation points per room")
    seed: int = Field(0, description="building, walk, noise and training seed")
    seeds: int = Field(1, ge=1, description="walks per method and scene, seeds seed, seed + 1, ...; the table and "
                       "the criteria take their mean (scaling_seeds.py)")
    threads: int | None = Field(None, ge=1, description="torch threads (None: torch's default)")
    out: str = Field("runs/bench-scaling", description="results folder")
    progress: bool = Field(True, description="print a line per event")
    source: Literal["served", "fused", "implicit", "measured"] = Field(
        "served", description="the answer scored (and judged by the criteria): served = query/sdf's default for "
        "the mapper (fused with its published measured points: protocol 1.4 with submaps, 1.5 with one network; "
        "fused for a mapper that sends none), fused = the network and surfel map (1.3's answer), implicit = the network alone, "
        "measured = fused with the measured surface; all are in the table")


PROFILES: dict[str, dict[str, Any]] = {
    "full": {},
    "quick": {"keyframes": 12, "period_s": 0.25, "tail_s": 2.0, "after_visit_s": 0.0, "H": 48, "W": 64,
              "n_points": 3000, "n_room_points": 300,
              "training": {"network": {"width": 64}, "n_rays": 40, "window_size": 3}},
}


def resolve(profile: str = "full", **overrides: Any) -> ScalingConfig:
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
    return ScalingConfig.model_validate(deep_merge(PROFILES[profile], {k: v for k, v in overrides.items()
                                                                        if v is not None}))
