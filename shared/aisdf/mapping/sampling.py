"""Training samples for one step (isdf-reference.md "Sampling"; paper Sec. III-D).

Per frame: ``n_rays`` random valid pixels (with replacement), and per ray, in camera z
(the rays have z = 1, so a sample at depth z is ``z * dir_C``):
1 sample at the measured depth D, ``n_gaussian`` at D + N(0, std) clipped to
[min_depth, D + margin], ``n_stratified`` stratified in [min_depth, D + margin] (one
uniform draw in each of as many equal bins). With surfels in use (config
``uses_surfels``) a frame with surfels also gets ``samples_per_ray`` points uniform on
each surfel rectangle; with ``surfel_mask`` its rays come only from non-surfel pixels
(those not set in the frame's surfel mask, ``StoredFrame.surfel_mask``; all valid pixels when
the frame has no mask),
and with ``surfels_replace_rays`` (off by default, see config.py) it gets one ray fewer per surfel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import geometry
from .config import TrainingConfig
from .frames import StoredFrame

FREE, SURFACE, SURFEL = 0, 1, 2  # Batch.kind values


@dataclass
class Batch:
    """Flat sample arrays, M points. kind: FREE (ray sample), SURFACE (ray sample at D), SURFEL.

    points_W (M, 3) float32; z, ray_depth (M,) float32 camera depth of the sample and the
    ray's measured depth D (NaN for surfel points); target (M, 3) float32 gradient target
    (depth normal for SURFACE, surfel normal for SURFEL, NaN otherwise); slot (M,) int64
    index of the frame in the window.
    """

    points_W: np.ndarray
    z: np.ndarray
    ray_depth: np.ndarray
    kind: np.ndarray
    target: np.ndarray
    slot: np.ndarray

    def __len__(self) -> int:
        return len(self.points_W)

    @staticmethod
    def concat(parts: list["Batch"]) -> "Batch":
        f = Batch.__dataclass_fields__
        if not parts:
            return Batch(np.zeros((0, 3), np.float32), *(np.zeros(0, np.float32),) * 2, np.zeros(0, np.int8),
                         np.zeros((0, 3), np.float32), np.zeros(0, np.int64))
        return Batch(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in f})


def sample_pixels(valid: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` flat indices of True pixels, uniform with replacement (empty if there are none)."""
    flat = valid.reshape(-1)
    if n <= 0 or flat.size == 0:
        return np.zeros(0, np.int64)
    got, count = [], 0
    for _ in range(3):  # rejection sampling: cheap when most pixels are valid
        cand = rng.integers(0, flat.size, size=2 * n)
        ok = cand[flat[cand]]
        got.append(ok)
        count += len(ok)
        if count >= n:
            return np.concatenate(got)[:n]
    idx = np.flatnonzero(flat)
    return rng.choice(idx, size=n) if len(idx) else np.zeros(0, np.int64)


def ray_depths(
    D: np.ndarray, rng: np.random.Generator, n_gaussian: int = 8, std: float = 0.1, n_stratified: int = 19,
    min_depth: float = 0.07, margin: float = 0.1,
) -> np.ndarray:
    """(R,) measured depths -> (R, 1 + n_gaussian + n_stratified) sample depths; column 0 is D."""
    D = np.asarray(D, np.float64)
    far = D + margin
    near = np.minimum(min_depth, far)
    zg = np.clip(D[:, None] + rng.normal(0.0, std, (len(D), n_gaussian)), near[:, None], far[:, None])
    step = (far - near)[:, None] / max(n_stratified, 1)
    zs = near[:, None] + step * (np.arange(n_stratified) + rng.uniform(size=(len(D), n_stratified)))
    return np.concatenate([D[:, None], zg, zs], axis=1)


def sample_frame(kf: StoredFrame, slot: int, cfg: TrainingConfig, rng: np.random.Generator) -> Batch:
    """Ray samples (and surfel points) of one keyframe."""
    frame = kf.frame
    surfels = frame.surfels if (cfg.uses_surfels and frame.surfels is not None) else None
    valid = kf.valid()
    mask = kf.pixel_mask  # unpacked once
    if mask is not None:
        valid = valid & mask
    n_rays = cfg.n_rays
    if cfg.surfel_mask and surfels is not None:
        smask = kf.surfel_mask
        if smask is not None:
            valid = valid & ~smask
        if cfg.surfels_replace_rays:
            n_rays = max(n_rays - len(surfels), 0)
    H, W = kf.shape
    pix = sample_pixels(valid, n_rays, rng)
    u, v = pix % W, pix // W
    K = frame.K
    dirs_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(pix))], axis=-1)
    D = kf.depth_at(pix).astype(np.float64)
    z = ray_depths(D, rng, cfg.n_gaussian, cfg.gaussian_std, cfg.n_stratified, cfg.min_depth, cfg.depth_margin)
    R, S = z.shape
    T_WC = np.asarray(frame.T_WC, np.float64)
    pts_W = geometry.transform(T_WC, dirs_C[:, None, :] * z[..., None])
    kind = np.full((R, S), FREE, np.int8)
    kind[:, 0] = SURFACE
    target = np.full((R, S, 3), np.nan, np.float32)
    # the sampled pixels' normals (geometry.normals_at, computed here rather than held per
    # keyframe), in half precision as they were once stored
    target[:, 0] = geometry.rotate(T_WC, geometry.normals_at(kf.raw, K, v, u, scale=kf.scale)).astype(np.float16)
    parts = [Batch(
        pts_W.reshape(-1, 3).astype(np.float32), z.reshape(-1).astype(np.float32),
        np.repeat(D, S).astype(np.float32), kind.reshape(-1), target.reshape(-1, 3),
        np.full(R * S, slot, np.int64),
    )]
    if surfels is not None and len(surfels):
        sp, si = surfels.sample_uniform(cfg.samples_per_ray, rng)
        nan = np.full(len(sp), np.nan, np.float32)
        parts.append(Batch(
            sp.astype(np.float32), nan, nan.copy(), np.full(len(sp), SURFEL, np.int8),
            surfels.normal[si].astype(np.float32), np.full(len(sp), slot, np.int64),
        ))
    if kf.region is not None:  # a submap's keyframe: its samples in the submap's box; surface
        # (reference) points a truncation distance further, so the bounds near the box's faces hold
        parts = [_within(p, kf.region, cfg.trunc_distance) for p in parts]
    return Batch.concat(parts)


def _within(b: Batch, region, margin: float) -> Batch:
    keep = np.where(b.kind == FREE, region(b.points_W, 0.0), region(b.points_W, margin))
    return Batch(**{k: getattr(b, k)[keep] for k in Batch.__dataclass_fields__})


def sample_batch(keyframes: list[StoredFrame], cfg: TrainingConfig, rng: np.random.Generator) -> Batch:
    """Samples of every frame of the window; ``slot`` = position in ``keyframes``."""
    return Batch.concat([sample_frame(kf, i, cfg, rng) for i, kf in enumerate(keyframes)])
