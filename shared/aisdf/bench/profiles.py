"""Benchmark profiles (plain dicts) and the typed, resolved benchmark configuration.

* ``quick``: CI-sized, about two minutes on two CPU cores: one small synthetic scene,
  80x60 images, 4 s of stream, a 64-wide network, a quarter of iSDF's schedule,
  20k evaluation points; no 2 cm voxel map (its dense ESDF over the scene's box takes
  seconds per evaluation).
* ``standard``: this project's CPU figures: every scene, the ``cpu`` training preset
  (width 128, 4 x 100 rays a step), a quarter of iSDF's schedule, iSDF's 200k
  evaluation points; the Replica office on every 2nd pose at 300x170.
* ``paper``: the paper's setting, for a GPU: iSDF's network and sampling (``paper``
  preset) and its full schedule.

Command-line options override the profile; the resolved ``BenchConfig`` is written to
config.json beside the results.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator

from ..config import Model, deep_merge

ALL_SCENES = ["manhattan", "atlanta", "stairs", "replica-office", "7scenes-redkitchen"]
ALL_METHODS = ["voxel-5cm", "voxel-2cm", "isdf", "aisdf", "aisdf+explicit", "aisdf-served", "aisdf-served-noprior", "aisdf-baked"]

PROFILES: dict[str, dict[str, Any]] = {
    "quick": {
        "scenes": ["manhattan"], "ablation": ["manhattan"], "preset": "cpu",
        "methods": [m for m in ALL_METHODS if m != "voxel-2cm"],
        "training": {"network": {"width": 64}, "n_rays": 50, "window_size": 4},
        "schedule_scale": 0.25, "n_points": 20_000, "n_points_checkpoint": 5_000, "checkpoints": 3,
        "mesh_res": 0.12, "slice_res": 0.06, "threads": 1,
        "scene_opts": {
            "synthetic": {"n_frames": 120, "H": 60, "W": 80},
            "replica-office": {"scale": 0.125, "stride": 4, "max_frames": 120},
            "7scenes-redkitchen": {"reference_voxel": 0.02, "max_frames": 40},
        },
    },
    "standard": {
        "scenes": ALL_SCENES, "ablation": ["atlanta", "replica-office"], "preset": "cpu", "training": {},
        "schedule_scale": 0.25, "n_points": 200_000, "n_points_checkpoint": 50_000, "checkpoints": 5,
        "mesh_res": 0.06, "slice_res": 0.03, "threads": None,
        "scene_opts": {
            "synthetic": {"n_frames": 600, "H": 120, "W": 160},
            "replica-office": {"scale": 0.25, "stride": 2},
            "7scenes-redkitchen": {"reference_voxel": 0.01},
        },
    },
    "paper": {
        "scenes": ALL_SCENES, "ablation": ["atlanta", "replica-office"], "preset": "paper", "training": {},
        "schedule_scale": 1.0, "n_points": 200_000, "n_points_checkpoint": 50_000, "checkpoints": 8,
        "mesh_res": 0.04, "slice_res": 0.02, "threads": None,
        "scene_opts": {
            "synthetic": {"n_frames": 900, "H": 240, "W": 320},
            "replica-office": {"scale": 0.5, "stride": 1, "gt_grid": True},
            "7scenes-redkitchen": {"reference_voxel": 0.01},
        },
    },
}


class BenchConfig(Model):
    """Everything one ``aisdf bench`` run used (config.json)."""

    profile: str = Field("standard", description="the profile the values started from")
    scenes: list[str] = Field(default_factory=lambda: list(ALL_SCENES), description="scenes, in table order")
    methods: list[str] = Field(default_factory=lambda: list(ALL_METHODS), description="Table I columns")
    ablation: list[str] = Field(default_factory=list, description="scenes that also get Table II's four models")
    mode: Literal["iterations", "realtime"] = Field("iterations", description="equal iterations, or iSDF's replay")
    seeds: int | list[int] = Field(1, description="training seeds per scene: a count N (seeds 0..N-1) or the seeds "
                                   "themselves; tables give the mean and the spread (standard deviation) over them")
    out: str = Field("results/bench", description="results folder")
    data: str | None = Field(None, description="shared data folder (default: AISDF_DATA or ../shared/data)")
    cache_dir: str | None = Field(None, description="ground-truth grids and reference meshes are cached here")
    preset: str = Field("cpu", description="training preset (aisdf.mapping.presets)")
    training: dict[str, Any] = Field(default_factory=dict, description="TrainingConfig overrides on the preset")
    keyframes: dict[str, Any] = Field(default_factory=dict, description="frontend KeyframeConfig overrides")
    schedule_scale: float = Field(1.0, gt=0, description="iterations mode: times iSDF's 200 / 60 steps")
    n_points: int = Field(200_000, ge=100, description="evaluation points at the end of the sequence")
    n_points_checkpoint: int = Field(50_000, ge=100, description="evaluation points at earlier checkpoints")
    checkpoints: int = Field(5, ge=1, description="evaluations over sequence time (the last at the end)")
    mesh_res: float = Field(0.06, gt=0, description="marching-cubes grid of the network meshes (m)")
    slice_res: float = Field(0.03, gt=0, description="pixel size of the SDF slices (m)")
    slice_height: float = Field(0.35, ge=0, le=1, description="slice height, fraction from floor to ceiling")
    threads: int | None = Field(None, ge=1, description="torch threads (None: torch's default)")
    slowdown: float = Field(1.0, gt=0, description="realtime mode: compute time is multiplied by this")
    frames: int | None = Field(None, ge=2, description="use only the first N frames of every scene")
    artefacts: bool = Field(True, description="write meshes and figures (tables and config always)")
    progress: bool = Field(True, description="show a progress bar")
    scene_opts: dict[str, dict[str, Any]] = Field(default_factory=dict, description="per scene (or 'synthetic')")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v):
        if isinstance(v, list):
            if not v or len(set(v)) != len(v) or min(v) < 0:
                raise ValueError("seeds: a non-empty list of distinct seeds >= 0")
        elif v < 1:
            raise ValueError("seeds: a count of at least 1")
        return v

    @property
    def seed_list(self) -> list[int]:
        """The training seeds, in run order."""
        return list(self.seeds) if isinstance(self.seeds, list) else list(range(self.seeds))

    def opts_for(self, scene: str) -> dict:
        from .scenes import SYNTHETIC

        o = dict(self.scene_opts.get("synthetic", {})) if scene in SYNTHETIC else {}
        o.update(self.scene_opts.get(scene, {}))
        if self.frames:
            o["n_frames" if scene in SYNTHETIC else "max_frames"] = self.frames
        if self.cache_dir:
            o.setdefault("cache_dir", self.cache_dir)
        return o

    def training_for(self, seed: int) -> dict:
        t = deep_merge(self.training, {"seed": seed})
        t.setdefault("steps_first_frame", max(1, round(200 * self.schedule_scale)))
        t.setdefault("steps_per_keyframe", max(1, round(60 * self.schedule_scale)))
        return t


def resolve(profile: str = "standard", **overrides: Any) -> BenchConfig:
    """The profile's values with ``overrides`` (None values are ignored)."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
    data = deep_merge({**PROFILES[profile], "profile": profile}, {k: v for k, v in overrides.items() if v is not None})
    return BenchConfig.model_validate(data)
