"""The submap grid: space cut into boxes ("cells") of a grid whose axes are the Atlanta
frame's (first horizontal direction, its perpendicular, the vertical) once the mapper
knows it, the world's axes otherwise; fixed at the first keyframe and never moved.

Cell ``(i, j, k)`` covers, in grid coordinates ``g = R_WG^T (x - origin)``, the *core*
``[i, i+1) x [j, j+1) x [k, k+1)`` times ``(cell_m, cell_m, cell_height_m)``; its submap
is trained on the *extended* box, the core grown by ``overlap_m`` on every side. Answers
blend the submaps whose extended boxes hold a point with C¹ weights:

    w(x) = prod over the 3 axes of s(clamp(d_a / (2 overlap), 0, 1)),  s(t) = 3t² − 2t³,

where ``d_a`` is the distance from x to the extended box's nearer face along axis a. Two
neighbours' weights sum to one across their shared band (s(t) + s(1 − t) = 1), inside a
core away from its faces the weight is 1, and it falls to 0 with zero slope at the
extended box's faces, so the normalised blend sum_i w_i f_i / sum_i w_i and its gradient
are continuous (C¹ where the submaps are).

A cell id is the string ``"i_j_k"`` (``"3_-1_0"``): the last chunk of its key
``<ns>/map/submaps/<id>``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def cell_id(ijk) -> str:
    i, j, k = (int(v) for v in ijk)
    return f"{i}_{j}_{k}"


def parse_cell_id(sid: str) -> tuple[int, int, int]:
    parts = sid.split("_")
    if len(parts) != 3:
        raise ValueError(f"submap id {sid!r} is not 'i_j_k'")
    try:
        i, j, k = (int(p) for p in parts)
    except ValueError:
        raise ValueError(f"submap id {sid!r} is not 'i_j_k' with integers") from None
    return i, j, k


@dataclass
class SubmapGrid:
    """Geometry of the partition. ``R_WG`` (3,3) columns = the grid axes in the world;
    ``origin`` (3,) world point of grid coordinate 0."""

    R_WG: np.ndarray
    origin: np.ndarray
    cell_m: float = 4.0
    cell_height_m: float = 6.0
    overlap_m: float = 0.5

    def __post_init__(self) -> None:
        self.R_WG = np.asarray(self.R_WG, np.float64).reshape(3, 3)
        self.origin = np.asarray(self.origin, np.float64).reshape(3)
        smallest = min(self.cell_m, self.cell_height_m)
        if not (self.cell_m > 0 and self.cell_height_m > 0 and 0 < self.overlap_m <= smallest / 2):
            raise ValueError("cell sizes must be positive and 0 < overlap <= half a cell")
        if not np.allclose(self.R_WG.T @ self.R_WG, np.eye(3), atol=1e-6) or np.linalg.det(self.R_WG) < 0:
            raise ValueError("R_WG must be a rotation")

    # ------------------------------------------------------------------ construction
    @classmethod
    def around(cls, camera_W: np.ndarray, vertical: np.ndarray | None = None, reference: np.ndarray | None = None,
               cell_m: float = 4.0, cell_height_m: float = 6.0, overlap_m: float = 0.5) -> "SubmapGrid":
        """A grid aligned with (``reference``, vertical × reference, ``vertical``) (world axes
        when None), with the first camera centred in a cell horizontally and half a cell
        height above its bottom (the floor and ceiling of a storey land in one layer)."""
        if vertical is None:
            R = np.eye(3)
        else:
            z = np.asarray(vertical, np.float64)
            z = z / np.linalg.norm(z)
            x = np.asarray(reference if reference is not None else _perpendicular(z), np.float64)
            x = x - z * (x @ z)
            if np.linalg.norm(x) < 1e-6:
                x = _perpendicular(z)
            x = x / np.linalg.norm(x)
            R = np.stack([x, np.cross(z, x), z], axis=1)
        half = np.array([cell_m / 2, cell_m / 2, cell_height_m / 2])
        origin = np.asarray(camera_W, np.float64) - R @ half
        return cls(R, origin, cell_m, cell_height_m, overlap_m)

    @property
    def size(self) -> np.ndarray:
        return np.array([self.cell_m, self.cell_m, self.cell_height_m])

    # ------------------------------------------------------------------ coordinates
    def to_grid(self, points_W: np.ndarray) -> np.ndarray:
        return (np.asarray(points_W, np.float64).reshape(-1, 3) - self.origin) @ self.R_WG

    def cell_of(self, points_W: np.ndarray) -> np.ndarray:
        """(N, 3) int64 index of the core cell holding each point."""
        return np.floor(self.to_grid(points_W) / self.size).astype(np.int64)

    def core_box(self, ijk) -> tuple[np.ndarray, np.ndarray]:
        """Core (lo, hi) in grid coordinates."""
        lo = np.asarray(ijk, np.float64) * self.size
        return lo, lo + self.size

    def centre_W(self, ijk) -> np.ndarray:
        lo, hi = self.core_box(ijk)
        return self.origin + self.R_WG @ ((lo + hi) / 2)

    def corners_W(self, ijk, grow: float = 0.0) -> np.ndarray:
        """The 8 corners (8, 3) of the core grown by ``grow`` metres, in world coordinates."""
        lo, hi = self.core_box(ijk)
        lo, hi = lo - grow, hi + grow
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        return self.origin + c @ self.R_WG.T

    def cells_touching(self, points_W: np.ndarray, grow: float | None = None) -> dict[tuple[int, int, int], int]:
        """{cell: number of points inside its core grown by ``grow`` (default the overlap)}."""
        grow = self.overlap_m if grow is None else float(grow)
        keys = [pack_cells(cells) for _, cells in self.grown_cells(self.to_grid(points_W), grow)]
        if not keys:
            return {}
        uniq, counts = np.unique(np.concatenate(keys), return_counts=True)
        return {tuple(int(x) for x in c): int(n) for c, n in zip(unpack_cells(uniq), counts)}

    def grown_cells(self, g: np.ndarray, grow: float):
        """For grid points ``g`` (N, 3): yields (indices, cells) for each of the 27 cells
        around a point's own whose core grown by ``grow`` (< a cell) may hold it: a
        neighbour below (above) along an axis when the point is within ``grow`` of that face."""
        size = self.size
        base = np.floor(g / size).astype(np.int64)
        frac = g - base * size
        near = [(frac[:, a] < grow, frac[:, a] >= size[a] - grow) for a in range(3)]
        for off in _OFFSETS:
            sel = np.ones(len(g), bool)
            for a in range(3):
                if off[a] == -1:
                    sel &= near[a][0]
                elif off[a] == 1:
                    sel &= near[a][1]
            idx = np.flatnonzero(sel)
            if len(idx):
                yield idx, base[idx] + off

    def inside(self, ijk, points_W: np.ndarray, grow: float | None = None) -> np.ndarray:
        """Points inside the core of ``ijk`` grown by ``grow`` (default the overlap)."""
        grow = self.overlap_m if grow is None else float(grow)
        g = self.to_grid(points_W)
        lo, hi = self.core_box(ijk)
        return np.all((g >= lo - grow) & (g <= hi + grow), axis=1)

    # ------------------------------------------------------------------ blending
    def weight(self, ijk, points_W: np.ndarray, grad: bool = False):
        """Blend weight (N,) of the submap ``ijk`` at the points (0 outside its extended box)
        and, with ``grad``, its world gradient (N, 3)."""
        g = self.to_grid(points_W)
        lo, hi = self.core_box(ijk)
        o = self.overlap_m
        d_lo, d_hi = g - (lo - o), (hi + o) - g  # distance to the extended faces, per axis
        use_lo = d_lo < d_hi
        d = np.where(use_lo, d_lo, d_hi)
        t = np.clip(d / (2 * o), 0.0, 1.0)
        s = t * t * (3 - 2 * t)
        w = np.prod(s, axis=1)
        if not grad:
            return w
        ds = 6 * t * (1 - t) / (2 * o) * np.where(use_lo, 1.0, -1.0)  # ds/dg per axis
        ds = np.where((t > 0) & (t < 1), ds, 0.0)
        dg = np.empty_like(g)
        for a in range(3):
            others = [b for b in range(3) if b != a]
            dg[:, a] = ds[:, a] * s[:, others[0]] * s[:, others[1]]
        return w, dg @ self.R_WG.T

    # ------------------------------------------------------------------ wire
    def to_msg(self) -> dict:
        return {"R_WG": self.R_WG.reshape(-1).tolist(), "origin": self.origin.tolist(), "cell_m": float(self.cell_m),
                "cell_height_m": float(self.cell_height_m), "overlap_m": float(self.overlap_m)}

    @classmethod
    def from_msg(cls, m) -> "SubmapGrid":
        try:
            return cls(np.asarray(m["R_WG"], np.float64).reshape(3, 3), np.asarray(m["origin"], np.float64).reshape(3),
                       float(m["cell_m"]), float(m["cell_height_m"]), float(m["overlap_m"]))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"bad submap grid: {e}") from None

    def same_as(self, other: "SubmapGrid") -> bool:
        return (np.allclose(self.R_WG, other.R_WG, atol=1e-9) and np.allclose(self.origin, other.origin, atol=1e-9)
                and np.isclose(self.cell_m, other.cell_m) and np.isclose(self.cell_height_m, other.cell_height_m)
                and np.isclose(self.overlap_m, other.overlap_m))


_BIAS = 1 << 20  # cells within +-1M of the origin (4,000 km at 4 m)


def pack_cells(ijk: np.ndarray) -> np.ndarray:
    """(N, 3) int cell indices -> (N,) int64 keys (21 bits per axis)."""
    ijk = np.asarray(ijk, np.int64) + _BIAS
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def unpack_cells(keys: np.ndarray) -> np.ndarray:
    keys = np.asarray(keys, np.int64)
    m = (1 << 21) - 1
    return np.stack([(keys >> 42) & m, (keys >> 21) & m, keys & m], axis=-1) - _BIAS


_OFFSETS = np.array([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)], np.int64)


def _perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = a - v * (a @ v)
    return p / np.linalg.norm(p)
