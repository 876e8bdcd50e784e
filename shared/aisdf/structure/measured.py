"""The measured surface: every depth pixel's 3-d point, pooled into voxels, and an answer
that uses it together with the network and the surfel map (beyond the paper; measured by
``aisdf bench scaling``; served by ``query/sdf`` since protocol 1.4, the submap mapper
publishing each submap's points).

Why. The fused answer (``fusion``) takes the smaller of the network and the surfel distance,
so where the network is below an exact surfel distance it stays below. On the building
floor that is most of the error (docs/experiments/scaling-notes.md, "The surfel map is exact"). Taking the surfel
distance everywhere halves the error but answers too high at furniture, which the surfel
map does not hold. The depth pixels do see the furniture: a point is nearer to an obstacle
than the surfel map says only if something was measured nearer (or the nearer surface was
never measured, which no answer can know). So:

* where no measured point is nearer than the surfel distance (minus ``margin``), the answer
  moves to the surfel distance; the weight goes linearly from 0 (a measured point at the
  surfel distance minus ``margin`` or nearer) to 1 (none nearer than the surfel distance);
* everywhere outside obstacles the answer is capped at the distance to the nearest measured
  point plus ``slack`` (a measured point is on a surface, up to depth noise), where that
  point is within the fusion radius (2 m, as surfels count);
* where the network says inside (negative), the fused answer is kept: neither the surfels
  nor the points say what is inside.

A voxel's point is the mean of the pixels that fell in it, on a flat surface projected onto
the plane of its neighbourhood (``surface_points``: the tails of the depth noise otherwise
leave points centimetres in front of a wall), and a voxel needs ``min_hits`` pixels, so one
noisy pixel does not pull answers down. Pure numpy (scipy's KD-tree).
"""

from __future__ import annotations

import numpy as np

from ..geometry import backproject, kdtree, transform, valid_depth
from ..observed import NEIGHBOUR_OFFSETS, neighbourhood, pack_keys, unpack_keys

