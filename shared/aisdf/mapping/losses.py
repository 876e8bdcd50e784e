"""Losses as pure functions (isdf-reference.md "Loss"; paper Sec. III-E).

Per point, with SDF f, gradient ∇f, bound b and gradient target g:

* SDF term: free space (b > t): max(relu(f - b), exp(-beta f) - 1); truncation band
  (b <= t): trunc_weight |f - b|.  t = 0.2937, beta = 5, trunc_weight = 5.383.
* Eikonal: |‖∇f‖ - 1| where b >= 0.1, else 0; weight 0.268.
* Gradient: 1 - cos(∇f, g), 0 where g is missing (NaN or zero); weight 0.018.

iSDF's loss is the mean over all its points of sdf + 0.268 eik + 0.018 grad (the three
means add up to it). The surfel loss per surfel point is |f| + 0.4 (1 - cos(∇f, v)) +
0.2 |‖∇f‖ - 1|, and the total is L_iSDF + L_surfel where (``surfel_loss_mean``):

* ``"joint"`` (default): both are sums over their points divided by the number of ALL
  points of the batch, i.e. one mean over every sample, each with the loss of its kind.
* ``"separate"``: L_iSDF the mean over the non-surfel points, L_surfel the mean over the
  surfel points (a literal reading of the paper's l = L_iSDF + L_surfel).

With ``surfel_loss`` off, surfel points stay in L_iSDF with b = 0 and g = v: band term
5.383 |f|, no Eikonal (0 < 0.1), 0.018 (1 - cos(∇f, v)).

Departure from the literal reading (measured on the synthetic Atlanta building, cpu
preset, 15 keyframes, 50 + 14 x 15 = 260 steps, iSDF's evaluation points, exact SDF):
with separate means the ~740 surfel points of a step (5 frames x ~9 surfels x 17) each
weigh N_iSDF / N_surfel ~ 4.6x a ray sample, and their 0.4 (1 - cos) term (22x iSDF's
0.018 per point) dominated the AdamW step: "surfel loss only" 9.5 cm vs iSDF 7.7 cm
(seed 0), 7.2 vs 6.1 cm over seeds 0-2. Diagnostics (seed 0): without the 0.4 gradient
term 5.8 cm, without the 0.2 Eikonal term 6.9 cm; with one joint mean (weights 1, 0.4,
0.2 kept) 6.8 cm, 5.6 cm over seeds 0-2. The surfels themselves were right: surfel
points lie 1.3 mm from the true faces on average, none beyond 5 cm, and 99.6% of the
surfel normals agree with the true SDF gradient.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .config import TrainingConfig
from .sampling import SURFEL


def sdf_term(
    f: torch.Tensor, b: torch.Tensor, trunc_distance: float = 0.2937, beta: float = 5.0, trunc_weight: float = 5.383
) -> torch.Tensor:
    """(M,) free-space term where b > trunc_distance, truncation-band term elsewhere."""
    free = torch.maximum(F.relu(f - b), torch.exp(-beta * f) - 1.0)
    band = (f - b).abs() * trunc_weight
    return torch.where(b > trunc_distance, free, band)


def eikonal_term(grad: torch.Tensor, b: torch.Tensor | None = None, apply_dist: float = 0.1) -> torch.Tensor:
    """(M,) |‖∇f‖ - 1|, zero where b < apply_dist (everywhere applied when b is None)."""
    e = (grad.norm(dim=-1) - 1.0).abs()
    return e if b is None else torch.where(b >= apply_dist, e, torch.zeros_like(e))


def grad_term(grad: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(M,) 1 - cos(∇f, g); zero where the target is non-finite or zero."""
    ok = torch.isfinite(target).all(dim=-1) & (target.abs().sum(dim=-1) > 0)
    t = torch.where(ok[:, None], target, torch.ones_like(target))
    cos = F.cosine_similarity(grad, t, dim=-1)
    return torch.where(ok, 1.0 - cos, torch.zeros_like(cos))


def isdf_point_loss(f, grad, b, g, cfg: TrainingConfig, trunc=None) -> dict[str, torch.Tensor]:
    """Weighted per-point terms (M,) "sdf", "eikonal", "grad" and their sum "total".
    ``trunc`` (M,) replaces ``cfg.trunc_distance`` per point when given."""
    out = {
        "sdf": sdf_term(f, b, cfg.trunc_distance if trunc is None else trunc, cfg.free_space_beta, cfg.trunc_weight),
        "eikonal": cfg.eik_weight * eikonal_term(grad, b, cfg.eik_apply_dist),
        "grad": cfg.grad_weight * grad_term(grad, g),
    }
    out["total"] = out["sdf"] + out["eikonal"] + out["grad"]
    return out


def surfel_point_loss(f, grad, v, cfg: TrainingConfig) -> dict[str, torch.Tensor]:
    """Weighted per-point surfel terms (M,) and their sum "total" (paper Sec. III-E)."""
    out = {
        "surfel_sdf": cfg.surfel_sdf_weight * f.abs(),
        "surfel_grad": cfg.surfel_grad_weight * grad_term(grad, v),
        "surfel_eikonal": cfg.surfel_eik_weight * eikonal_term(grad),
    }
    out["total"] = out["surfel_sdf"] + out["surfel_grad"] + out["surfel_eikonal"]
    return out


def _mean(x: torch.Tensor) -> torch.Tensor:
    return x.mean() if x.numel() else x.new_zeros(())


def training_loss(
    f: torch.Tensor, grad: torch.Tensor, b: torch.Tensor, g: torch.Tensor, kind: torch.Tensor, slot: torch.Tensor,
    n_slots: int, cfg: TrainingConfig, trunc: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float], np.ndarray]:
    """Total loss (scalar), term means (floats; sdf + eikonal + grad + surfel = loss) and the mean
    per-point loss of each window slot (n_slots,) (NaN for a slot without samples)."""
    is_surfel = (kind == SURFEL) if cfg.surfel_loss else torch.zeros_like(kind, dtype=torch.bool)
    ii = ~is_surfel
    n_all = max(len(f), 1)

    def reduce(x: torch.Tensor) -> torch.Tensor:  # see the module docstring: "joint" or "separate"
        return _mean(x) if cfg.surfel_loss_mean == "separate" else x.sum() / n_all

    iso = isdf_point_loss(f[ii], grad[ii], b[ii], g[ii], cfg, None if trunc is None else trunc[ii])
    loss = reduce(iso["total"])
    terms = {k: float(reduce(iso[k]).detach()) for k in ("sdf", "eikonal", "grad")}
    per_point = torch.empty_like(f)
    per_point[ii] = iso["total"].detach()
    terms["surfel"] = 0.0
    if is_surfel.any():
        sur = surfel_point_loss(f[is_surfel], grad[is_surfel], g[is_surfel], cfg)
        l_s = reduce(sur["total"])
        loss = loss + l_s
        terms["surfel"] = float(l_s.detach())
        per_point[is_surfel] = sur["total"].detach()
    terms["loss"] = float(loss.detach())
    s = slot.detach().cpu().numpy()
    sums = np.bincount(s, weights=per_point.detach().cpu().numpy().astype(np.float64), minlength=n_slots)
    counts = np.bincount(s, minlength=n_slots)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame = sums / counts
    return loss, terms, per_frame
