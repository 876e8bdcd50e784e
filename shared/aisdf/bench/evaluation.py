"""iSDF's three metrics on one set of points, with the ground truth computed once and shared
by every method (``aisdf.metrics`` does the arithmetic; isdf-reference.md, "Evaluation").

Points: ``metrics.eval_points`` over every 5th frame of the stream so far (the same
points for every method, also in real-time mode, where a model may have skipped some
of those frames), one point per ray, z uniform in [0.1, D + 0.1] for a signed ground truth or [0.1, D] for an unsigned
one. Points where the ground truth is undefined are left out. The gradient metric also
leaves out points inside walls (s < 0, signed fields) or whose 1 cm stencil leaves a
ground-truth grid. Ground-truth gradients: analytic for the synthetic buildings, else
central differences with 1 cm steps.

Observed / unobserved (``split=True``, the final evaluation: Table Ib): a point's nearest
true surface point is ``p - s * n`` with ``s`` its ground-truth distance and ``n`` the unit
ground-truth gradient (the synthetic buildings: the exact SDF and its analytic gradient;
the meshes: the point-to-mesh distance and its gradient, so the closest mesh point itself
for the exact distance, within about a centimetre for a 1 cm grid). It is *observed* when
a measured depth point lies within ``OBSERVED_M`` (5 cm) of it: any valid pixel (depth up
to the scene's ``max_depth``, as the maps use it) of the frames the points are drawn from
(every 5th frame of the stream), back-projected, thinned to one per 1 cm voxel. Else
*unobserved*: a surface no camera measured (behind furniture, beyond the walls, the far
side of a corner), whose distance every map has to guess.

Near furniture (``split=True`` on a labelled synthetic building; Table I's near-furniture
rows): a point is *near furniture* when the primitive its exact SDF comes from (its nearest
surface, for a point in free space) is furniture, or when it lies within ``NEAR_FURNITURE_M``
(30 cm) of a furniture surface or inside furniture (``Scene.furniture_distance``). Furniture
is every labelled box that is not layout (``aisdf.synthetic.scene``: tables, chairs, shelves,
cabinets, boxes, the staircase; the layout is the room's walls, floor and ceiling and the
floor's interior walls). The meshes and the 7-Scenes reference carry no such labels: their
split is None (the tables say n/a).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .. import metrics
from ..geometry import backproject, kdtree, transform, valid_depth

OBSERVED_M = 0.05  # a nearest true surface point this close to a measured depth point is observed
THIN_M = 0.01  # measured points: one per voxel of this edge
NEAR_FURNITURE_M = 0.30  # a point this close to a furniture surface (or inside furniture) is near furniture


def labelled_building(scene):
    """The labelled synthetic building behind a bench scene (``aisdf.synthetic.Scene`` with
    ``kinds``), or None (a mesh, a reference, an unlabelled scene)."""
    building = getattr(getattr(scene, "frames", None), "scene", None)
    return building if getattr(building, "kinds", None) is not None else None


def near_furniture_mask(building, points: np.ndarray, within: float = NEAR_FURNITURE_M) -> np.ndarray:
    """(N,) bool: the nearest primitive of each world point is furniture, or a furniture
    surface lies within ``within`` of it (or it is inside furniture). Module docstring."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    return building.nearest_is_furniture(points) | (building.furniture_distance(points) <= within)


def measured_depth_points(frames: Sequence[dict], max_depth: float, voxel: float = THIN_M) -> np.ndarray:
    """(M, 3): every valid pixel of ``frames`` back-projected into the world, one per ``voxel``."""
    out = []
    for f in frames:
        d = np.asarray(f["depth"], np.float64)
        ok = valid_depth(d, max_depth)
        out.append(transform(np.asarray(f["T_WC"], np.float64), backproject(d, f["K"])[ok]))
    pts = np.concatenate(out) if out else np.zeros((0, 3))
    if not len(pts):
        return pts
    _, first = np.unique(np.floor(pts / voxel).astype(np.int64), axis=0, return_index=True)
    return pts[first]


def nearest_surface(scene, points: np.ndarray, sdf: np.ndarray) -> np.ndarray:
    """(N, 3): the nearest true surface point of each point, ``p - s * n`` (module docstring)."""
    if scene.gt_grad is not None:
        n = np.asarray(scene.gt_grad(points), dtype=np.float64)
    else:
        n = metrics.gt_gradient_central(scene.gt_sdf, points, metrics.GRAD_STEP)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-9, n / np.maximum(norm, 1e-12), 0.0)
    return points - sdf[:, None] * n


