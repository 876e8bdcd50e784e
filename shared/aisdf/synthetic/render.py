"""Depth rendering by exact raycasting, and a Kinect-v1-like noise model. Pure numpy.

Noise model (``KinectNoise.apply``), in this order, on the exact z-depth ``z``:

1. Axial noise: Gaussian, with the total per-pixel standard deviation of Nguyen et al.
   (3DIMPVT 2012), sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m. Their measurement already
   contains the disparity quantisation, so the Gaussian part has
   sigma_g = sqrt(max(sigma(z)^2 - dz^2 / 12, 0)) and the total stays at sigma(z).
2. Disparity quantisation: disparity = f b / z in pixels, rounded to 1/8 pixel (Kinect
   v1: f = 580 px for the 640x480 IR camera, baseline b = 7.5 cm). Depth resolution
   dz = z^2 / (8 f b), 1.1 cm at 2 m, 4.6 cm at 4 m. ``focal_px=None`` takes f from K.
3. Holes (depth 0): incidence angle above ``grazing_deg``; pixels within ``edge_px`` of a
   depth discontinuity (neighbour differing by more than ``edge_jump`` x z), each dropped
   with probability ``edge_prob``; ``blobs_per_frame`` (Poisson mean) elliptic blobs of
   radius ``blob_radius`` x image width; i.i.d. ``pixel_dropout``.
4. Range: depth outside [min_range, max_range] after noise becomes 0.

Randomness is ``np.random.default_rng([seed, *key])``: deterministic per seed and frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import ray_dirs_C
from .scene import Scene


_RAY_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def camera_rays(K: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (3, H*W) in the camera frame (row-major pixels) and the z-depth
    per unit of ray length (H*W,). Cached per (K, H, W)."""
    key = (np.asarray(K, dtype=np.float64).tobytes(), int(H), int(W))
    if key not in _RAY_CACHE:
        d = ray_dirs_C(K, H, W).reshape(-1, 3)
        n = np.linalg.norm(d, axis=1)
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = (np.ascontiguousarray((d / n[:, None]).T), 1.0 / n)
    return _RAY_CACHE[key]


_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def _box_pixels(scene: Scene, T_canon_C: np.ndarray, K: np.ndarray, H: int, W: int) -> list[np.ndarray]:
    """Per box, the pixel indices whose rays can hit it: the bounding rectangle of its
    projected corners (all pixels if it straddles the camera plane, none if behind)."""
    bx = scene.boxes
    corners = bx.centers[:, None] + np.einsum("bij,bkj->bki", bx.rotations, _CORNERS[None] * bx.halves[:, None])
    pc = (corners - T_canon_C[:3, 3]) @ T_canon_C[:3, :3]  # (B, 8, 3) camera frame
    every = np.arange(H * W)
    out = []
    for q in pc:
        z = q[:, 2]
        if (z <= 0).all():
            out.append(every[:0])
            continue
        if (z <= 1e-6).any():
            out.append(every)
            continue
        u, v = K[0, 0] * q[:, 0] / z + K[0, 2], K[1, 1] * q[:, 1] / z + K[1, 2]
        u0, u1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())), W - 1)
        v0, v1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())), H - 1)
        if u0 > u1 or v0 > v1:
            out.append(every[:0])
            continue
        out.append((np.arange(v0, v1 + 1)[:, None] * W + np.arange(u0, u1 + 1)[None]).ravel())
    return out


def render_depth_and_cos(scene: Scene, T_WC: np.ndarray, K: np.ndarray, H: int, W: int):
    """Exact z-depth (H, W) float64 (0 where no surface) and |cos| of the incidence angle.

    Pinhole fast path of ``scene.raycast``: rays in the canonical frame from one origin,
    boxes tested only on the pixels inside their projected bounding rectangle.
    """
    dirs_C, z_per_t = camera_rays(K, H, W)
    T = scene.T_canon_W @ np.asarray(T_WC, dtype=np.float64)
    d = T[:3, :3] @ dirs_C
    t, face = scene.raycast_canon(T[:3, 3].copy(), d, _box_pixels(scene, T, K, H, W))
    hit = face >= 0
    depth = np.where(hit, t * z_per_t, 0.0)
    ax = scene.face_axes.T[:, np.maximum(face, 0)]
    cos = np.where(hit, np.abs(ax[0] * d[0] + ax[1] * d[1] + ax[2] * d[2]), 0.0)
    return depth.reshape(H, W), cos.reshape(H, W)


def render_depth(
    scene: Scene, T_WC: np.ndarray, K: np.ndarray, H: int, W: int,
    noise: "KinectNoise | None" = None, key: tuple[int, ...] = (0,),
) -> np.ndarray:
    """Depth image (H, W) float32 in metres, 0 = no measurement.

    ``noise=None``: the exact z-depth (not ray length) of the first surface along every
    pixel's ray, no range limits. Otherwise ``noise.apply`` with the random stream ``key``.
    """
    depth, cos = render_depth_and_cos(scene, T_WC, K, H, W)
    if noise is not None:
        depth = noise.apply(depth, K, cos, key)
    return depth.astype(np.float32)


