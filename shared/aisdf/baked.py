"""The baked field: a sampled copy of an SDF (the query service bakes the fused map) over
observed space, answered by interpolation in constant time per point.

Layout (sparse blocks, two levels)
----------------------------------
Space is cut into cubic blocks of edge ``block`` (aligned with the observed-space grid).
A block is *baked* when it holds observed space. Every baked block has the **coarse**
level: value and gradient at its 8 corners (spacing ``block``; corners are shared between
neighbouring blocks). Blocks near a surface also have the **fine** level: value and
gradient on an ``(nf+1)^3`` lattice (spacing ``block / nf``). The bake runs coarse to
fine: the coarse corners are evaluated first and only blocks whose corners say a surface
may be near (``min |f| < block*sqrt(3)/2 + band``, the 1-Lipschitz bound plus a margin:
the *core*) get fine samples, together with their 26 neighbours (so the level blend
below is complete on every core block). Empty space costs 1 evaluation per block.

Interpolation (C^1, exact on linear fields)
-------------------------------------------
In a cell with corners x_i, values f_i and gradients g_i, with smoothstep weights
s(t) = 3t^2 - 2t^3 per axis (w_i = product over axes of s or 1 - s)::

    f(x) = sum_i w_i(x) * (f_i + g_i . (x - x_i))

Each term is the first-order Taylor expansion at a corner, so the interpolant reproduces
any linear field exactly (a plane's SDF) and is second-order accurate elsewhere, as the
gradient-augmented trilinear interpolation of ∇-SDF; smoothstep weights (instead of the
linear ones) have zero slope at cell faces, which makes the interpolant's gradient
continuous across cells and blocks: it interpolates the stored value and gradient at
every sample. The gradient returned is the interpolant's exact gradient.

The two levels are blended with a weight alpha that is 1 on core blocks and 0 on every
face shared with a coarse-only block (alpha is 1 at a block corner none of whose 8
blocks is a baked coarse-only one, else 0, blended with the same smoothstep weights), so the whole
field is C^1 across level borders too: ``f = alpha f_fine + (1 - alpha) f_coarse``.

Points outside every baked block are reported as not covered; the caller answers them
another way (the query service: the network).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

try:  # numba compiles the per-point kernel; without it a (slower) numpy path answers.
    import numba

    _njit = numba.njit(nogil=True, cache=True, fastmath=False)
except ImportError:  # pragma: no cover - numba is a dependency
    numba = None
    _njit = None


@dataclass
class BakeConfig:
    block: float = 0.2  # block edge (m), also the coarse spacing
    fine: int = 4  # fine cells per block edge: spacing block / fine
    band: float = 0.05  # extra margin (m) on the surface-proximity test of the coarse corners
    chunk: int = 65_536  # points per evaluation call


# ----------------------------------------------------------------------------- kernels


def _smooth(t):
    return t * t * (3.0 - 2.0 * t)


def _query_py(P, origin, block, state, C, fidx, A, F, nf, want_grad, out_f, out_g, out_in):
    """Reference implementation (numba compiles the same code)."""
    nbx, nby, nbz = state.shape
    hf = block / nf
    for n in range(P.shape[0]):
        x = (P[n, 0] - origin[0]) / block
        y = (P[n, 1] - origin[1]) / block
        z = (P[n, 2] - origin[2]) / block
        bx = int(math.floor(x))
        by = int(math.floor(y))
        bz = int(math.floor(z))
        if bx < 0 or by < 0 or bz < 0 or bx >= nbx or by >= nby or bz >= nbz or state[bx, by, bz] == 0:
            out_in[n] = False
            continue
        out_in[n] = True
        tx = x - bx
        ty = y - by
        tz = z - bz
        fi = fidx[bx, by, bz]
        # alpha and its gradient
        alpha = 0.0
        ax = 0.0
        ay = 0.0
        az = 0.0
        if fi >= 0:
            sx = _smooth(tx)
            sy = _smooth(ty)
            sz = _smooth(tz)
            dsx = 6.0 * tx * (1.0 - tx) / block
            dsy = 6.0 * ty * (1.0 - ty) / block
            dsz = 6.0 * tz * (1.0 - tz) / block
            for a in range(2):
                wx = sx if a else 1.0 - sx
                dwx = dsx if a else -dsx
                for b in range(2):
                    wy = sy if b else 1.0 - sy
                    dwy = dsy if b else -dsy
                    for c in range(2):
                        wz = sz if c else 1.0 - sz
                        dwz = dsz if c else -dsz
                        av = A[bx + a, by + b, bz + c]
                        alpha += wx * wy * wz * av
                        ax += dwx * wy * wz * av
                        ay += wx * dwy * wz * av
                        az += wx * wy * dwz * av
        fc = 0.0
        gcx = 0.0
        gcy = 0.0
        gcz = 0.0
        if alpha < 1.0:
            fc, gcx, gcy, gcz = _blend(C, bx, by, bz, tx, ty, tz, block, want_grad)
        ff = 0.0
        gfx = 0.0
        gfy = 0.0
        gfz = 0.0
        if alpha > 0.0:
            ux = tx * nf
            uy = ty * nf
            uz = tz * nf
            cx = min(int(ux), nf - 1)
            cy = min(int(uy), nf - 1)
            cz = min(int(uz), nf - 1)
            ff, gfx, gfy, gfz = _blend(F[fi], cx, cy, cz, ux - cx, uy - cy, uz - cz, hf, want_grad)
        out_f[n] = alpha * ff + (1.0 - alpha) * fc
        if want_grad:
            d = ff - fc
            out_g[n, 0] = alpha * gfx + (1.0 - alpha) * gcx + ax * d
            out_g[n, 1] = alpha * gfy + (1.0 - alpha) * gcy + ay * d
            out_g[n, 2] = alpha * gfz + (1.0 - alpha) * gcz + az * d


def _blend(V, i0, j0, k0, tx, ty, tz, h, want_grad):
    """Smoothstep-weighted blend of the 8 corners' first-order expansions in one cell."""
    sx = _smooth(tx)
    sy = _smooth(ty)
    sz = _smooth(tz)
    dsx = 6.0 * tx * (1.0 - tx) / h
    dsy = 6.0 * ty * (1.0 - ty) / h
    dsz = 6.0 * tz * (1.0 - tz) / h
    f = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    for a in range(2):
        wx = sx if a else 1.0 - sx
        dwx = dsx if a else -dsx
        ox = (tx - a) * h
        for b in range(2):
            wy = sy if b else 1.0 - sy
            dwy = dsy if b else -dsy
            oy = (ty - b) * h
            for c in range(2):
                wz = sz if c else 1.0 - sz
                dwz = dsz if c else -dsz
                oz = (tz - c) * h
                v0 = V[i0 + a, j0 + b, k0 + c, 0]
                v1 = V[i0 + a, j0 + b, k0 + c, 1]
                v2 = V[i0 + a, j0 + b, k0 + c, 2]
                v3 = V[i0 + a, j0 + b, k0 + c, 3]
                p = v0 + v1 * ox + v2 * oy + v3 * oz
                w = wx * wy * wz
                f += w * p
                if want_grad:
                    gx += dwx * wy * wz * p + w * v1
                    gy += wx * dwy * wz * p + w * v2
                    gz += wx * wy * dwz * p + w * v3
    return f, gx, gy, gz


