"""The answer planners are served by default (``source: "fused"``), composed in this one
function for the query service (exact answers and the bake), the benchmarks and the tests.

From the map's implicit answer (the network, or the blend of submaps) and the distance to
the surfel map: ``fusion.fuse`` (the paper's Sec. IV-D, surfels within ``radius``); where
the map carries measured points (protocols 1.4 and 1.5), the measured-surface rule on top
(``structure.measured.measured_fuse_grad``: the surfel distance where nothing was measured
nearer, capped at the nearest measured point); where the map predicts its layout beyond
what was observed (``structure.layout``, protocol 1.13), the nearest predicted surface point
caps the answer the same way, outside the surfaces only; and away from every measured point
(protocol 1.15) the answer is raised to the distance to the nearest surface the map holds
(``far_floor``)."""

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
FLOOR_NEAR = 0.1  # m from the nearest measured point where the far-field floor starts (``far_floor``)
FLOOR_BAND = 0.3  # m beyond FLOOR_NEAR over which it comes in fully
FLOOR_SUPPORT = 0.1  # m: a surfel bounds the floor where its nearest point is this near a measured point


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
    d_p = g_p = None
    if layout is not None and len(layout):
        d_p, g_p = layout.nearest(points, within=radius, workers=workers)
    if measured is not None:
        # A measured point counts within the radius only (measured_fuse_grad), so the search may stop there.
        d_m, g_m = measured.nearest(points, within=radius, workers=workers)
        sdf, grad = measured_fuse_grad(sdf, grad, sdf_i, d_e, g_e, d_m, g_m if grad is not None else None,
                                       radius=radius)
    if d_p is not None:
        sdf, grad = layout_cap(points, sdf, grad, layout, radius, workers, nearest=(d_p, g_p))
    if measured is not None:
        # A surfel counts within the radius only, as everywhere in the rule (the bake's changes rely on it).
        within = np.abs(np.asarray(d_e, np.float64)) <= radius
        support = surfel_support(points, d_e, g_e, d_m, measured, workers) & within
        sdf, grad = far_floor(sdf, grad, d_m, g_m, np.where(support, d_e, np.inf), g_e, d_p, g_p,
                              behind=(np.asarray(d_e) < 0) & within)
    return np.asarray(sdf, np.float32), (None if grad is None else np.asarray(grad, np.float32))


def surfel_support(points: np.ndarray, d_e: np.ndarray, g_e: np.ndarray | None, d_m: np.ndarray,
                   measured: NearestMeasured, workers: int = 1, support: float = FLOOR_SUPPORT) -> np.ndarray:
    """(N,) bool: where the nearest surfel's nearest point (``points - d_e g_e``) lies within
    ``support`` of a measured point, or where that does not matter (the surfel no nearer than
    the nearest measured point, or within ``FLOOR_NEAR`` of it). A surfel rectangle can reach
    past the surface it was fitted to (a wall's rectangle across the open side of a room's
    corner: 6 to 8 cm too near at 7 % of the points of one sparse walk); there the depth
    pixels measured nothing. Without ``g_e`` every surfel counts."""
    d_e = np.asarray(d_e, np.float64)
    d_m = np.asarray(d_m, np.float64)
    ok = np.ones(len(d_e), bool)
    if g_e is None:
        return ok
    ask = np.isfinite(d_e) & (np.abs(d_e) < d_m) & (d_m > FLOOR_NEAR)
    if ask.any():
        c = np.asarray(points, np.float64)[ask] - d_e[ask, None] * np.asarray(g_e, np.float64)[ask]
        ok[ask] = np.isfinite(measured.nearest(c, within=support, workers=workers)[0])
    return ok


