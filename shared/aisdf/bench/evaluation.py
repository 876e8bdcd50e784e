"""iSDF's three metrics on one set of points, with the ground truth computed once and shared
by every method (``aisdf.metrics`` does the arithmetic; isdf-reference.md, "Evaluation").

Points: ``metrics.eval_points`` over every 5th frame of the stream so far (the same
points for every method, also in real-time mode, where a model may have skipped some
of those frames), one point per ray, z uniform in [0.1, D + 0.1] for a signed ground truth or [0.1, D] for an unsigned
one. Points where the ground truth is undefined are left out. The gradient metric also
leaves out points inside walls (s < 0, signed fields) or whose 1 cm stencil leaves a
ground-truth grid. Ground-truth gradients: analytic for the synthetic buildings, else
central differences with 1 cm steps.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .. import metrics


class EvalSet:
    def __init__(self, scene, frames: Sequence[dict], n_points: int, seed: int | np.random.Generator = 0):
        p = metrics.eval_points(frames, n_points=n_points, every=1, rng=seed, far_margin=scene.far_margin)
        s = np.asarray(scene.gt_sdf(p), dtype=np.float64)
        keep = np.isfinite(s)
        self.points, self.gt = p[keep], s[keep]
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
        return {
            "sdf_error_cm": 100.0 * e,
            "collision_cost_error": metrics.collision_cost_error(f, self.gt, metrics.EPSILON),
            "gradient_cosine_distance": metrics.gradient_cosine_distance(np.asarray(g)[self.gmask], self.gt_grad),
            "n_points": int(len(self.points)),
            "n_gradient_points": int(self.gmask.sum()),
        }
