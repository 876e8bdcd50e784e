"""Image side of surfel extraction: block-averaged keyframe points with edge-aware normals,
and the full-resolution surfel mask. Pure numpy."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..geometry import backproject, rotate, transform
from .surfel_config import SurfelConfig, choose_stride, depth_sigma, inlier_threshold
from .surfel_types import Surfels


@dataclass
class KeyframePoints:
    """One keyframe's block-averaged points: P valid points with normals, world frame."""

    points_W: np.ndarray  # (P, 3)
    normals_W: np.ndarray  # (P, 3) unit, towards the camera
    depth: np.ndarray  # (P,) z in the camera frame
    spacing: np.ndarray  # (P,) distance to the neighbouring sample on the surface (m)
    cam_W: np.ndarray  # (3,) camera centre
    stride: int


def keyframe_points(depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray,
                    config: SurfelConfig | None = None) -> KeyframePoints:
    """Block-averaged points and normals of a depth image (H, W) in metres, in the world frame."""
    cfg = config or SurfelConfig()
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    s = choose_stride(H, W, cfg)
    h, w = H // s, W // s
    d = depth[: h * s, : w * s]
    valid = np.isfinite(d) & (d > 0)
    dz = np.where(valid, d, 0.0).reshape(h, s, w, s).sum(axis=(1, 3))
    cnt = valid.reshape(h, s, w, s).sum(axis=(1, 3))
    avg = np.where(cnt * 2 >= s * s, dz / np.maximum(cnt, 1), 0.0)
    if s > 1:  # a block across an occlusion edge averages two surfaces into a flying point: drop it
        dv = np.where(valid, d, np.nan)
        jump = np.zeros_like(d)
        with np.errstate(invalid="ignore"):
            jump[:, :-1] = np.fmax(jump[:, :-1], np.abs(dv[:, 1:] - dv[:, :-1]))
            jump[:-1] = np.fmax(jump[:-1], np.abs(dv[1:] - dv[:-1]))
        bj = np.nan_to_num(jump).reshape(h, s, w, s).max(axis=(1, 3))
        tol = np.maximum(cfg.pixel_jump * avg, 4 * np.sqrt(2) * depth_sigma(avg, cfg))
        avg[bj > tol] = 0.0
    # block centres: u = s u' + (s - 1) / 2
    Ks = np.array([[K[0, 0] / s, 0, (K[0, 2] - (s - 1) / 2) / s],
                   [0, K[1, 1] / s, (K[1, 2] - (s - 1) / 2) / s], [0, 0, 1]])
    p_C = backproject(avg, Ks)
    zs = smooth_depth(avg, cfg.normal_smooth, cfg.max_jump) if cfg.normal_smooth > 0 else avg
    n_C = edge_aware_normals(backproject(zs, Ks), zs, cfg.max_jump, cfg.planar_tol)
    ok = np.isfinite(n_C).all(axis=-1)
    n_C, p_C, z = n_C[ok], p_C[ok], avg[ok]
    cos = np.abs(np.einsum("pc,pc->p", n_C, p_C)) / np.linalg.norm(p_C, axis=1)
    spacing = s * z / (0.5 * (K[0, 0] + K[1, 1])) / np.maximum(cos, 0.25)
    cam_W = np.asarray(T_WC, dtype=np.float64)[:3, 3].copy()
    return KeyframePoints(transform(T_WC, p_C), rotate(T_WC, n_C), z, spacing, cam_W, s)


def smooth_depth(z: np.ndarray, radius: int, max_jump: float) -> np.ndarray:
    """Box mean of inverse depth over (2 radius + 1)^2 neighbours, leaving out invalid ones and
    those across a depth jump (> max_jump * z). Inverse depth is affine in the pixel
    coordinates on a plane, so the mean keeps planes exactly and only averages noise."""
    h, w = z.shape
    r = radius
    inv = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), 0.0)
    zp = np.pad(z, r)
    ip = np.pad(inv, r)
    acc = np.zeros_like(z)
    cnt = np.zeros_like(z)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            zn = zp[r + di: r + di + h, r + dj: r + dj + w]
            ok = (zn > 0) & (np.abs(zn - z) <= max_jump * z)
            acc += np.where(ok, ip[r + di: r + di + h, r + dj: r + dj + w], 0.0)
            cnt += ok
    return np.where((z > 0) & (cnt > 0), 1.0 / np.where(acc > 0, acc, 1.0) * np.maximum(cnt, 1), 0.0)