DEFAULT_VOXEL = 0.1
DEFAULT_MIN_HITS = 3
DEFAULT_MARGIN = 0.05
DEFAULT_SLACK = 0.01
FLAT = 0.1  # a neighbourhood is flat where its smallest eigenvalue is below this share of the middle one


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
        # newer keyframes in a row whose rays passed through the voxel's point (``note_evidence``)
        self.misses = np.zeros(0, np.uint8)
        self._points: MeasuredPoints | None = None
        self._voxel_pts: np.ndarray | None = None  # surface_points of every voxel, kept up to date (voxel_points)
        self._dirty: list[np.ndarray] = []  # keys changed since: their neighbourhoods are computed again
        self._msg: dict | None = None
        self.version = 0  # counts changes (points added or removed)

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
        valid = valid_depth(depth, self.max_depth)
        n = int(valid.sum())
        if not n:
            return 0
        P = transform(T, backproject(depth, K)[valid])
        k = pack_keys(np.floor(P / self.voxel).astype(np.int64))
        # This view's voxels (a unique over its own pixels), then merged into the held ones by
        # binary search: held voxels add in place, new ones are inserted in order (one copy,
        # not a sort of everything held, which grows with the building).
        new, group = np.unique(k, return_inverse=True)
        group = group.ravel()
        add_s = np.stack([np.bincount(group, P[:, i], minlength=len(new)) for i in range(3)], axis=1)
        add_c = np.bincount(group, minlength=len(new)).astype(np.int64)
        i = np.searchsorted(self.keys, new)
        held = np.zeros(len(new), bool)
        if len(self.keys):  # (an index past the end meets the last key, which is smaller)
            held = self.keys[np.minimum(i, len(self.keys) - 1)] == new
        self.sums[i[held]] += add_s[held]  # (the input was checked above: nothing below fails half way)
        self.counts[i[held]] += add_c[held]
        fresh = ~held
        self.keys = np.insert(self.keys, i[fresh], new[fresh])
        self.sums = np.insert(self.sums, i[fresh], add_s[fresh], axis=0)
        self.counts = np.insert(self.counts, i[fresh], add_c[fresh])
        self.misses = np.insert(self.misses, i[fresh], 0)
        if self._voxel_pts is not None:
            self._voxel_pts = np.insert(self._voxel_pts, i[fresh], np.nan, axis=0)
            self._dirty.append(new)
        self._points, self._msg = None, None
        self.version += 1
        return n

    def remove(self, which: np.ndarray) -> int:
        """Removes the voxels ``which`` selects (a boolean mask over ``keys``, or indices):
        what newer keyframes saw as free space (``aisdf.mapper.clearing``). Returns how many."""
        gone = np.zeros(len(self.keys), bool)
        gone[which] = True
        n = int(gone.sum())
        if n:
            keep = ~gone
            if self._voxel_pts is not None:
                self._dirty.append(self.keys[gone])
                self._voxel_pts = self._voxel_pts[keep]
            self.keys, self.sums, self.counts = self.keys[keep], self.sums[keep], self.counts[keep]
            self.misses = self.misses[keep]
            self._points, self._msg = None, None
            self.version += 1
        return n

    def note_evidence(self, passed: np.ndarray, confirmed: np.ndarray, passes: int) -> np.ndarray:
        """One newer keyframe's verdict on every voxel's mean point (``aisdf.mapper.clearing``):
        ``passed`` (its rays went through the point) counts a miss, ``confirmed`` (it measured a
        surface there) clears the count. Returns the (N,) mask of voxels with ``passes`` misses
        in a row or more; nothing is removed here."""
        passed, confirmed = np.asarray(passed, bool), np.asarray(confirmed, bool)
        if passed.shape != self.keys.shape or confirmed.shape != self.keys.shape:
            raise ValueError("one verdict per voxel")
        self.misses[confirmed] = 0
        self.misses[passed] = np.minimum(self.misses[passed].astype(np.int64) + 1, 255).astype(np.uint8)
        return self.misses >= max(1, int(passes))

    def points(self) -> np.ndarray:
        """(M, 3) the point of each voxel with at least ``min_hits`` pixels: its mean, on a flat
        surface projected onto the plane of its neighbourhood (``surface_points``)."""
        ok = self.counts >= self.min_hits
        if not ok.any():
            return np.zeros((0, 3))
        return self.voxel_points()[ok]

    def voxel_points(self) -> np.ndarray:
        """(N, 3) ``surface_points`` of every voxel, computed again only around the voxels that
        changed since the last call (a voxel's point depends on its 26 neighbours)."""
        if not len(self.keys):
            self._voxel_pts, self._dirty = np.zeros((0, 3)), []
            return self._voxel_pts
        if self._voxel_pts is None or len(self._voxel_pts) != len(self.keys):
            self._voxel_pts = surface_points(self.keys, self.sums, self.counts, self.voxel)
        elif self._dirty:
            i, hit = _lookup(self.keys, neighbourhood(np.unique(np.concatenate(self._dirty))))
            rows = i[hit]
            self._voxel_pts[rows] = surface_points(self.keys, self.sums, self.counts, self.voxel, rows=rows)
        self._dirty = []
        return self._voxel_pts

    def message(self) -> dict:
        """The protocol's ``measured`` map (1.4): {"voxel": float, "points": (M, 3) float32},
        built once per change (the one-network mapper sends it with every snapshot)."""
        if self._msg is None:
            self._msg = {"voxel": self.voxel, "points": self.points().astype(np.float32)}
        return self._msg

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance from each point to the nearest measured point (inf when none)."""
        return self.nearest(points)[0]

    def nearest(self, points: np.ndarray, within: float | None = None,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``MeasuredPoints.nearest`` over the pool's points."""
        if self._points is None:  # built once per change
            self._points = MeasuredPoints(self.points())
        return self._points.nearest(points, within, workers)

    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.sums.nbytes + self.counts.nbytes + self.misses.nbytes)

    def state_dict(self) -> dict:
        """Plain types and arrays (for checkpoints): the settings and every voxel's sums."""
        return {"voxel": self.voxel, "min_hits": self.min_hits, "max_depth": self.max_depth,
                "keys": self.keys.copy(), "sums": self.sums.copy(), "counts": self.counts.copy(),
                "misses": self.misses.copy()}

    @classmethod
    def from_state_dict(cls, d: dict) -> "MeasuredSurface":
        """``state_dict``'s pool; ValueError when its arrays do not fit together. A state
        without ``misses`` (an older checkpoint) starts every count at 0."""
        m = cls(float(d["voxel"]), int(d["min_hits"]), float(d["max_depth"]))
        keys = np.asarray(d["keys"], np.int64).reshape(-1)
        sums = np.asarray(d["sums"], np.float64).reshape(-1, 3)
        counts = np.asarray(d["counts"], np.int64).reshape(-1)
        misses = np.asarray(d.get("misses", np.zeros(len(keys))), np.int64).reshape(-1)
        if not (len(keys) == len(sums) == len(counts) == len(misses)) or np.any(np.diff(keys) <= 0) \
                or np.any(counts < 1) or np.any((misses < 0) | (misses > 255)):
            raise ValueError("measured surface state: keys must be sorted and unique, one sum, count and "
                             "miss count (0-255) each")
        m.keys, m.sums, m.counts, m.misses = keys, sums, counts, misses.astype(np.uint8)
        return m


