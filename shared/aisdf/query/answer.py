"""The answer planners are served by default (``source: "fused"``), composed in this one
function for the query service (exact answers and the bake), the benchmarks and the tests.

From the map's implicit answer (the network, or the blend of submaps) and the distance to
the surfel map: ``fusion.fuse`` (the paper's Sec. IV-D, surfels within ``radius``); where
the map carries measured points (protocols 1.4 and 1.5), the measured-surface rule on top
(``structure.measured.measured_fuse_grad``: the surfel distance where nothing was measured
nearer, capped at the nearest measured point)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..structure.fusion import DEFAULT_FUSE_RADIUS, fuse
from ..structure.measured import measured_fuse_grad


class NearestMeasured(Protocol):
    """What the rule needs of measured points (``MeasuredPoints``, ``MeasuredSurface``)."""

    def nearest(self, q: np.ndarray, within: float | None = None,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]: ...


def served_answer(points: np.ndarray, sdf_i: np.ndarray, grad_i: np.ndarray | None,
                  d_e: np.ndarray | None, g_e: np.ndarray | None, measured: NearestMeasured | None,
                  radius: float = DEFAULT_FUSE_RADIUS, workers: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """(sdf (N,), gradient (N, 3) or None) served at ``points``. ``sdf_i``/``grad_i``: the
    map's implicit answer (gradient None: values only); ``d_e``/``g_e``: the (signed or
    unsigned) distance to the surfel map and its gradient (None: no surfels); ``measured``:
    the map's measured points (None: the map carries none, protocol 1.3's answer).
    ``workers``: threads of the nearest-point search."""
    if d_e is None:
        d_e, g_e = np.full(len(sdf_i), np.inf, np.float32), np.zeros((len(sdf_i), 3), np.float32)
    sdf, grad, _ = fuse(sdf_i, grad_i, d_e, g_e, radius)
    if measured is None:
        return sdf, grad
    # A measured point counts within the radius only (measured_fuse_grad), so the search may stop there.
    d_m, g_m = measured.nearest(points, within=radius, workers=workers)
    f, g = measured_fuse_grad(sdf, grad, sdf_i, d_e, g_e, d_m, g_m if grad is not None else None, radius=radius)
    return f.astype(np.float32), (None if g is None else g.astype(np.float32))