def edge_aware_normals(P: np.ndarray, z: np.ndarray, max_jump: float, planar_tol: float) -> np.ndarray:
    """Normals (h, w, 3) of points P (h, w, 3) with depth z (0 = invalid), towards the camera.

    Like geometry.normals_from_depth (cross product of the x and y tangents), but at a
    crease or occlusion edge, where the second difference of the depth along an axis
    exceeds ``planar_tol`` * z, that axis uses the one-sided difference with the smaller
    depth change, so points next to an edge get their own surface's normal rather than a
    mix of both (a wall just behind a table edge would otherwise look like a floor).
    One-sided jumps above ``max_jump`` * z are not used; NaN where no tangent is left.
    """
    h, w = z.shape
    n = np.full((h, w, 3), np.nan)
    if h < 3 or w < 3:
        return n
    zc = z[1:-1, 1:-1]
    Pc = P[1:-1, 1:-1]
    tangents = []
    for (a, b), (za, zb) in (((P[1:-1, 2:], P[1:-1, :-2]), (z[1:-1, 2:], z[1:-1, :-2])),
                             ((P[2:, 1:-1], P[:-2, 1:-1]), (z[2:, 1:-1], z[:-2, 1:-1]))):
        fwd, bwd = a - Pc, Pc - b
        jf, jb = np.abs(za - zc), np.abs(zc - zb)
        okf = (za > 0) & (jf <= max_jump * zc)
        okb = (zb > 0) & (jb <= max_jump * zc)
        planar = okf & okb & (np.abs(za - 2 * zc + zb) <= planar_tol * zc)
        use_f = okf & (~okb | (jf <= jb))
        t = np.where(planar[..., None], fwd + bwd, np.where(use_f[..., None], fwd, bwd))
        t[~(okf | okb)] = np.nan
        tangents.append(t)
    c = np.cross(tangents[0], tangents[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        c /= np.linalg.norm(c, axis=-1, keepdims=True)
        flip = np.einsum("hwc,hwc->hw", c, Pc) > 0
    c[flip] *= -1
    c[~(zc > 0)] = np.nan
    n[1:-1, 1:-1] = c
    return n


@lru_cache(maxsize=8)
def _block_rays(K_key: tuple, H: int, W: int, s: int) -> np.ndarray:
    """Ray directions (z = 1) padded to whole blocks, laid out (h*w, s*s, 3) float32."""
    K = np.array(K_key).reshape(3, 3)
    h, w = -(-H // s), -(-W // s)
    v, u = np.mgrid[0: h * s, 0: w * s].astype(np.float64)
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return np.ascontiguousarray(r.reshape(h, s, w, s, 3).transpose(0, 2, 1, 3, 4).reshape(h * w, s * s, 3), np.float32)


def _to_blocks(a: np.ndarray, s: int) -> np.ndarray:
    """(H, W) -> (h*w, s*s), zero-padded to whole blocks."""
    H, W = a.shape
    h, w = -(-H // s), -(-W // s)
    p = np.zeros((h * s, w * s), a.dtype)
    p[:H, :W] = a
    return p.reshape(h, s, w, s).transpose(0, 2, 1, 3).reshape(h * w, s * s)


def surfel_mask(depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, surfels: Surfels,
                config: SurfelConfig | None = None, stride: int | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose back-projected point lies on one of ``surfels`` (world frame).

    Coarse to fine: each block of ``stride`` x ``stride`` pixels is labelled with a surfel
    its mean point lies on (all surfels tested), then every pixel is tested against its
    block's label and the largest label around the block (so mask edges are at full
    resolution): "on" = within the inlier distance of the plane and inside the rectangle.
    """
    cfg = config or SurfelConfig()
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    if len(surfels) == 0:
        return np.zeros((H, W), dtype=bool)
    s = stride or choose_stride(H, W, cfg)
    h, w = -(-H // s), -(-W // s)
    T_CW = np.linalg.inv(T_WC)
    # Per surfel: rows (normal, axis1, axis2) in the camera frame, offsets, half extents.
    M = np.stack([rotate(T_CW, surfels.normal), rotate(T_CW, surfels.axis1), rotate(T_CW, surfels.axis2)], axis=1)
    off = np.einsum("skc,sc->sk", M, transform(T_CW, surfels.center))
    half = np.concatenate([np.zeros((len(surfels), 1)), surfels.extent / 2], axis=1)
    M, off, half = M.astype(np.float32), off.astype(np.float32), half.astype(np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    zb = _to_blocks(np.where(valid, depth, 0.0).astype(np.float32), s)  # (B, s*s)
    thr = inlier_threshold(zb, cfg).astype(np.float32)
    P = _block_rays(tuple(np.asarray(K, dtype=np.float64).ravel()), H, W, s) * zb[..., None]  # (B, s*s, 3)
    cnt = (zb > 0).sum(axis=1)
    pm = P.sum(axis=1) / np.maximum(cnt, 1)[:, None]  # block mean points
    zm = zb.sum(axis=1) / np.maximum(cnt, 1)
    loc = np.einsum("bc,skc->bsk", pm, M) - off[None]
    on = ((np.abs(loc[..., 0]) < inlier_threshold(zm, cfg)[:, None]) & (cnt[:, None] > 0)
          & (np.abs(loc[..., 1]) <= half[None, :, 1]) & (np.abs(loc[..., 2]) <= half[None, :, 2]))
    lab = np.where(on.any(axis=1), np.argmax(on, axis=1), -1).reshape(h, w)
    lp = np.pad(lab, 1, constant_values=-1)
    dil = np.max([lp[1 + di: 1 + di + h, 1 + dj: 1 + dj + w] for di in (-1, 0, 1) for dj in (-1, 0, 1)], axis=0)
    mask = np.zeros(zb.shape, dtype=bool)
    lab, dil = lab.ravel(), dil.ravel()
    for L, b in ((lab, np.flatnonzero(lab >= 0)), (dil, np.flatnonzero((dil >= 0) & (dil != lab)))):
        li = L[b]
        lq = np.matmul(P[b], M[li].transpose(0, 2, 1)) - off[li][:, None]  # (b, s*s, 3)
        mask[b] |= ((np.abs(lq[..., 0]) < thr[b]) & (np.abs(lq[..., 1]) <= half[li, None, 1])
                    & (np.abs(lq[..., 2]) <= half[li, None, 2]))
    mask &= zb > 0
    return mask.reshape(h, w, s, s).transpose(0, 2, 1, 3).reshape(h * s, w * s)[:H, :W]
