"""Bounds and approximate gradients: iSDF's "batch distance" and the paper's Eqs. 1-2.

Reference points P = every SURFACE sample of the batch (the points at the measured
depth of all rays of all window frames) plus every SURFEL point (present only when the
AiSDF switches put them in the batch; then this is Eq. 1's set of surface and surfel
points). For a ray sample x at camera depth z on a ray of measured depth D, with p its
nearest point of P and s = +1 if z <= D else -1 (behind the measured surface):

    bound b = s |x - p|,   gradient target g = s (x - p) / |x - p|   (NaN when x = p).

SURFACE samples get b = 0 and g = their depth-image normal; SURFEL points b = 0 and
g = their surfel normal (the Atlanta direction pointing to free space).

Nearest-point search: ``"kdtree"`` (scipy cKDTree on the CPU) or ``"cdist"`` (torch.cdist
in chunks of queries, on the batch's device). On a 2-core CPU for iSDF's batch (26k
queries, 1000 references) the KD-tree took 9-13 ms and cdist 50 ms (chunks of 2048; 55-130 ms
with larger chunks), so ``auto``
uses the KD-tree on CPU and cdist on CUDA.
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry import kdtree
from .sampling import FREE, SURFACE, SURFEL


def nearest_index(queries: torch.Tensor, refs: torch.Tensor, method: str = "auto", chunk: int = 2048) -> torch.Tensor:
    """Index (Q,) into ``refs`` (P, 3) of each query's (Q, 3) nearest reference point."""
    if method == "auto":
        method = "kdtree" if queries.device.type == "cpu" else "cdist"
    if len(refs) == 0 or len(queries) == 0:
        return torch.zeros(len(queries), dtype=torch.long, device=queries.device)
    if method == "kdtree":
        tree = kdtree(refs.detach().cpu().numpy().astype(np.float64))
        _, idx = tree.query(queries.detach().cpu().numpy().astype(np.float64), k=1,
                            workers=max(1, torch.get_num_threads()))
        return torch.as_tensor(idx, dtype=torch.long, device=queries.device)
    if method == "cdist":
        out = [torch.cdist(q, refs).argmin(dim=1) for q in torch.split(queries.detach(), chunk)]
        return torch.cat(out)
    raise ValueError(f"unknown bound method {method!r}")


def batch_bounds(
    points: torch.Tensor, z: torch.Tensor, ray_depth: torch.Tensor, kind: torch.Tensor, target: torch.Tensor,
    method: str = "auto", chunk: int = 2048,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bound (M,) and gradient target (M, 3) of every sample (see the module docstring).

    points (M, 3); z, ray_depth (M,); kind (M,) FREE/SURFACE/SURFEL; target (M, 3) used
    as the gradient target of SURFACE and SURFEL points. No gradients flow through.
    """
    with torch.no_grad():
        points = points.detach()
        b = torch.zeros(len(points), dtype=points.dtype, device=points.device)
        g = target.detach().clone().to(points.dtype)
        free = kind == FREE
        refs = points[(kind == SURFACE) | (kind == SURFEL)]
        if free.any() and len(refs):
            x = points[free]
            vec = x - refs[nearest_index(x, refs, method, chunk)]
            dist = vec.norm(dim=1)
            sign = torch.where(z[free] > ray_depth[free], -1.0, 1.0).to(points.dtype)
            b[free] = sign * dist
            unit = vec / dist[:, None]
            unit[dist == 0] = float("nan")
            g[free] = sign[:, None] * unit
        elif free.any():
            b[free] = float("nan")
            g[free] = float("nan")
    return b, g


def tighten_bounds(b: torch.Tensor, g: torch.Tensor, batch, prior) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Caps the bound of every FREE sample by ``prior``'s distance to known surface
    (``TrainingConfig.surfel_bounds``): any surface point bounds |SDF|, so
    ``|b| <= min(batch distance, prior distance)``; where the prior is nearer, the gradient
    target is its direction (signed like the bound). ``prior(points (K, 3) float64)`` ->
    (distance (K,), unit direction from the nearest surface point (K, 3)); inf = unknown.
    Also returns the mask (M,) of the samples whose bound the prior set."""
    used = torch.zeros(len(b), dtype=torch.bool, device=b.device)
    free = np.flatnonzero(batch.kind == FREE)
    if not len(free):
        return b, g, used
    d, u = prior(batch.points_W[free].astype(np.float64))
    d_t = torch.as_tensor(d, dtype=b.dtype, device=b.device)
    idx = torch.as_tensor(free, device=b.device)
    cur = b[idx]
    closer = torch.isfinite(d_t) & (d_t < cur.abs())
    if not bool(closer.any()):
        return b, g, used
    sign = torch.where(cur < 0, -1.0, 1.0).to(b.dtype)
    u_t = torch.as_tensor(u, dtype=g.dtype, device=g.device)
    b, g = b.clone(), g.clone()
    sel = idx[closer]
    b[sel] = (sign * d_t)[closer]
    g[sel] = (sign[:, None] * u_t)[closer]
    used[sel] = True
    return b, g, used