def _lookup(keys: np.ndarray, want: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index, found) of ``want`` in the sorted ``keys``."""
    i = np.minimum(np.searchsorted(keys, want), len(keys) - 1)
    return i, keys[i] == want


def surface_points(keys: np.ndarray, sums: np.ndarray, counts: np.ndarray, voxel: float = DEFAULT_VOXEL,
                   rows: np.ndarray | None = None, flat: float = FLAT) -> np.ndarray:
    """(N, 3) each voxel's point (of the voxels ``rows`` indexes only, when given:
    (len(rows), 3)): where its 3x3x3 neighbourhood is flat, its mean projected onto the plane
    fitted to the neighbourhood's means (weighted by their pixels); elsewhere (edges, corners,
    thin objects) its own mean.

    Why. Depth noise spreads a surface's pixels over the voxels in front of it and behind it
    (Kinect v1: sigma 1.7 cm at 3 m, 4 cm at 4.6 m), and the voxels there hold the tails of
    that spread: their own means lie 3 to 8 cm off the surface, on the side of the camera as
    often as behind. A measured point caps the served answer at its distance plus 1 cm, so a
    point in front of a wall pulled every answer near it too low. On built-in Atlanta rooms
    walked with 20 keyframes of 320x240 depth, 14 to 20 % of the measured points lay more than
    3 cm off a true surface; projected, 2 to 4 % (docs/benchmarks.md, "A room the defaults
    never saw"). The plane is what a TSDF averages along the rays: the voxels holding most of
    the surface's pixels weigh most. Flat: the smallest eigenvalue of the neighbourhood's
    covariance below ``flat`` times the middle one, and the middle one above (voxel / 10)^2
    (a plane's spread, not a line's)."""
    keys = np.asarray(keys, np.int64)
    sums = np.asarray(sums, np.float64)
    counts = np.asarray(counts, np.float64)
    rows = np.arange(len(keys)) if rows is None else np.asarray(rows, np.int64)
    own_all = sums / counts[:, None]
    own = own_all[rows]
    if len(keys) < 3 or not len(rows):
        return own
    ijk = unpack_keys(keys[rows])
    offs = NEIGHBOUR_OFFSETS
    # the neighbours' indices (-1: none), then the count-weighted covariance of the 27 means
    nb = np.full((len(offs), len(rows)), -1, np.int64)
    for j, o in enumerate(offs):
        i, hit = _lookup(keys, pack_keys(ijk + o))
        nb[j, hit] = i[hit]
    idx = np.concatenate([rows[None], nb])
    w = np.where(idx >= 0, counts[idx], 0.0)  # (27, n)
    q = own_all[idx] - own[None]  # about the voxel's own mean (numerically tame)
    w_tot = w.sum(0)
    mu = np.einsum("kn,kni->ni", w, q) / w_tot[:, None]
    cov = np.einsum("kn,kni,knj->nij", w, q, q) / w_tot[:, None, None] - mu[:, :, None] * mu[:, None, :]
    ev, vec = np.linalg.eigh(cov)  # ascending
    normal = vec[:, :, 0]
    planar = (ev[:, 1] > (0.1 * voxel) ** 2) & (ev[:, 0] < flat * ev[:, 1])
    # own + mu is on the plane: move the mean along the normal by its offset from it
    return np.where(planar[:, None], own + np.einsum("ni,ni->n", mu, normal)[:, None] * normal, own)


class MeasuredPoints:
    """A fixed set of measured points (a ``MeasuredSurface``'s, or the union of what the
    submaps of a map carry) and the distance to the nearest of them, with its direction."""

    def __init__(self, points: np.ndarray):
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise ValueError("measured points must be finite")
        self.points = pts
        self._tree = None

    def __len__(self) -> int:
        return len(self.points)

    def distance(self, q: np.ndarray, within: float | None = None) -> np.ndarray:
        """(N,) distance to the nearest point (inf when there is none, or none within ``within``)."""
        return self.nearest(q, within)[0]

    def nearest(self, q: np.ndarray, within: float | None = None,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(distance (N,), unit direction from the nearest point to the query (N, 3)); inf and
        zeros when there is no point (or where the query is on a point). With ``within``, only
        points up to that distance are looked for (the search stops early: much faster far
        from every point); inf beyond. ``workers``: threads of the search (scipy's)."""
        q = np.asarray(q, np.float64).reshape(-1, 3)
        if not len(self.points):
            return np.full(len(q), np.inf), np.zeros((len(q), 3))
        if self._tree is None:
            # Leaves of 64: searches up to the 2 m radius in a cloud of surfaces visit many
            # leaves; bigger ones cost ~35 % less there (scipy's default is 16).
            self._tree = kdtree(self.points, leafsize=64)
        if within is None:
            d, i = self._tree.query(q, workers=workers)
        else:  # a hair more, so a point at exactly ``within`` is found whatever the bound's test
            d, i = self._tree.query(q, distance_upper_bound=float(within) * (1 + 1e-9) + 1e-12, workers=workers)
            d = np.where(d <= within, d, np.inf)
        found = np.isfinite(d)
        diff = np.zeros_like(q)
        diff[found] = q[found] - self.points[i[found]]
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.where((d[:, None] > 0) & found[:, None], diff / d[:, None], 0.0)
        return d, g


def measured_fuse(fused: np.ndarray, sdf_i: np.ndarray, d_e: np.ndarray, d_m: np.ndarray,
                  margin: float = DEFAULT_MARGIN, slack: float = DEFAULT_SLACK,
                  radius: float | None = 2.0) -> np.ndarray:
    """The answer of the module docstring, values only. ``fused``: ``fusion.fuse``'s answer;
    ``sdf_i``: the network's; ``d_e``: the (signed or unsigned) distance to the surfel map
    (inf where none); ``d_m``: ``MeasuredSurface.distance``. The surfel distance counts only
    within ``radius`` (as in ``fusion``), and so does a measured point: a point changes
    answers only within ``radius`` of it (what lets the query service re-bake only there)."""
    return measured_fuse_grad(fused, None, sdf_i, d_e, None, d_m, None, margin, slack, radius)[0]


def measured_fuse_grad(fused, g_fused, sdf_i, d_e, g_e, d_m, g_m, margin: float = DEFAULT_MARGIN,
                       slack: float = DEFAULT_SLACK, radius: float | None = 2.0):
    """``measured_fuse`` with its gradient: returns (sdf (N,), gradient (N, 3) or None).
    ``g_fused``: the fused answer's gradient; ``g_e``: the gradient of ``d_e`` as given (signed
    or not; it is turned to point away from the surfel, as ``fusion.fuse`` does); ``g_m``: the
    direction from the nearest measured point (``MeasuredPoints.nearest``). The gradient is
    the exact one of the rule: the blend's ``w g_e + (1 - w) g_fused + (d_e - fused) grad w``,
    the nearest point's direction where the cap holds, the fused gradient inside."""
    fused, sdf_i = np.asarray(fused, np.float64), np.asarray(sdf_i, np.float64)
    d_e_raw = np.asarray(d_e, np.float64)
    d_e, d_m = np.abs(d_e_raw), np.asarray(d_m, np.float64)
    outside = sdf_i >= 0
    near = np.isfinite(d_e) & (d_e <= (np.inf if radius is None else radius))
    with np.errstate(invalid="ignore"):  # inf - inf where no surfel: not near, weight 0
        t = (d_m - (d_e - margin)) / margin
    t = np.nan_to_num(t, nan=0.0)
    w = np.where(near & outside, np.clip(t, 0.0, 1.0), 0.0)
    de0 = np.where(near, d_e, 0.0)
    a = w * de0 + (1.0 - w) * fused
    cap = d_m + slack if radius is None else np.where(d_m <= radius, d_m + slack, np.inf)
    capped = outside & (cap < a)
    sdf = np.where(capped, cap, np.where(outside, a, fused))
    if g_fused is None:
        return sdf, None
    g_fused = np.asarray(g_fused, np.float64)
    g_u = np.zeros_like(g_fused) if g_e is None else np.where((d_e_raw < 0)[:, None], -1.0, 1.0) * np.asarray(
        g_e, np.float64)
    g_m = np.zeros_like(g_fused) if g_m is None else np.asarray(g_m, np.float64)
    ramp = (near & outside & (t > 0) & (t < 1))[:, None]
    grad_w = np.where(ramp, (g_m - g_u) / margin, 0.0)
    ga = w[:, None] * g_u + (1.0 - w[:, None]) * g_fused + np.where(ramp, (de0 - fused)[:, None], 0.0) * grad_w
    grad = np.where(capped[:, None], g_m, np.where(outside[:, None], ga, g_fused))
    return sdf, grad
