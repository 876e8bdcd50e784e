"""The explicit planar map: distance to surfels (paper Sec. IV-D) and a global surfel map.

``explicit_sdf(points, surfels)`` is the explicit SDF: the Euclidean distance to the
nearest rectangle (closest point on the bounded rectangle). Sign: the paper takes the
plain distance; planners need a sign, so a point behind its nearest surfel (on the side
opposite its normal) gets the negative distance (``signed=False`` gives the paper's).
The gradient is that of the returned field: the unit direction from the closest surfel
point to the query point (the paper's) in front of the surfel, its opposite behind it
(pointing to free space), the surfel normal on the surfel. The fused rule of the query
service is min(implicit, explicit). Caveat of the sign: surfels are one-sided sheets, so
a point under a table top (behind the top's upward surfel) comes out negative.

``GlobalSurfelMap`` goes beyond the paper (whose surfels are per keyframe): surfels of one
Atlanta direction with the same normal orientation and in-plane axes (within
``angle_tol_deg``, so a slightly refined Atlanta frame still merges), planes within
``offset_tol`` and rectangles overlapping or touching (``touch_tol``) are merged into
their common bounding rectangle when the area observed (tracked per merged surfel)
covers at least ``min_cover`` of it; else they stay apart. The merged plane is the
area-weighted mean; ``realign(frame)`` snaps normals to the latest Atlanta directions.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from .atlanta import AtlantaFrame
from ..config import Model
from .surfel_types import FIELDS, Surfels

# ----------------------------------------------------------------------------- explicit SDF


def _pack(S: Surfels) -> np.ndarray:
    """(S, 14): center, normal, axis1, axis2, half extents (one gather per pair batch)."""
    return np.concatenate([S.center, S.normal, S.axis1, S.axis2, S.extent / 2], axis=1)


def _pair_sqdist(p: np.ndarray, pack: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Squared distance only (screening): points p (K,3) against surfels s (K,)."""
    G = pack[s]
    q = p - G[:, 0:3]
    h = np.einsum("kc,kc->k", q, G[:, 3:6])
    du = np.maximum(np.abs(np.einsum("kc,kc->k", q, G[:, 6:9])) - G[:, 12], 0)
    dv = np.maximum(np.abs(np.einsum("kc,kc->k", q, G[:, 9:12])) - G[:, 13], 0)
    return du * du + dv * dv + h * h


def _all_sqdist(p: np.ndarray, pack: np.ndarray) -> np.ndarray:
    """Squared distances of every point p (n,3) to every surfel of pack (S,14): (n, S). The
    projections are matrix products, (p - c)·a = p·a - c·a (pack is origin-shifted, so the
    coordinates stay small and float32 loses nothing that matters for screening)."""
    c = pack[:, 0:3]
    axes = np.concatenate([pack[:, 3:6], pack[:, 6:9], pack[:, 9:12]])  # (3S, 3): normals, axis1, axis2
    proj = p @ axes.T - np.einsum("sc,sc->s", np.tile(c, (3, 1)), axes)  # (n, 3S)
    S = len(pack)
    h, u, v = proj[:, :S], proj[:, S:2 * S], proj[:, 2 * S:]
    du = np.maximum(np.abs(u) - pack[:, 12], 0)
    dv = np.maximum(np.abs(v) - pack[:, 13], 0)
    return du * du + dv * dv + h * h