def nguyen_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect v1 axial noise standard deviation (m) at depth z (m), Nguyen et al. 2012."""
    return 0.0012 + 0.0019 * (np.asarray(z) - 0.4) ** 2


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for _ in range(r):
        m = out.copy()
        m[1:] |= out[:-1]
        m[:-1] |= out[1:]
        m[:, 1:] |= out[:, :-1]
        m[:, :-1] |= out[:, 1:]
        out = m
    return out


@dataclass(frozen=True)
class KinectNoise:
    """Kinect-v1-like depth noise and holes (see the module docstring for the model)."""

    seed: int = 0
    min_range: float = 0.3  # m; nearer depths become 0
    max_range: float = 5.0  # m; farther depths become 0
    axial: bool = True  # Nguyen et al. axial noise
    focal_px: float | None = 580.0  # focal for disparity quantisation; None: K[0, 0]
    baseline_m: float = 0.075  # projector-camera baseline
    subpixel: float = 1.0 / 8.0  # disparity quantisation step (pixels); 0: off
    grazing_deg: float = 78.0  # drop pixels seen at incidence angles above this
    edge_jump: float = 0.05  # relative depth jump to a 4-neighbour that marks an edge
    edge_px: int = 1  # half width of the dropped band around depth edges
    edge_prob: float = 0.7  # drop probability inside that band
    blobs_per_frame: float = 3.0  # Poisson mean number of hole blobs per frame
    blob_radius: tuple[float, float] = (0.01, 0.04)  # blob radius range, fraction of width
    pixel_dropout: float = 0.002  # i.i.d. dropout probability per pixel

    def depth_resolution(self, z: np.ndarray, K: np.ndarray | None = None) -> np.ndarray:
        """Depth quantisation step dz(z) = z^2 * subpixel / (f b)."""
        f = self.focal_px if self.focal_px is not None else float(K[0, 0])
        return np.asarray(z) ** 2 * self.subpixel / (f * self.baseline_m)

    def apply(self, depth: np.ndarray, K: np.ndarray, cos_incidence: np.ndarray | None = None,
              key: tuple[int, ...] | int = (0,)) -> np.ndarray:
        """Noisy depth (H, W) float32 from exact depth (H, W) (0 = none) and |cos| of the
        incidence angle (H, W) (None: no grazing dropout)."""
        key = (key,) if np.isscalar(key) else tuple(key)
        rng = np.random.default_rng([self.seed, *key])
        z = np.asarray(depth, dtype=np.float64)
        valid = z > 0
        H, W = z.shape
        out = z.copy()
        if self.axial:
            dz = self.depth_resolution(z, K) if self.subpixel > 0 else 0.0
            sg = np.sqrt(np.maximum(nguyen_sigma(z) ** 2 - dz**2 / 12.0, 0.0))
            out = out + sg * rng.standard_normal(z.shape)
        if self.subpixel > 0:
            fb = (self.focal_px if self.focal_px is not None else float(K[0, 0])) * self.baseline_m
            with np.errstate(divide="ignore"):
                disp = np.round(fb / np.maximum(out, 1e-6) / self.subpixel) * self.subpixel
                out = np.where(disp > 0, fb / disp, 0.0)
        drop = ~valid
        if cos_incidence is not None:
            drop |= cos_incidence < np.cos(np.radians(self.grazing_deg))
        zp = np.pad(z, 1, mode="edge")
        jump = np.zeros_like(valid)
        for sl in ((slice(0, -2), slice(1, -1)), (slice(2, None), slice(1, -1)),
                   (slice(1, -1), slice(0, -2)), (slice(1, -1), slice(2, None))):
            jump |= np.abs(zp[sl] - z) > self.edge_jump * np.maximum(z, zp[sl])
        if self.edge_px > 0:
            band = _dilate(jump, self.edge_px - 1) if self.edge_px > 1 else jump
            drop |= band & (rng.random(z.shape) < self.edge_prob)
        v, u = np.mgrid[0:H, 0:W]
        for _ in range(rng.poisson(self.blobs_per_frame)):
            cu, cv = rng.uniform(0, W), rng.uniform(0, H)
            r = rng.uniform(*self.blob_radius) * W
            a, ang = rng.uniform(0.5, 1.0), rng.uniform(0, np.pi)
            du, dv = u - cu, v - cv
            x, y = du * np.cos(ang) + dv * np.sin(ang), -du * np.sin(ang) + dv * np.cos(ang)
            drop |= (x / r) ** 2 + (y / (a * r)) ** 2 <= 1.0
        drop |= rng.random(z.shape) < self.pixel_dropout
        out[drop | (out < self.min_range) | (out > self.max_range)] = 0.0
        return out.astype(np.float32)