def far_floor(sdf: np.ndarray, grad: np.ndarray | None, d_m: np.ndarray, g_m: np.ndarray,
              d_e: np.ndarray, g_e: np.ndarray | None, d_p: np.ndarray | None = None,
              g_p: np.ndarray | None = None, near: float = FLOOR_NEAR, band: float = FLOOR_BAND,
              behind: np.ndarray | None = None):
    """Away from the measured surface, the answer raised toward the distance to the nearest
    surface the map holds: the nearest measured point ``d_m``, surfel ``|d_e|`` (one that
    ``surfel_support`` finds measured there; inf for the others) or predicted point ``d_p``
    (inf where none), where the answer is positive and below it.

    Why. A network trained from depth rays answers well near what it saw and too low far from
    it: on a sparse walk (20 keyframes of an Atlanta room) the networks were 8 cm low at points
    over 1 m from every surface, the served answer 4 cm low, while the nearest measured point
    was within 1 cm of the truth there (docs/benchmarks.md, "A room the defaults never saw").
    A surface nearer than all of those is one the map never measured nor predicted, which no
    answer can know (a voxel map's distance field says the same). The weight ``w`` goes from 0
    at ``near`` from the nearest measured point to 1 at ``near + band``, so near surfaces the
    network's answer stands and nothing jumps; the answer is ``sdf + w (floor - sdf)``, its
    gradient the exact one of that blend. A point behind its nearest surfel (``behind``, by
    default ``d_e`` negative: inside an object whose faces were seen) is not raised."""
    sdf = np.asarray(sdf, np.float64)
    d_m = np.asarray(d_m, np.float64)
    cands = [d_m, np.abs(np.asarray(d_e, np.float64))]
    if d_p is not None:
        cands.append(np.asarray(d_p, np.float64))
    c = np.stack(cands, axis=1)
    which = np.argmin(c, axis=1)
    floor = c[np.arange(len(c)), which]
    w = np.clip((d_m - near) / band, 0.0, 1.0) if band > 0 else (d_m > near).astype(np.float64)
    # Not behind the nearest surfel (a face of a solid seen from outside: its inside is never observed).
    behind = np.asarray(d_e, np.float64) < 0 if behind is None else np.asarray(behind, bool)
    use = np.isfinite(d_m) & np.isfinite(floor) & (sdf > 0) & (floor > sdf) & (w > 0) & ~behind
    out = np.where(use, sdf + w * (np.where(use, floor, 0.0) - sdf), sdf)
    if grad is None:
        return out, None
    grad = np.asarray(grad, np.float64)
    g_e = np.zeros_like(grad) if g_e is None else np.asarray(g_e, np.float64)
    g_e = np.where((np.asarray(d_e, np.float64) < 0)[:, None], -g_e, g_e)  # of |d_e|: away from the surfel
    gs = [np.asarray(g_m, np.float64), g_e] + ([np.asarray(g_p, np.float64)] if d_p is not None else [])
    g_floor = np.stack(gs, axis=1)[np.arange(len(c)), which]
    ramp = use & (w < 1)
    g_w = np.where(ramp[:, None], np.asarray(g_m, np.float64) / band if band > 0 else 0.0, 0.0)
    g_new = grad + w[:, None] * (g_floor - grad) + np.where(ramp, floor - sdf, 0.0)[:, None] * g_w
    return out, np.where(use[:, None], g_new, grad)


def layout_cap(points: np.ndarray, sdf: np.ndarray, grad: np.ndarray | None, layout: NearestMeasured,
               radius: float = DEFAULT_FUSE_RADIUS, workers: int = 1, nearest=None):
    """The answer capped at the nearest predicted surface point plus ``LAYOUT_SLACK`` where
    that is nearer (outside the surfaces, within ``radius``); the gradient there points away
    from that point. ``nearest``: ``layout.nearest(points, within=radius)`` when already asked."""
    d_p, g_p = layout.nearest(points, within=radius, workers=workers) if nearest is None else nearest
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
    1.13's ``predicted``): positive, and at least the distance to the nearest predicted point
    less ``tol`` (the bake's tolerance for a baked answer): the cap holds them at most
    ``LAYOUT_SLACK`` above it, so the predicted surface bounds them."""
    sdf = np.asarray(sdf, np.float64)
    if layout is None or not len(layout):
        return np.zeros(len(sdf), bool)
    d_p, _ = layout.nearest(np.asarray(points, np.float64), within=radius)
    return (sdf > 0) & np.isfinite(d_p) & (sdf >= d_p - tol - 1e-6)