def observed_mask(scene, frames: Sequence[dict], points: np.ndarray, sdf: np.ndarray,
                  within: float = OBSERVED_M) -> np.ndarray:
    """(N,) bool: the nearest true surface point of each point lies within ``within`` of a
    measured depth point of ``frames``."""
    measured = measured_depth_points(frames, scene.max_depth)
    if not len(measured) or not len(points):
        return np.zeros(len(points), bool)
    q = nearest_surface(scene, points, sdf)
    ok = np.all(np.isfinite(q), axis=1)  # a gradient undefined there (off a ground-truth grid): not known observed
    out = np.zeros(len(points), bool)
    d, _ = kdtree(measured).query(q[ok], distance_upper_bound=within)
    out[ok] = np.isfinite(d)
    return out


class EvalSet:
    def __init__(self, scene, frames: Sequence[dict], n_points: int, seed: int | np.random.Generator = 0,
                 split: bool = False):
        p = metrics.eval_points(frames, n_points=n_points, every=1, rng=seed, far_margin=scene.far_margin)
        s = np.asarray(scene.gt_sdf(p), dtype=np.float64)
        keep = np.isfinite(s)
        self.points, self.gt = p[keep], s[keep]
        # Table Ib: whether each point's nearest true surface was measured (None: not split)
        self.observed = observed_mask(scene, frames, self.points, self.gt) if split else None
        # Table I's near-furniture rows: None where not split or the scene has no labels
        building = labelled_building(scene) if split else None
        self.near_furniture = None if building is None else near_furniture_mask(building, self.points)
        if hasattr(scene.gt_sdf, "gradient_mask"):
            self.gmask = np.asarray(scene.gt_sdf.gradient_mask(self.points, metrics.GRAD_STEP), dtype=bool)
        else:
            self.gmask = self.gt >= 0 if scene.signed else np.ones(len(self.gt), bool)
        pg = self.points[self.gmask]
        if scene.gt_grad is not None:
            self.gt_grad = np.asarray(scene.gt_grad(pg), dtype=np.float64)
        else:
            self.gt_grad = metrics.gt_gradient_central(scene.gt_sdf, pg, metrics.GRAD_STEP)

    def __len__(self) -> int:
        return len(self.points)

    def score(self, query: Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]) -> dict:
        """``query(points, grad) -> (sdf (N,), gradient (N, 3))`` of a method -> the three metrics."""
        f, g = query(self.points, True)
        f = np.asarray(f, dtype=np.float64)
        e = metrics.sdf_error(f, self.gt)
        out = {
            "sdf_error_cm": 100.0 * e,
            "collision_cost_error": metrics.collision_cost_error(f, self.gt, metrics.EPSILON),
            "gradient_cosine_distance": metrics.gradient_cosine_distance(np.asarray(g)[self.gmask], self.gt_grad),
            "n_points": int(len(self.points)),
            "n_gradient_points": int(self.gmask.sum()),
        }
        if self.observed is not None:
            out.update(self.split(f))
        return out

    def split(self, f: np.ndarray) -> dict:
        """Mean SDF error (cm) on the points whose nearest true surface was observed and on the
        others (NaN where there are none), and the share of each; on a labelled building also
        near furniture, away from it, and near it where unobserved."""
        err = np.abs(np.asarray(f, np.float64) - self.gt)
        obs = self.observed
        n = max(len(err), 1)
        mean = lambda m: 100.0 * float(err[m].mean()) if m.any() else float("nan")  # noqa: E731
        out = {"sdf_error_observed_cm": mean(obs), "sdf_error_unobserved_cm": mean(~obs),
               "observed_share": float(obs.sum()) / n, "unobserved_share": float((~obs).sum()) / n}
        near = self.near_furniture
        if near is not None:  # near furniture, and the part of it whose nearest surface no camera measured
            out.update({"near_furniture_share": float(near.sum()) / n, "sdf_error_near_furniture_cm": mean(near),
                        "sdf_error_away_from_furniture_cm": mean(~near),
                        "near_furniture_unobserved_share": float((near & ~obs).sum()) / n,
                        "sdf_error_near_furniture_unobserved_cm": mean(near & ~obs)})
        return out
