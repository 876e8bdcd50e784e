"""The fused SDF of the paper's Sec. IV-D: the smaller of the implicit (network) and the
explicit (nearest surfel) distance, where a surfel is near; where the explicit one wins,
its gradient is the direction from the surfel point. Shared by the query service and the
benchmark so both compute the same thing."""

from __future__ import annotations

import numpy as np

DEFAULT_FUSE_RADIUS = 0.5


def fuse(sdf_i: np.ndarray, grad_i: np.ndarray | None, sdf_e: np.ndarray, grad_e: np.ndarray | None,
         radius: float = DEFAULT_FUSE_RADIUS) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Returns (sdf, gradient or None, mask of points where the explicit map won).

    The explicit distance is used only within ``radius`` of a surfel: far from every
    surfel the nearest rectangle says nothing about the obstacles in between, and a point
    behind a distant wall surfel (negative explicit distance) may be free space of the
    next room."""
    use = (np.abs(sdf_e) <= radius) & (sdf_e < sdf_i)
    sdf = np.where(use, sdf_e, sdf_i)
    grad = None
    if grad_i is not None:
        grad = np.array(grad_i, copy=True)
        if grad_e is not None:
            grad[use] = grad_e[use]
    return sdf, grad, use
