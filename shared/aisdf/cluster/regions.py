"""Which regions a keyframe touches (protocol 1.14): the submap cells whose extended boxes
(core grown by the overlap) hold any of the points sampled along its rays (every 8th pixel,
4 points per ray, the last on the surface: what the submap mapper assigns keyframes by), and
the regions of those cells. A superset of the cells the keyframe is trained in."""

from __future__ import annotations

import numpy as np

from .. import geometry
from ..submaps.grid import SubmapGrid
from .ownership import region_id, region_of


def ray_points(depth_m: np.ndarray, K: np.ndarray, T_WC: np.ndarray, stride: int = 8) -> np.ndarray:
    d = np.asarray(depth_m)[::stride, ::stride]
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    K, T = np.asarray(K, np.float64), np.asarray(T_WC, np.float64)
    D = d[v, u].astype(np.float64)
    uu, vv = u * stride, v * stride
    dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones(len(D))], axis=-1)
    fr = np.array([0.25, 0.5, 0.75, 1.0])
    pts_C = dirs[:, None, :] * (D[:, None] * fr)[..., None]
    return np.concatenate([geometry.transform(T, pts_C.reshape(-1, 3)), T[None, :3, 3]])


def touched_cells(grid: SubmapGrid, depth_m, K, T_WC) -> set[tuple[int, int, int]]:
    return set(grid.cells_touching(ray_points(depth_m, K, T_WC)))


def touched_regions(grid: SubmapGrid, depth_m, K, T_WC, region_cells: int = 2) -> list[str]:
    """Sorted region ids the keyframe touches."""
    return sorted({region_id(region_of(c, region_cells)) for c in touched_cells(grid, depth_m, K, T_WC)})