if _njit is not None:
    _smooth = _njit(_smooth)
    _blend = _njit(_blend)
    _query_kernel = _njit(_query_py)
else:  # pragma: no cover
    _query_kernel = _query_py


# ----------------------------------------------------------------------------- the field


class BakedField:
    """Arrays of a bake and the vectorised lookup. Immutable once built."""

    def __init__(self, origin, block, state, C, fidx, A, F, nf, stats=None):
        self.origin = np.asarray(origin, np.float64)
        self.block = float(block)
        self.state = state  # (nbx, nby, nbz) int8: 0 = not baked, 1 = coarse, 2 = coarse + fine
        self.C = C  # (nbx+1, nby+1, nbz+1, 4) float32 coarse [f, gx, gy, gz] (NaN where unused)
        self.fidx = fidx  # (nbx, nby, nbz) int32 index into F, -1 = no fine level
        self.A = A  # (nbx+1, nby+1, nbz+1) float32 corner blend weights of the fine level
        self.F = F  # (n_fine, nf+1, nf+1, nf+1, 4) float32
        self.nf = int(nf)
        self.stats = stats or {}

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.state, self.C, self.fidx, self.A, self.F)))

    def query(self, points: np.ndarray, gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """(sdf (N,) float32, gradient (N, 3) float32 or None, covered (N,) bool); values of
        points not covered are undefined (0)."""
        P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(P)
        f = np.zeros(n, np.float32)
        g = np.zeros((n, 3), np.float32) if gradient else np.zeros((0, 3), np.float32)
        covered = np.zeros(n, np.bool_)
        _query_kernel(P, self.origin, self.block, self.state, self.C, self.fidx, self.A, self.F, self.nf,
                      bool(gradient), f, g, covered)
        return f, (g if gradient else None), covered


def _dilate26(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, structure=np.ones((3, 3, 3), bool))


def bake(fn, observed, cfg: BakeConfig | None = None) -> BakedField:
    """Bake ``fn`` (points (M, 3) float32 -> (sdf (M,), grad (M, 3))) over the observed
    space ``observed`` (an :class:`aisdf.observed.ObservedGrid`), coarse to fine."""
    cfg = cfg or BakeConfig()
    t0 = time.perf_counter()
    B, nf = float(cfg.block), int(cfg.fine)
    origin = observed.origin.copy()
    extent = observed.voxel * np.array(observed.occ.shape)
    nb = np.maximum(np.ceil(extent / B - 1e-9).astype(np.int64), 1)
    # Blocks holding an observed voxel (voxel centres, so a voxel belongs to one block).
    vox = np.argwhere(observed.occ)
    centres = (vox + 0.5) * observed.voxel
    bidx = np.minimum(np.floor(centres / B).astype(np.int64), nb - 1)
    state = np.zeros(tuple(nb), np.int8)
    state[bidx[:, 0], bidx[:, 1], bidx[:, 2]] = 1
    blocks = np.argwhere(state > 0)
    evals = 0

    def evaluate(pts: np.ndarray) -> np.ndarray:
        nonlocal evals
        out = np.empty((len(pts), 4), np.float32)
        for i in range(0, len(pts), cfg.chunk):
            f, g = fn(pts[i:i + cfg.chunk].astype(np.float32))
            out[i:i + cfg.chunk, 0] = f
            out[i:i + cfg.chunk, 1:] = g
        evals += len(pts)
        return out

    # Coarse level: the corners of every baked block.
    corner_mask = np.zeros(tuple(nb + 1), bool)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                corner_mask[blocks[:, 0] + a, blocks[:, 1] + b, blocks[:, 2] + c] = True
    corners = np.argwhere(corner_mask)
    C = np.full(tuple(nb + 1) + (4,), np.nan, np.float32)
    C[corners[:, 0], corners[:, 1], corners[:, 2]] = evaluate(origin + corners * B)
    t_coarse = time.perf_counter() - t0
    # Core blocks: a surface may pass within band of them.
    absf = np.abs(C[..., 0])
    minc = np.full(tuple(nb), np.inf, np.float32)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                minc = np.fmin(minc, absf[a:a + nb[0], b:b + nb[1], c:c + nb[2]])
    core = (state > 0) & (minc < B * math.sqrt(3) / 2 + cfg.band)
    fine = _dilate26(core) & (state > 0)
    state[fine] = 2
    fblocks = np.argwhere(fine)
    fidx = np.full(tuple(nb), -1, np.int32)
    fidx[fblocks[:, 0], fblocks[:, 1], fblocks[:, 2]] = np.arange(len(fblocks), dtype=np.int32)
    # Blend weights: 1 at a corner none of whose 8 blocks is a baked coarse-only block
    # (blocks outside the bake never answer, so they do not pull the blend down).
    padded = np.ones(tuple(nb + 2), bool)
    padded[1:-1, 1:-1, 1:-1] = fine | (state == 0)
    A = np.ones(tuple(nb + 1), bool)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                A &= padded[a:a + nb[0] + 1, b:b + nb[1] + 1, c:c + nb[2] + 1]
    A = A.astype(np.float32)
    # Fine level: unique lattice points (spacing B/nf) of the fine blocks, evaluated once.
    F = np.zeros((len(fblocks), nf + 1, nf + 1, nf + 1, 4), np.float32)
    if len(fblocks):
        local = np.stack(np.meshgrid(*(np.arange(nf + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
        lat = (fblocks[:, None, :] * nf + local[None]).reshape(-1, 3)  # global fine lattice index
        dims = nb * nf + 1
        key = (lat[:, 0] * dims[1] + lat[:, 1]) * dims[2] + lat[:, 2]
        ukey, inv = np.unique(key, return_inverse=True)
        uz = ukey % dims[2]
        uy = (ukey // dims[2]) % dims[1]
        ux = ukey // (dims[1] * dims[2])
        vals = evaluate(origin + np.stack([ux, uy, uz], -1) * (B / nf))
        F[...] = vals[inv.reshape(-1)].reshape(F.shape)
    stats = {"blocks": int(len(blocks)), "fine_blocks": int(len(fblocks)), "core_blocks": int(core.sum()),
             "evaluations": int(evals), "coarse_s": round(t_coarse, 3),
             "bake_s": round(time.perf_counter() - t0, 3)}
    field = BakedField(origin, B, state, C, fidx, A, F, nf, stats)
    field.stats["bytes"] = field.nbytes
    return field
