"""Exact geometry of the scene primitives in the canonical z-up frame. Pure numpy.

* ``Room``: a prism over a simple (possibly non-convex) 2D polygon, floor at z = 0,
  ceiling at z = ``height``. Free space is its interior.
* ``Boxes``: B oriented boxes (solid obstacles), stored as stacked arrays so every
  query is vectorised over points and boxes at once.

Sign convention: positive in free space. Each primitive's signed distance is exact on
both sides of its own surface (the room is a product set, so the distance to it is
``hypot`` of the 2D and the vertical parts). Raycasting is in raycast.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (positive for counter-clockwise vertex order)."""
    return 0.5 * float(np.sum(_cross2(poly, np.roll(poly, -1, axis=0))))


def polygon_contains(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test, (N, 2) -> (N,) bool."""
    a, b = poly, np.roll(poly, -1, axis=0)
    x, y = xy[:, :1], xy[:, 1:]
    straddle = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):  # horizontal edges never straddle
        slope = (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        xc = a[:, 0] + (y - a[:, 1]) * slope
    return (np.count_nonzero(straddle & (x < xc), axis=1) % 2) == 1


def polygon_nearest(xy: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unsigned distance (N,) from each point to the polygon's boundary and the nearest
    boundary point (N, 2)."""
    e = np.roll(poly, -1, axis=0) - poly
    wx, wy = xy[:, :1] - poly[:, 0], xy[:, 1:] - poly[:, 1]  # (N, M)
    s = np.clip((wx * e[:, 0] + wy * e[:, 1]) / np.sum(e * e, axis=1), 0.0, 1.0)
    dx, dy = wx - s * e[:, 0], wy - s * e[:, 1]
    d2 = dx * dx + dy * dy
    k = np.argmin(d2, axis=1)
    idx = np.arange(len(xy))
    return np.sqrt(d2[idx, k]), poly[k] + s[idx, k, None] * e[k]


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / n
    return np.where(n > 1e-12, u, fallback)


@dataclass(frozen=True, eq=False)
class Room:
    """Prism over ``polygon`` (M, 2), stored counter-clockwise, from z = 0 to ``height``."""

    polygon: np.ndarray
    height: float

    def __post_init__(self) -> None:
        poly = np.asarray(self.polygon, dtype=np.float64).reshape(-1, 2)
        if polygon_area(poly) < 0:
            poly = poly[::-1].copy()
        object.__setattr__(self, "polygon", poly)

    @property
    def edge_normals(self) -> np.ndarray:
        """(M, 2) unit inward normals of the edges (edge k runs from vertex k to k+1)."""
        e = np.roll(self.polygon, -1, axis=0) - self.polygon
        n = np.stack([-e[:, 1], e[:, 0]], axis=1)  # left of a CCW edge = inside
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def contains(self, p: np.ndarray) -> np.ndarray:
        return polygon_contains(p[:, :2], self.polygon) & (p[:, 2] > 0) & (p[:, 2] < self.height)

    def sdf_grad(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact signed distance (N,) to the room boundary (positive inside) and its gradient."""
        xy, z, h = p[:, :2], p[:, 2], self.height
        d2, near = polygon_nearest(xy, self.polygon)
        in2 = polygon_contains(xy, self.polygon)
        inside = in2 & (z > 0) & (z < h)
        cand = np.stack([d2, z, h - z], axis=1)
        k = np.argmin(cand, axis=1)
        g = np.zeros_like(p)
        g[:, :2] = _unit(xy - near, np.zeros(2))
        g[k == 1] = (0.0, 0.0, 1.0)
        g[k == 2] = (0.0, 0.0, -1.0)
        # Outside the prism: distance to the product set = hypot(2D part, vertical part).
        vec = np.zeros_like(p)
        vec[:, :2] = np.where(in2[:, None], 0.0, xy - near)
        vec[:, 2] = np.where(z < 0, z, np.where(z > h, z - h, 0.0))
        dout = np.linalg.norm(vec, axis=1)
        gout = -_unit(vec, np.array([0.0, 0.0, 1.0]))
        sdf = np.where(inside, cand[np.arange(len(p)), k], -dout)
        return sdf, np.where(inside[:, None], g, gout)

    @property
    def face_axes(self) -> np.ndarray:
        """(M + 2, 3) unit normals of the faces: walls 0..M-1 (inward), floor M, ceiling M+1."""
        return np.r_[np.c_[self.edge_normals, np.zeros(len(self.polygon))], [[0.0, 0.0, 1.0]] * 2]


@dataclass(frozen=True, eq=False)
class Boxes:
    """B oriented boxes: centers (B, 3), rotations (B, 3, 3) whose columns are the box
    axes in the canonical frame, half sizes (B, 3)."""

    centers: np.ndarray
    rotations: np.ndarray
    halves: np.ndarray

    def __post_init__(self) -> None:
        for f, shape in (("centers", (-1, 3)), ("rotations", (-1, 3, 3)), ("halves", (-1, 3))):
            object.__setattr__(self, f, np.asarray(getattr(self, f), dtype=np.float64).reshape(shape))

    def __len__(self) -> int:
        return len(self.centers)

    @property
    def radii(self) -> np.ndarray:
        return np.linalg.norm(self.halves, axis=1)

    def local(self, p: np.ndarray) -> np.ndarray:
        """Points (N, 3) in every box's frame, (N, B, 3), via one matrix product."""
        B = len(self)
        Rcat = self.rotations.transpose(1, 0, 2).reshape(3, 3 * B)  # column 3b+j = axis j of box b
        off = np.einsum("bi,bij->bj", self.centers, self.rotations).reshape(3 * B)
        return (p @ Rcat - off).reshape(len(p), B, 3)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Exact signed distance (N, B) from each point to each box (positive outside)."""
        q = np.abs(self.local(p)) - self.halves[None]
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        return outside + np.minimum(np.max(q, axis=-1), 0.0)

    def nearest(self, p: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smallest box signed distance (N,) per point where it is below ``upper`` (N,), and
        that box's index (-1 and ``upper`` elsewhere). Exact; boxes are pruned with the
        bounds |p - c| - r <= sdf <= |p - c| (r: the box's circumradius)."""
        best, arg = np.array(upper, dtype=np.float64, copy=True), np.full(len(p), -1)
        if len(self) == 0 or len(p) == 0:
            return best, arg
        C = self.centers
        dc2 = np.sum(C * C, axis=1)[:, None] - 2.0 * (C @ p.T) + np.sum(p * p, axis=1)[None]
        dc = np.sqrt(np.maximum(dc2, 0.0))  # (B, N)
        best = np.minimum(best, dc.min(axis=0) + 1e-9)
        cand = dc - (self.radii[:, None] + 1e-9) < best[None]
        for j in range(len(self)):
            idx = np.flatnonzero(cand[j])
            if len(idx) == 0:
                continue
            q = np.abs((p[idx] - C[j]) @ self.rotations[j]) - self.halves[j]
            d = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
            win = d < best[idx]
            best[idx[win]] = d[win]
            arg[idx[win]] = j
        best[arg < 0] = np.asarray(upper)[arg < 0]
        return best, arg

    def grad(self, p: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Gradient (N, 3) of box ``b[i]``'s signed distance at ``p[i]``."""
        R, c, e = self.rotations[b], self.centers[b], self.halves[b]
        ql = np.einsum("nij,ni->nj", R, p - c)
        q = np.abs(ql) - e
        s = np.where(ql < 0, -1.0, 1.0)
        out = np.maximum(q, 0.0) * s
        k = np.argmax(q, axis=1)
        gin = np.zeros_like(q)
        gin[np.arange(len(p)), k] = s[np.arange(len(p)), k]
        gl = np.where((q > 0).any(axis=1)[:, None], _unit(out, gin), gin)
        return np.einsum("nij,nj->ni", R, gl)

    @property
    def face_axes(self) -> np.ndarray:
        """(3B, 3) box axes; faces 3b + k are the two faces of box b normal to axis k."""
        return self.rotations.transpose(0, 2, 1).reshape(-1, 3)
