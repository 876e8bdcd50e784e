"""Training configuration. Every default is iSDF's number (isdf-reference.md) or the
AiSDF paper's (Sec. III-D/E); named presets live in ``presets.py``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..config import Model
from ..network import NetworkConfig


class TrainingConfig(Model):
    """Continual SDF training (iSDF, plus AiSDF's surfel switches)."""

    preset: str = Field("paper", description="label: the preset these values started from (training_config sets it)")
    network: NetworkConfig = Field(default_factory=NetworkConfig)
    device: str = Field("auto", description='"auto" = cuda when available else cpu; or "cpu", "cuda", "cuda:1"')
    seed: int = Field(0, description="seeds the network init and the sampling generator")
    torch_threads: int | None = Field(None, ge=1, description="torch.set_num_threads at Trainer start; None = leave")

    # Input.
    max_depth: float = Field(12.0, gt=0, description="depth above this (m) is invalid, as 0 and non-finite are")

    # Window (isdf-reference.md, "Sampling").
    window_size: int = Field(5, ge=1, description="frames per step: the newest two keyframes + loss-weighted replay")
    replay_uniform: int = Field(
        0, ge=0, description="beyond iSDF: this many of the replayed frames of a window are drawn uniformly from "
        "the stored keyframes, the rest by loss (iSDF: all by loss)")
    max_keyframes: int = Field(
        200, ge=2, description="memory bound; beyond it the lowest-loss keyframe (not the newest two) is dropped"
    )

    # Ray samples.
    n_rays: int = Field(200, ge=1, description="random valid pixels per frame")
    n_gaussian: int = Field(
        7, ge=0, description="samples at D + N(0, gaussian_std) per ray (iSDF: 8 near-surface samples, one of "
        "them exactly at D, so 1 + 7 + 19 = 27 per ray)"
    )
    gaussian_std: float = Field(0.1, gt=0, description="std (m) of the samples around the measured depth")
    n_stratified: int = Field(19, ge=0, description="stratified samples in [min_depth, D + depth_margin] per ray")
    min_depth: float = Field(0.07, ge=0, description="near end (m, camera z) of the sampled depth range")
    depth_margin: float = Field(0.1, ge=0, description="far end of the range is D + this (m)")

    # Bounds.
    bound_method: Literal["auto", "cdist", "kdtree"] = Field(
        "auto", description="nearest surface point search: torch.cdist in chunks, or scipy cKDTree; auto = kdtree "
        "on cpu, cdist on cuda"
    )
    bound_chunk: int = Field(2048, ge=1, description="query points per torch.cdist chunk")

    # iSDF loss.
    trunc_distance: float = Field(0.2937, gt=0, description="bound above this (m) = free space, else truncation band")
    free_space_beta: float = Field(5.0, description="free-space term max(relu(f - b), exp(-beta f) - 1)")
    trunc_weight: float = Field(5.383, description="band term |f - b| times this")
    eik_weight: float = Field(0.268, description="weight of |‖∇f‖ - 1|")
    eik_apply_dist: float = Field(0.1, description="Eikonal term only where bound >= this (m)")
    grad_weight: float = Field(0.018, description="weight of 1 - cos(∇f, g)")

    # AiSDF (paper Sec. III-D/E; Table II's two switches). Both off = exactly iSDF. Either on: a frame
    # that has surfels also gets samples_per_ray points uniform on each surfel ("surfel points"), and the
    # bound/gradient of its ray samples use the nearest of the surface AND surfel points (Eqs. 1-2).
    surfel_mask: bool = Field(
        False, description="rays only from non-surfel pixels of frames that have surfels (and, with "
        "surfels_replace_rays, one ray fewer per surfel)"
    )
    surfel_loss: bool = Field(
        False, description="surfel points get |f| + 0.4(1 - cos(∇f, v)) + 0.2|‖∇f‖ - 1|; off = surfel points "
        "join iSDF's loss with bound 0 and gradient target v (band term 5.383|f| and 0.018(1 - cos))"
    )
    surfels_replace_rays: bool = Field(
        False, description="with surfel_mask: a frame with S surfels gets n_rays - S rays, so one surfel takes the "
        "place of one ray and the number of samples stays the same (paper: 'without increasing the total'). Off "
        "by default (a departure): with the cpu preset's 40 rays a frame's ~9 surfels took 22% of its rays (4.5% "
        "of the paper preset's 200), thinning the free-space samples in front of the walls; off, the frame keeps "
        "its n_rays rays (all on non-surfel pixels) and the surfel points come on top (~740 of ~4100 points a "
        "step). Measured (synthetic Atlanta, cpu preset, 260 steps, seeds 0-2, joint mean): mask + loss 5.9 cm "
        "with replacement, 5.4 cm without (iSDF 6.1); the mask alone 5.7 with, 6.3 without: within seed noise"
    )
    surfel_loss_mean: Literal["joint", "separate"] = Field(
        "joint", description="how L_iSDF and L_surfel are averaged: 'joint' (default; a departure from a literal "
        "reading of the paper's l = L_iSDF + L_surfel, which does not say how each is normalised) = each point's "
        "loss (iSDF's or the surfel loss, chosen by its kind) summed over ALL points and divided by their number, "
        "so a surfel point weighs as much as any other sample; 'separate' = mean over non-surfel points + mean "
        "over surfel points, which made each surfel point weigh ~4-5x a ray sample and, with the 0.4 gradient "
        "term, made AiSDF worse than iSDF on the synthetic Atlanta building (see losses.py)")
    surfel_bounds: bool = Field(
        False, description="beyond the paper: a free ray sample's bound is also capped by its distance to the "
        "global surfel map (any surfel point is a surface point, so that distance bounds |SDF| too), when the "
        "pipeline provides that map (Trainer.bound_prior); the gradient target then points away from the "
        "nearest surfel point. iSDF bounds a sample only by the ~200 surface points of its own batch, loose in "
        "large rooms and corridors. Off = exactly iSDF's bounds"
    )
    surfel_trunc_distance: float = Field(
        1.0, gt=0, description="with surfel_bounds: a sample whose bound the surfel map set gets the "
        "truncation band's two-sided term |f - b| up to this bound (iSDF's trunc_distance elsewhere)"
    )
    surfel_sdf_weight: float = Field(1.0, description="surfel loss: weight of |f|")
    surfel_grad_weight: float = Field(0.4, description="surfel loss: weight of 1 - cos(∇f, v)")
    surfel_eik_weight: float = Field(0.2, description="surfel loss: weight of |‖∇f‖ - 1|")

    # Optimiser (AdamW; iSDF's constant rate unless lr_settle is set).
    lr: float = Field(1.3e-3, gt=0, description="AdamW learning rate")
    weight_decay: float = Field(1.2e-2, ge=0, description="AdamW weight decay")
    lr_settle: float | None = Field(
        None, gt=0, description="beyond the paper: the rate decays from lr towards this one while no new keyframe "
        "arrives (None: iSDF's constant lr)")
    lr_halflife_steps: float = Field(100.0, gt=0, description="steps since the newest keyframe over which the "
                                     "rate's excess over lr_settle halves")
    lr_settle_after: float = Field(0.0, ge=0, description="the rate settles only once the network has had this "
                                   "many steps per keyframe it holds (fewer: the full lr)")
    lr_decay_from: Literal["keyframe", "start"] = Field(
        "keyframe", description="the decay counts steps since the newest keyframe, or since the first step")

    # iSDF's offline schedule (for "equal iterations" comparisons).
    steps_first_frame: int = Field(200, ge=0, description="steps after the first keyframe")
    steps_per_keyframe: int = Field(60, ge=0, description="steps after each later keyframe")

    @property
    def samples_per_ray(self) -> int:
        """1 surface sample + gaussian + stratified (iSDF: 27); also the points per surfel."""
        return 1 + self.n_gaussian + self.n_stratified

    def steps_for_keyframe(self, index: int) -> int:
        """iSDF's schedule: steps to run after adding keyframe number ``index`` (0-based)."""
        return self.steps_first_frame if index == 0 else self.steps_per_keyframe

    @property
    def uses_surfels(self) -> bool:
        """Whether surfel points are sampled (either AiSDF switch on)."""
        return self.surfel_mask or self.surfel_loss