def _pair_distance(p: np.ndarray, pack: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points p (K,3) against surfels s (K,): distance (K,), closest point (K,3), height over the plane (K,)."""
    G = pack[s]
    c, n, a1, a2 = G[:, 0:3], G[:, 3:6], G[:, 6:9], G[:, 9:12]
    q = p - c
    u = np.einsum("kc,kc->k", q, a1)
    v = np.einsum("kc,kc->k", q, a2)
    h = np.einsum("kc,kc->k", q, n)
    uc = np.clip(u, -G[:, 12], G[:, 12])
    vc = np.clip(v, -G[:, 13], G[:, 13])
    d = np.sqrt((u - uc) ** 2 + (v - vc) ** 2 + h * h)
    return d, c + uc[:, None] * a1 + vc[:, None] * a2, h


class ExplicitSdf:
    """Distance queries against a fixed set of surfels (build once per map version).

    Pruning: query points are binned into cubic cells; from each cell's centre the exact
    distance to every surfel bounds which surfels can be nearest for any point in the cell
    (d(x, s) <= min_s d(x, s) + 2 * half-diagonal), and only those are tested per point.
    """

    def __init__(self, surfels: Surfels, cell: float = 0.25, max_cell_pairs: int = 2_000_000,
                 chunk_pairs: int = 1_000_000) -> None:
        self.surfels = surfels
        self._pack = _pack(surfels)
        self._origin = self._pack[:, 0:3].mean(axis=0) if len(surfels) else np.zeros(3)
        pack = self._pack.copy()
        pack[:, 0:3] -= self._origin  # float32 screening near the map, whatever the world offset
        self._pack32 = pack.astype(np.float32)
        self.cell = cell
        self.max_cell_pairs = max_cell_pairs
        self.chunk_pairs = chunk_pairs

    def __call__(self, points: np.ndarray, signed: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """points (N,3) world -> sdf (N,), gradient (N,3) unit, nearest surfel index (N,) (-1: no surfels)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        N, S = len(p), len(self.surfels)
        if S == 0 or N == 0:
            return np.full(N, np.inf), np.zeros((N, 3)), np.full(N, -1, dtype=np.int64)
        p32 = (p - self._origin).astype(np.float32)  # screening in float32; the winner is recomputed in float64
        if N * S <= self.max_cell_pairs:  # few pairs: all of them
            rows = max(1, self.chunk_pairs // S)
            idx = np.concatenate([np.argmin(_all_sqdist(p32[a: a + rows], self._pack32), axis=1)
                                  for a in range(0, N, rows)])
        else:
            idx = self._nearest_pruned(p32)
        dist, cp, h = _pair_distance(p, self._pack, idx)
        with np.errstate(invalid="ignore", divide="ignore"):
            grad = (p - cp) / dist[:, None]
        on = dist < 1e-9
        grad[on] = self.surfels.normal[idx[on]]
        if signed:
            behind = h < 0
            dist = np.where(behind, -dist, dist)
            grad[behind & ~on] *= -1
        return dist, grad, idx

    def _nearest_pruned(self, p32: np.ndarray) -> np.ndarray:
        """Index of the nearest surfel of each point, testing only the candidates of its cell."""
        pair_p, pair_s = self._candidates(p32)
        d = np.empty(len(pair_p), np.float32)
        for a in range(0, len(pair_p), self.chunk_pairs):
            b = a + self.chunk_pairs
            d[a:b] = _pair_sqdist(p32[pair_p[a:b]], self._pack32, pair_s[a:b])
        # pairs are grouped by point (ascending): per-point minimum, first one on ties
        starts = np.flatnonzero(np.r_[True, pair_p[1:] != pair_p[:-1]])
        dmin = np.minimum.reduceat(d, starts)
        pos = np.flatnonzero(d == np.repeat(dmin, np.diff(np.r_[starts, len(d)])))
        pos = pos[np.r_[True, pair_p[pos][1:] != pair_p[pos][:-1]]]
        return pair_s[pos]

    def _candidates(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point, surfel) pairs to test, grouped by point in ascending order."""
        N, S = len(p), len(self.surfels)
        cell = self.cell
        lo = p.min(axis=0)
        while True:
            key3 = np.floor((p - lo) / cell).astype(np.int64)
            dims = key3.max(axis=0) + 1
            key = (key3[:, 0] * dims[1] + key3[:, 1]) * dims[2] + key3[:, 2]
            if np.prod(dims) <= 4 * N + 1_000_000:  # dense: compaction by bincount, O(N)
                used = np.bincount(key, minlength=int(np.prod(dims))) > 0
                ids = np.flatnonzero(used)
                inv = (np.cumsum(used) - 1)[key]
            else:
                ids, inv = np.unique(key, return_inverse=True)
            if len(ids) * S <= self.max_cell_pairs or len(ids) == 1:
                break
            cell *= 1.5
        cells = np.stack(np.unravel_index(ids, tuple(dims)), axis=1)
        inv = inv.reshape(-1)
        C = len(cells)
        x = lo + (cells + 0.5) * cell
        rows = max(1, self.chunk_pairs // S)
        D = np.sqrt(np.concatenate([_all_sqdist(x[a: a + rows].astype(np.float32), self._pack32)
                                    for a in range(0, C, rows)]))
        rho = cell * np.sqrt(3) / 2
        cand = D <= D.min(axis=1, keepdims=True) + 2 * rho + 1e-3  # (C, S); 1 mm for float32
        counts = cand.sum(axis=1)
        cand_s = np.nonzero(cand)[1]  # row-major: grouped by cell
        start = np.r_[0, np.cumsum(counts)[:-1]]
        n_per = counts[inv]
        pair_p = np.repeat(np.arange(N), n_per)
        within = np.arange(len(pair_p)) - np.repeat(np.cumsum(n_per) - n_per, n_per)
        pair_s = cand_s[np.repeat(start[inv], n_per) + within]
        return pair_p, pair_s


def explicit_sdf(points: np.ndarray, surfels: Surfels,
                 signed: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Explicit SDF of points (N,3): (sdf (N,), gradient (N,3), nearest surfel index (N,)); see module doc."""
    return ExplicitSdf(surfels)(points, signed)


# ----------------------------------------------------------------------------- global map


class SurfelMapConfig(Model):
    """Merging per-keyframe surfels into one global map; lengths in metres."""

    offset_tol: float = Field(0.03, description="planes closer than this are one plane")
    angle_tol_deg: float = Field(3.0, description="normals closer than this are one orientation")
    touch_tol: float = Field(0.05, description="rectangles this close count as touching")
    min_cover: float = Field(0.95, description="observed area / merged bounding rectangle area, at least")


def _orthonormal(n: np.ndarray, a1: np.ndarray, a2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = n / np.linalg.norm(n)
    a1 = a1 - (a1 @ n) * n
    a1 /= np.linalg.norm(a1)
    b = np.cross(n, a1)
    return n, a1, b if b @ a2 >= 0 else -b


def realign(m: Surfels, frame: AtlantaFrame) -> None:
    """Snap every surfel's normal (and axes) of ``m`` to ``frame``'s Atlanta directions, about
    its centre, in place."""
    for i in range(len(m)):
        d = int(m.direction[i])
        if d >= len(frame.horizontal):
            continue
        t = frame.direction(d)
        t = t if t @ m.normal[i] >= 0 else -t
        m.normal[i], m.axis1[i], m.axis2[i] = _orthonormal(t, m.axis1[i], m.axis2[i])


class GlobalSurfelMap:
    """One planar map from the surfels of every keyframe (see module doc)."""

    def __init__(self, config: SurfelMapConfig | None = None) -> None:
        self.config = config or SurfelMapConfig()
        self._map = Surfels()
        self._covered = np.zeros(0)  # observed area inside each rectangle (m^2)
        self.n_produced = 0

    def __len__(self) -> int:
        return len(self._map)

    @property
    def n_kept(self) -> int:
        return len(self._map)

    def surfels(self) -> Surfels:
        return self._map[np.arange(len(self._map))]  # a copy

    def add(self, surfels: Surfels) -> None:
        """Merge one keyframe's surfels (world frame) into the map."""
        self.n_produced += len(surfels)
        for i in range(len(surfels)):
            row = {f: np.array(getattr(surfels, f)[i]) for f in FIELDS}
            row["covered"] = float(np.prod(row["extent"]))
            while True:
                j, merged = self._best_merge(row)
                if j < 0:
                    break
                keep = np.arange(len(self._map)) != j
                self._map, self._covered = self._map[keep], self._covered[keep]
                row = merged
            self._map = Surfels.concat([self._map, Surfels(**{f: row[f] for f in FIELDS})])
            self._covered = np.append(self._covered, row["covered"])

    def remove(self, which: np.ndarray) -> int:
        """Removes the surfels ``which`` selects (a boolean mask over the map): what newer
        keyframes saw as free space (``aisdf.mapper.clearing``). Returns how many."""
        which = np.asarray(which, bool)
        n = int(which.sum())
        if n:
            keep = np.flatnonzero(~which)
            self._map, self._covered = self._map[keep], self._covered[keep]
        return n

    def realign(self, frame: AtlantaFrame) -> None:
        """Snap every surfel's normal (and axes) to the current Atlanta directions, about its centre."""
        realign(self._map, frame)

    def aligned(self, frame: AtlantaFrame | None) -> Surfels:
        """A copy of the map realigned to ``frame`` (the map itself is left as it is)."""
        s = self.surfels()
        if frame is not None:
            realign(s, frame)
        return s

    def state_dict(self) -> dict:
        return {"surfels": {f: getattr(self._map, f).tolist() for f in FIELDS},
                "covered": self._covered.tolist(), "n_produced": self.n_produced}

    def load_state_dict(self, state: dict) -> None:
        self._map = Surfels(**{f: np.asarray(v) for f, v in state["surfels"].items()})
        self._covered = np.asarray(state["covered"], dtype=np.float64)
        self.n_produced = int(state["n_produced"])

    def _row(self, j: int) -> dict:
        r = {f: getattr(self._map, f)[j] for f in FIELDS}
        r["covered"] = float(self._covered[j])
        return r

    def _best_merge(self, s: dict) -> tuple[int, dict | None]:
        cfg = self.config
        m = self._map
        best, best_cover, best_row = -1, -1.0, None
        if not len(m):
            return best, best_row
        cos_tol = np.cos(np.radians(cfg.angle_tol_deg))
        near = ((m.direction == int(s["direction"])) & (m.normal @ s["normal"] >= cos_tol)
                # same in-plane axes up to a quarter turn (floors may be cut along any horizontal)
                & (np.maximum(np.abs(m.axis1 @ s["axis1"]), np.abs(m.axis1 @ s["axis2"])) >= cos_tol)
                & (np.abs((m.center - s["center"]) @ s["normal"]) <= cfg.offset_tol))
        cand = np.flatnonzero(near)
        if len(cand):  # overlapping or touching in s's frame (vectorised screen)
            A = np.stack([s["axis1"], s["axis2"]])
            half = (np.abs(m.axis1[cand] @ A.T) * m.extent[cand, :1] / 2
                    + np.abs(m.axis2[cand] @ A.T) * m.extent[cand, 1:] / 2)
            c = (m.center[cand] - s["center"]) @ A.T
            hs = s["extent"] / 2
            gap = np.maximum(c - half, -hs) - np.minimum(c + half, hs)
            cand = cand[np.all(gap <= cfg.touch_tol + 1e-6, axis=1)]
        for j in cand:
            merged, cover = self._merge(self._row(j), s)
            if merged is not None and cover > best_cover:
                best, best_cover, best_row = int(j), cover, merged
        return best, best_row

    def _merge(self, k: dict, s: dict) -> tuple[dict | None, float]:
        """Merged rectangle in k's frame, or None if they neither touch nor fill their union box."""
        cfg = self.config
        A = np.stack([k["axis1"], k["axis2"]])

        def box(r: dict) -> tuple[np.ndarray, np.ndarray]:
            h = np.abs(A @ r["axis1"]) * r["extent"][0] / 2 + np.abs(A @ r["axis2"]) * r["extent"][1] / 2
            c = A @ (r["center"] - k["center"])
            return c - h, c + h

        lk, hk = box(k)
        ls, hs = box(s)
        if np.any(np.maximum(lk, ls) - np.minimum(hk, hs) > cfg.touch_tol):
            return None, 0.0
        lo, hi = np.minimum(lk, ls), np.maximum(hk, hs)
        ak, as_ = float(np.prod(k["extent"])), float(np.prod(s["extent"]))
        inter = float(np.prod(np.clip(np.minimum(hk, hs) - np.maximum(lk, ls), 0, None)))
        covered = k["covered"] + s["covered"] - inter * min(k["covered"] / ak, s["covered"] / as_, 1.0)
        area = float(np.prod(hi - lo))
        cover = covered / max(area, 1e-12)
        if cover < cfg.min_cover:
            return None, cover
        w = np.array([ak, as_]) / (ak + as_)
        n, a1, a2 = _orthonormal(w[0] * k["normal"] + w[1] * s["normal"], k["axis1"], k["axis2"])
        offset = w[0] * (n @ k["center"]) + w[1] * (n @ s["center"])
        mid = k["center"] + A.T @ ((lo + hi) / 2)
        center = mid + (offset - n @ mid) * n
        return {"center": center, "normal": n, "axis1": a1, "axis2": a2, "extent": hi - lo,
                "direction": k["direction"], "keyframe": np.array(-1), "covered": min(covered, area)}, cover
