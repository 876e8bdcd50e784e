"""The measured surface: every depth pixel's 3-d point, pooled into voxels, and an answer
that uses it together with the network and the surfel map (beyond the paper; measured by
``aisdf bench scaling``, not served by ``query/sdf`` yet).

Why. The fused answer (``fusion``) takes the smaller of the network and the surfel distance,
so where the network is below an exact surfel distance it stays below. On the building
floor that is most of the error (README, "The surfel map is exact"). Taking the surfel
distance everywhere halves the error but answers too high at furniture, which the surfel
map does not hold. The depth pixels do see the furniture: a point is nearer to an obstacle
than the surfel map says only if something was measured nearer (or the nearer surface was
never measured, which no answer can know). So:

* where no measured point is nearer than the surfel distance (minus ``margin``), the answer
  moves to the surfel distance; the weight goes linearly from 0 (a measured point at the
  surfel distance minus ``margin`` or nearer) to 1 (none nearer than the surfel distance);
* everywhere outside obstacles the answer is capped at the distance to the nearest measured
  point plus ``slack`` (a measured point is on a surface, up to depth noise);
* where the network says inside (negative), the fused answer is kept: neither the surfels
  nor the points say what is inside.

A voxel's point is the mean of the pixels that fell in it, and a voxel needs ``min_hits``
of them, so one noisy pixel does not pull answers down. Pure numpy (scipy's KD-tree).
"""

from __future__ import annotations

import numpy as np

from ..geometry import backproject, transform
from ..observed import pack_keys

DEFAULT_VOXEL = 0.1
DEFAULT_MIN_HITS = 3
DEFAULT_MARGIN = 0.05
DEFAULT_SLACK = 0.01


class MeasuredSurface:
    """Depth pixels pooled into ``voxel`` cubes: per voxel the sum of its points and their
    count (memory follows the surface seen, not the building's volume)."""

    def __init__(self, voxel: float = DEFAULT_VOXEL, min_hits: int = DEFAULT_MIN_HITS, max_depth: float = 12.0):
        if not voxel > 0 or min_hits < 1 or not max_depth > 0:
            raise ValueError("voxel and max_depth must be positive and min_hits at least 1")
        self.voxel, self.min_hits, self.max_depth = float(voxel), int(min_hits), float(max_depth)
        self.keys = np.zeros(0, np.int64)  # sorted, unique
        self.sums = np.zeros((0, 3), np.float64)
        self.counts = np.zeros(0, np.int64)
        self._tree = None

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray) -> int:
        """Adds one depth image's points (metres, 0 or non-finite = none); returns how many."""
        depth = np.asarray(depth, np.float64)
        if depth.ndim != 2:
            raise ValueError(f"depth must be 2-d, got shape {depth.shape}")
        K, T = np.asarray(K, np.float64), np.asarray(T_WC, np.float64)
        if K.shape != (3, 3) or T.shape != (4, 4) or not (np.all(np.isfinite(K)) and np.all(np.isfinite(T))):
            raise ValueError("K must be a finite 3x3 and T_WC a finite 4x4 matrix")
        valid = np.isfinite(depth) & (depth > 0) & (depth <= self.max_depth)
        n = int(valid.sum())
        if not n:
            return 0
        P = transform(T, backproject(depth, K)[valid])
        k = pack_keys(np.floor(P / self.voxel).astype(np.int64))
        # Merge into the held voxels: one unique over held and new keys, sums and counts by group.
        keys, group = np.unique(np.concatenate([self.keys, k]), return_inverse=True)
        group = group.ravel()
        sums = np.concatenate([self.sums, P])
        self.sums = np.stack([np.bincount(group, sums[:, i], minlength=len(keys)) for i in range(3)], axis=1)
        self.counts = np.bincount(group, np.concatenate([self.counts, np.ones(n, np.int64)]).astype(np.float64),
                                  minlength=len(keys)).astype(np.int64)
        self.keys = keys
        self._tree = None
        return n

    def points(self) -> np.ndarray:
        """(M, 3) the mean point of each voxel with at least ``min_hits`` pixels."""
        ok = self.counts >= self.min_hits
        return self.sums[ok] / self.counts[ok, None]

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance from each point to the nearest measured point (inf when none)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if self._tree is None:
            from scipy.spatial import cKDTree

            pts = self.points()
            self._tree = cKDTree(pts) if len(pts) else False
        if self._tree is False:
            return np.full(len(points), np.inf)
        return self._tree.query(points)[0]

    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.sums.nbytes + self.counts.nbytes)


def measured_fuse(fused: np.ndarray, sdf_i: np.ndarray, d_e: np.ndarray, d_m: np.ndarray,
                  margin: float = DEFAULT_MARGIN, slack: float = DEFAULT_SLACK,
                  radius: float | None = 2.0) -> np.ndarray:
    """The answer of the module docstring, values only. ``fused``: ``fusion.fuse``'s answer;
    ``sdf_i``: the network's; ``d_e``: the (signed or unsigned) distance to the surfel map
    (inf where none); ``d_m``: ``MeasuredSurface.distance``. The surfel distance counts only
    within ``radius`` (as in ``fusion``)."""
    fused, sdf_i = np.asarray(fused, np.float64), np.asarray(sdf_i, np.float64)
    d_e, d_m = np.abs(np.asarray(d_e, np.float64)), np.asarray(d_m, np.float64)
    outside = sdf_i >= 0
    near = np.isfinite(d_e) & (d_e <= (np.inf if radius is None else radius))
    with np.errstate(invalid="ignore"):  # inf - inf where no surfel: not near, weight 0
        w = np.clip((d_m - (d_e - margin)) / margin, 0.0, 1.0)
    w = np.where(near & outside, np.nan_to_num(w, nan=0.0), 0.0)
    a = w * np.where(near, d_e, 0.0) + (1.0 - w) * fused
    return np.where(outside, np.minimum(a, d_m + slack), fused)
