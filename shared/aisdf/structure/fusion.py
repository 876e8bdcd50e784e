"""The fused SDF of the paper's Sec. IV-D: the smaller of the implicit (network) and the
explicit (nearest surfel) distance; where the explicit one wins, its gradient is the
direction from the surfel point. Shared by the query service and the benchmark so both
compute the same thing.

The paper takes the smaller of the two at every point. Here a surfel counts only within
``radius`` (``DEFAULT_FUSE_RADIUS``, 2 m), so that a changed surfel changes answers only
near it (the query service's incremental bake re-evaluates only there). A surfel is a piece
of observed surface, so the distance to it bounds the distance to the nearest surface
however far it is: a larger radius only ever lowers an answer towards a surface that is
there (the radius was chosen by measurement: docs/experiments/fuse-radius.md)."""

from __future__ import annotations

import numpy as np

DEFAULT_FUSE_RADIUS = 2.0


def fuse(sdf_i: np.ndarray, grad_i: np.ndarray | None, sdf_e: np.ndarray, grad_e: np.ndarray | None,
         radius: float | None = DEFAULT_FUSE_RADIUS) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Returns (sdf, gradient or None, mask of points where the explicit map won).

    As the paper does, the explicit value is the (unsigned) distance to the closest surfel
    point: surfels are one-sided pieces of surface, so "behind a surfel" is not "inside an
    obstacle" (under a table top, behind a cabinet's front). Inside is the network's to say:
    where it is negative it is smaller and wins. The explicit distance is used only within
    ``radius`` of a surfel (see the module docstring; ``None``: everywhere, as the paper).
    ``sdf_e``/``grad_e`` may be signed (``surfel_map.explicit_sdf``); they are made unsigned
    here, the gradient pointing from the surfel point to the query point."""
    d_e = np.abs(sdf_e)
    use = d_e < sdf_i
    if radius is not None:
        use &= d_e <= radius
    sdf = np.where(use, d_e, sdf_i)
    grad = None
    if grad_i is not None:
        grad = np.array(grad_i, copy=True)
        if grad_e is not None:
            g_u = np.where((sdf_e < 0)[:, None], -grad_e, grad_e)
            grad[use] = g_u[use]
    return sdf, grad, use


def fused_sdf(points: np.ndarray, sdf_i: np.ndarray, grad_i: np.ndarray | None, surfels,
              radius: float | None = DEFAULT_FUSE_RADIUS) -> tuple[np.ndarray, np.ndarray | None]:
    """``fuse`` of the network's answer at ``points`` with the explicit distance to ``surfels``
    (none or empty: the network's answer as it is). Returns (sdf, gradient or None)."""
    if surfels is None or not len(surfels):
        return sdf_i, grad_i
    from .surfel_map import explicit_sdf

    d_e, g_e, _ = explicit_sdf(points, surfels)
    f, g, _ = fuse(sdf_i, grad_i, d_e, None if grad_i is None else g_e, radius)
    return f, g
