"""Configuration of surfel extraction (surfels.py) and the depth-noise model it uses."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..config import Model


class SurfelConfig(Model):
    """Surfel extraction; lengths in metres, angles in degrees."""

    stride: int | None = Field(None, description="block size for points and normals; None: from target_points")
    target_points: int = Field(4800, description="points per keyframe when stride is None")
    normal_deg: float = Field(25.0, description="a point belongs to direction v if its normal is within this of +-v")
    normal_smooth: int = Field(1, description="normals from inverse depth box-averaged over (2r+1)^2 blocks (0 = off)")
    max_jump: float = Field(0.1, description="relative depth jump that marks an occlusion edge (no normal)")
    pixel_jump: float = Field(0.03, description="adjacent-pixel relative depth step (or 4 sigma) dropping a block")
    planar_tol: float = Field(0.01, description="relative 2nd depth difference giving one-sided normals")
    inlier_min: float = Field(0.02, description="smallest plane inlier distance")
    inlier_sigmas: float = Field(2.5, description="inlier distance in depth-noise sigmas, when larger")
    noise_a: float = Field(0.0012, description="depth noise sigma(z) = a + b (z - z0)^2 (Kinect-like)")
    noise_b: float = Field(0.0019, description="see noise_a")
    noise_z0: float = Field(0.4, description="see noise_a")
    max_planes_per_direction: int = Field(4, description="RANSAC planes per Atlanta direction, at most")
    min_plane_points: int = Field(30, description="a plane needs this many inlier points")
    min_plane_fraction: float = Field(0.01, description="... and this share of the keyframe's points")
    cell_min: float = Field(0.04, description="occupancy grid cell, at least")
    cell_spacing: float = Field(1.5, description="occupancy grid cell in median point spacings, when larger")
    max_cells: int = Field(40000, description="occupancy grid size cap (the cell grows to fit)")
    n_candidates: int = Field(300, description="random rectangles per search")
    empty_penalty: float = Field(12.0, description="score = occupied cells - penalty * empty cells")
    min_fill: float = Field(0.9, description="a kept rectangle's occupied share of cells, at least")
    min_hull_fill: float = Field(0.8, description="convex hull area of its points / its area, at least")
    min_normal_share: float = Field(0.6, description="share of points on a rectangle with its direction's normal")
    max_rects_per_plane: int = Field(6, description="rectangles per plane, at most")
    min_rect_points: int = Field(20, description="points inside a kept rectangle, at least")
    min_area: float = Field(0.04, description="kept rectangle area (m^2), at least")
    min_side: float = Field(0.2, description="kept rectangle side, at least (thinner strips are often creases)")
    floor_axes: Literal["best", "reference"] = Field(
        "best", description="floor/ceiling rectangle axes: 'reference' = horizontal[0] (the paper); "
        "'best' = the Atlanta horizontal giving the tightest bounding box of the plane's points")


def choose_stride(H: int, W: int, config: SurfelConfig) -> int:
    if config.stride:
        return int(config.stride)
    return max(1, int(round(np.sqrt(H * W / config.target_points))))


def depth_sigma(z: np.ndarray, config: SurfelConfig) -> np.ndarray:
    return config.noise_a + config.noise_b * (z - config.noise_z0) ** 2


def inlier_threshold(z: np.ndarray, config: SurfelConfig) -> np.ndarray:
    return np.maximum(config.inlier_min, config.inlier_sigmas * depth_sigma(z, config))
