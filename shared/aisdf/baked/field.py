"""The baked field's lookup (``aisdf.baked``, its docstring says the layout and the
interpolation): per-point kernels, compiled by numba (nogil: answers run beside a bake),
and :class:`BakedField`, the arrays of one bake."""

from __future__ import annotations

import math

import numpy as np

try:  # numba compiles the per-point kernel; without it a (slower) numpy path answers.
    import numba

    _njit = numba.njit(nogil=True, cache=True, fastmath=False)
except ImportError:  # pragma: no cover - numba is a dependency
    numba = None
    _njit = None


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
    """Cubic Hermite interpolation in one cell from the 8 corners' values and gradients
    (tensor-product cubic Hermite, cross derivatives zero)."""
    f = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    for a in range(2):
        ax, bx, dax, dbx = _hermite(tx, a, h)
        for b in range(2):
            ay, by, day, dby = _hermite(ty, b, h)
            for c in range(2):
                az, bz, daz, dbz = _hermite(tz, c, h)
                v0 = V[i0 + a, j0 + b, k0 + c, 0]
                v1 = V[i0 + a, j0 + b, k0 + c, 1]
                v2 = V[i0 + a, j0 + b, k0 + c, 2]
                v3 = V[i0 + a, j0 + b, k0 + c, 3]
                f += v0 * ax * ay * az + v1 * bx * ay * az + v2 * ax * by * az + v3 * ax * ay * bz
                if want_grad:
                    gx += v0 * dax * ay * az + v1 * dbx * ay * az + v2 * dax * by * az + v3 * dax * ay * bz
                    gy += v0 * ax * day * az + v1 * bx * day * az + v2 * ax * dby * az + v3 * ax * day * bz
                    gz += v0 * ax * ay * daz + v1 * bx * ay * daz + v2 * ax * by * daz + v3 * ax * ay * dbz
    return f, gx, gy, gz


def _hermite(t, corner, h):
    """Cubic Hermite basis on [0, 1] for the value (A) and the slope (B, times h) of the
    corner at t = ``corner``, and their derivatives with respect to x (t = x / h)."""
    if corner == 0:
        A = 2.0 * t * t * t - 3.0 * t * t + 1.0
        dA = (6.0 * t * t - 6.0 * t) / h
        Bn = t * t * t - 2.0 * t * t + t
        dB = 3.0 * t * t - 4.0 * t + 1.0
    else:
        A = -2.0 * t * t * t + 3.0 * t * t
        dA = (-6.0 * t * t + 6.0 * t) / h
        Bn = t * t * t - t * t
        dB = 3.0 * t * t - 2.0 * t
    return A, h * Bn, dA, dB


if _njit is not None:
    _smooth = _njit(_smooth)
    _hermite = _njit(_hermite)
    _blend = _njit(_blend)
    _query_kernel = _njit(_query_py)
else:  # pragma: no cover
    _query_kernel = _query_py


# ----------------------------------------------------------------------------- the field


class BakedField:
    """Arrays of a bake and the vectorised lookup. Immutable once built."""

    def __init__(self, origin, block, state, C, fidx, A, F, nf, stats=None, centres=None):
        self.origin = np.asarray(origin, np.float64)
        self.block = float(block)
        self.state = state  # (nbx, nby, nbz) int8: 0 = not baked, 1 = coarse, 2 = coarse + fine
        self.C = C  # (nbx+1, nby+1, nbz+1, 4) float32 coarse [f, gx, gy, gz] (NaN where unused)
        self.fidx = fidx  # (nbx, nby, nbz) int32 index into F, -1 = no fine level
        self.A = A  # (nbx+1, nby+1, nbz+1) float32 corner blend weights of the fine level
        self.F = F  # (n_fine, nf+1, nf+1, nf+1, 4) float32
        self.nf = int(nf)
        self.stats = stats or {}
        self.centres = centres  # (nbx, nby, nbz, 4) float32 field at the block centres (NaN: none), or None

    @property
    def nbytes(self) -> int:
        arrays = (self.state, self.C, self.fidx, self.A, self.F) + ((self.centres,) if self.centres is not None else ())
        return int(sum(a.nbytes for a in arrays))

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
