"""The answer planners are served by default (``source: "fused"``), composed in this one
function for the query service (exact answers and the bake), the benchmarks and the tests.

From the map's implicit answer (the network, or the blend of submaps) and the distance to
the surfel map: ``fusion.fuse`` (the paper's Sec. IV-D, surfels within ``radius``); where
the map carries measured points (protocols 1.4 and 1.5), the measured-surface rule on top
(``structure.measured.measured_fuse_grad``: the surfel distance where nothing was measured
nearer, capped at the nearest measured point); where the map predicts its layout beyond
what was observed (``structure.layout``, protocol 1.13), the nearest predicted surface point
caps the answer the same way, outside the surfaces only."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..structure.fusion import DEFAULT_FUSE_RADIUS, fuse
from ..structure.measured import measured_fuse_grad


class NearestMeasured(Protocol):
    """What the rule needs of measured points (``MeasuredPoints``, ``MeasuredSurface``)."""

    def nearest(self, q: np.ndarray, within: float | None = None,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]: ...


LAYOUT_SLACK = 0.01  # m added to the distance to the nearest predicted point, as to a measured one


def served_answer(points: np.ndarray, sdf_i: np.ndarray, grad_i: np.ndarray | None,
                  d_e: np.ndarray | None, g_e: np.ndarray | None, measured: NearestMeasured | None,
                  radius: float = DEFAULT_FUSE_RADIUS, workers: int = 1,
                  layout: NearestMeasured | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(sdf (N,), gradient (N, 3) or None) served at ``points``. ``sdf_i``/``grad_i``: the
    map's implicit answer (gradient None: values only); ``d_e``/``g_e``: the (signed or
    unsigned) distance to the surfel map and its gradient (None: no surfels); ``measured``:
    the map's measured points (None: the map carries none, protocol 1.3's answer).
    ``workers``: threads of the nearest-point search. ``layout``: the map's predicted surface
    points (``predicted_layout``; None: no prior)."""
    if d_e is None:
        d_e, g_e = np.full(len(sdf_i), np.inf, np.float32), np.zeros((len(sdf_i), 3), np.float32)
    sdf, grad, _ = fuse(sdf_i, grad_i, d_e, g_e, radius)
    if measured is not None:
        # A measured point counts within the radius only (measured_fuse_grad), so the search may stop there.
        d_m, g_m = measured.nearest(points, within=radius, workers=workers)
        sdf, grad = measured_fuse_grad(sdf, grad, sdf_i, d_e, g_e, d_m, g_m if grad is not None else None,
                                       radius=radius)
    if layout is not None and len(layout):
        sdf, grad = layout_cap(points, sdf, grad, layout, radius, workers)
    return np.asarray(sdf, np.float32), (None if grad is None else np.asarray(grad, np.float32))


def layout_cap(points: np.ndarray, sdf: np.ndarray, grad: np.ndarray | None, layout: NearestMeasured,
               radius: float = DEFAULT_FUSE_RADIUS, workers: int = 1):
    """The answer capped at the nearest predicted surface point plus ``LAYOUT_SLACK`` where
    that is nearer (outside the surfaces, within ``radius``); the gradient there points away
    from that point."""
    d_p, g_p = layout.nearest(points, within=radius, workers=workers)
    sdf = np.asarray(sdf, np.float64)
    cap = d_p + LAYOUT_SLACK
    use = (sdf > 0) & (cap < sdf)
    sdf = np.where(use, cap, sdf)
    if grad is not None:
        grad = np.where(use[:, None], g_p, grad)
    return sdf, grad


def predicted_layout(state, cfg=None):
    """The predicted surface points of a map (``query.mapstate.MapState``: its surfels, observed
    space and bounds) as ``MeasuredPoints``, or None where nothing is predicted; computed once
    per map state (kept on it: a state is replaced whole, never changed)."""
    cached = getattr(state, "_layout_points", False)
    if cached is not False:
        return cached
    from ..structure.layout import LayoutConfig, predict
    from ..structure.measured import MeasuredPoints

    pts = predict(state.surfels, state.observed, state.bounds, None, cfg or LayoutConfig())
    out = MeasuredPoints(pts) if len(pts) else None
    object.__setattr__(state, "_layout_points", out)  # a frozen dataclass: a cache, not a field
    return out


def predicted_mask(layout: NearestMeasured | None, points: np.ndarray, sdf: np.ndarray,
                   radius: float = DEFAULT_FUSE_RADIUS, tol: float = 0.0) -> np.ndarray:
    """(N,) bool: the served distances ``sdf`` that rest on the predicted layout (protocol
    1.13's ``predicted``): positive, and within ``tol`` (the bake's tolerance for a baked
    answer) of the distance to the nearest predicted point plus ``LAYOUT_SLACK``."""
    sdf = np.asarray(sdf, np.float64)
    if layout is None or not len(layout):
        return np.zeros(len(sdf), bool)
    d_p, _ = layout.nearest(np.asarray(points, np.float64), within=radius)
    return (sdf > 0) & np.isfinite(d_p) & (sdf >= d_p + LAYOUT_SLACK - tol - 1e-6)
