"""Observed space: which voxels any keyframe has seen, for planners that treat unknown
space as occupied (as Voxblox users do) and for the query service's baked field, which
covers exactly this space.

A voxel is observed when a depth ray of a keyframe passes through it on its way to the
measured surface, or lies within ``margin`` behind that surface (the surface itself is
seen). Pixels without a measurement mark nothing: no return is no knowledge.

The mapper keeps an :class:`ObservedSpace` (a sorted set of voxel keys; memory follows
what was seen, not the building's box) and publishes it with each weight snapshot as an
:class:`ObservedGrid` message (protocol 1.1, the ``observed`` field)::

    {"origin": [x, y, z],          # world corner of voxel (0, 0, 0), metres
     "voxel": float,               # edge length, metres
     "shape": [nx, ny, nz],
     "bits": array "|u1"}          # numpy.packbits of the C-order nx*ny*nz booleans (big-endian bits)

Pure: arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .codec import ProtocolError, _bad, decode_array, encode_array
from .geometry import kdtree, valid_depth

_OFF = 1 << 20  # voxel indices in [-2^20, 2^20) pack into 21 bits each
_MASK = (1 << 21) - 1


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    ijk = np.asarray(ijk, dtype=np.int64) + _OFF
    return (ijk[..., 0] << 42) | (ijk[..., 1] << 21) | ijk[..., 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([(keys >> 42) & _MASK, (keys >> 21) & _MASK, keys & _MASK], axis=-1) - _OFF


# the 26 offsets to a voxel's neighbours
NEIGHBOUR_OFFSETS = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3)
NEIGHBOUR_OFFSETS = NEIGHBOUR_OFFSETS[np.any(NEIGHBOUR_OFFSETS != 0, axis=1)]


def neighbourhood(keys: np.ndarray) -> np.ndarray:
    """The voxel keys and their 26 neighbours (sorted, unique)."""
    offs = np.concatenate([np.zeros((1, 3), np.int64), NEIGHBOUR_OFFSETS])
    return np.unique(pack_keys((unpack_keys(keys)[:, None, :] + offs[None]).reshape(-1, 3)))


class ObservedSpace:
    """The set of observed voxels, grown one depth image at a time. Each voxel also counts
    the images that marked it, so an image can be taken back out (``remove``: a keyframe
    re-posed by a pose correction, protocol 1.11); ``counts`` None (a checkpoint from before
    the counts) cannot."""

    def __init__(self, voxel: float = 0.1, margin: float = 0.15, max_rays: int = 6000):
        if voxel <= 0 or margin < 0:
            raise ValueError("voxel must be positive and margin non-negative")
        self.voxel = float(voxel)
        self.margin = float(margin)
        self.max_rays = int(max_rays)
        self.keys = np.zeros(0, np.int64)  # sorted, unique
        self.counts: np.ndarray | None = np.zeros(0, np.uint32)  # images marking each voxel (None: unknown)
        self._msg: dict | None = None  # the grid message of the current keys (built once per change)

    def __len__(self) -> int:
        return len(self.keys)

    def marks(self, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, max_depth: float = 12.0) -> np.ndarray:
        """The sorted voxel keys one depth image (metres, 0 = none) marks: its rays, to the
        measured surface and ``margin`` past it."""
        depth = np.asarray(depth, dtype=np.float64)
        H, W = depth.shape
        # Rays a little closer than a voxel apart at 4 m, and no more than max_rays of them.
        stride = max(1, int(self.voxel * min(K[0, 0], K[1, 1]) / 4.0))
        while (H // stride) * (W // stride) > self.max_rays:
            stride += 1
        v, u = np.mgrid[stride // 2:H:stride, stride // 2:W:stride]
        d = depth[v, u]
        ok = valid_depth(d, max_depth)
        u, v, d = u[ok], v[ok], d[ok]
        if not len(d):
            return np.zeros(0, np.int64)
        dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(d)], axis=-1)
        norm = np.linalg.norm(dirs, axis=1)
        length = d * norm + self.margin  # along the ray, to the surface and past it
        dirs_W = (dirs / norm[:, None]) @ T_WC[:3, :3].T
        step = 0.5 * self.voxel
        n = np.ceil(length / step).astype(np.int64) + 1
        ray = np.repeat(np.arange(len(d)), n)
        first = np.cumsum(n) - n
        s = (np.arange(len(ray)) - np.repeat(first, n)) * step
        s = np.minimum(s, np.repeat(length, n))
        pts = T_WC[:3, 3] + dirs_W[ray] * s[:, None]
        return np.unique(pack_keys(np.floor(pts / self.voxel).astype(np.int64)))

    def add(self, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, max_depth: float = 12.0) -> int:
        """Mark what one depth image (metres, 0 = none) saw; returns the number of new voxels."""
        new = self.marks(depth, K, T_WC, max_depth)
        if not len(new):
            return 0
        # Only the voxels not yet held are inserted, in order: binary searches into the held keys
        # and one copy, not a sort of everything held (which grew with the building).
        if len(self.keys):
            i = np.searchsorted(self.keys, new)
            held = self.keys[np.minimum(i, len(self.keys) - 1)] == new
            if self.counts is not None:
                self.counts[i[held]] += 1
            new, i = new[~held], i[~held]
            if len(new):
                self.keys = np.insert(self.keys, i, new)
                if self.counts is not None:
                    self.counts = np.insert(self.counts, i, np.ones(len(new), np.uint32))
        else:
            self.keys = new
            if self.counts is not None:
                self.counts = np.ones(len(new), np.uint32)
        if len(new):
            self._msg = None
        return len(new)

    def remove(self, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, max_depth: float = 12.0) -> int:
        """Take back what ``add`` of the same image marked (the same depth, K and pose): each
        voxel it marked counts one image less and goes when none is left. Returns the number of
        voxels gone. ValueError without counts (``counts`` None)."""
        if self.counts is None:
            raise ValueError("this observed space has no per-voxel counts (a checkpoint from before them)")
        old = self.marks(depth, K, T_WC, max_depth)
        if not len(old) or not len(self.keys):
            return 0
        i = np.searchsorted(self.keys, old)
        held = self.keys[np.minimum(i, len(self.keys) - 1)] == old
        i = i[held]
        self.counts[i] -= np.minimum(self.counts[i], 1)
        gone = self.counts == 0
        n = int(gone.sum())
        if n:
            self.keys, self.counts = self.keys[~gone], self.counts[~gone]
            self._msg = None
        return n

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: is each world point in an observed voxel."""
        if not len(self.keys):
            return np.zeros(len(points), bool)
        k = pack_keys(np.floor(np.asarray(points, np.float64) / self.voxel).astype(np.int64))
        i = np.clip(np.searchsorted(self.keys, k), 0, len(self.keys) - 1)
        return self.keys[i] == k

    def nbytes(self) -> int:
        return int(self.keys.nbytes + (0 if self.counts is None else self.counts.nbytes))

    def grid(self, keep=None) -> "ObservedGrid | None":
        """The occupancy grid of the observed voxels; ``keep(centres (N, 3)) -> (N,) bool``
        limits it to some of them (a submap's box)."""
        keys = self.keys
        if keep is not None and len(keys):
            keys = keys[keep((unpack_keys(keys) + 0.5) * self.voxel)]
        if not len(keys):
            return None
        ijk = unpack_keys(keys)
        lo = ijk.min(0)
        shape = tuple(int(x) for x in ijk.max(0) - lo + 1)
        occ = np.zeros(shape, bool)
        occ[tuple((ijk - lo).T)] = True
        return ObservedGrid(lo * self.voxel, self.voxel, occ)

    def message(self) -> dict | None:
        """The :class:`ObservedGrid` message of what is observed (None before anything is):
        built when the observed space changed, reused for every snapshot in between."""
        if self._msg is None and len(self.keys):
            self._msg = self.grid().to_msg()
        return self._msg

    def state_dict(self) -> dict:
        return {"voxel": self.voxel, "margin": self.margin, "keys": self.keys.copy(),
                "counts": None if self.counts is None else self.counts.copy()}

    def load_state_dict(self, d: dict) -> None:
        """``state_dict``'s space; one without ``counts`` (before 1.11) has none (``remove`` refuses)."""
        self.voxel, self.margin = float(d["voxel"]), float(d["margin"])
        self.keys = np.asarray(d["keys"], np.int64)
        c = d.get("counts")
        self.counts = None if c is None else np.asarray(c, np.uint32).reshape(-1)
        if self.counts is not None and len(self.counts) != len(self.keys):
            raise ValueError("observed space state: one count per key")
        self._msg = None


class ObservedGrid:
    """A dense boolean voxel grid of observed space over its bounding box."""

    def __init__(self, origin: np.ndarray, voxel: float, occ: np.ndarray):
        self.origin = np.asarray(origin, np.float64).reshape(3)
        self.voxel = float(voxel)
        self.occ = np.asarray(occ, bool)

    def contains(self, points: np.ndarray) -> np.ndarray:
        idx = np.floor((np.asarray(points, np.float64) - self.origin) / self.voxel).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(self.occ.shape)), axis=1)
        out = np.zeros(len(idx), bool)
        i = idx[inside]
        out[inside] = self.occ[i[:, 0], i[:, 1], i[:, 2]]
        return out

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) world box of the grid."""
        return np.stack([self.origin, self.origin + self.voxel * np.array(self.occ.shape)])

    def unknown_index(self):
        """(the cKDTree of the centres of the unobserved voxels that share a face with an
        observed one, those centres (M, 3)), built once per grid (``unknown_distance``). The
        grid is padded with one unobserved layer: outside the grid nothing is observed."""
        idx = getattr(self, "_unknown", None)
        if idx is None:
            from scipy import ndimage

            occ = np.pad(self.occ, 1)
            rim = ndimage.binary_dilation(occ) & ~occ  # 6-neighbours of observed voxels
            centres = self.origin + (np.argwhere(rim) - 0.5) * self.voxel
            idx = (kdtree(centres, leafsize=32) if len(centres) else None, centres)
            self._unknown = idx  # (a race builds it twice; the assignment is atomic)
        return idx

    def unknown_distance(self, points: np.ndarray, k: int = 8, k_max: int = 512) -> np.ndarray:
        """(N,) the distance from each point to the nearest space no keyframe observed (the
        cubes of the unobserved voxels, and everything outside the grid); 0 in unobserved
        space. The nearest point of unobserved space lies on a face between an unobserved and
        an observed voxel, so the exact distances to the cubes of the ``k`` such voxels with
        the nearest centres are taken; a cube farther in that order is at least the k-th
        centre's distance minus half a voxel diagonal away, and where that could be nearer the
        point is asked again with 8 times as many (up to ``k_max``, beyond which that bound is
        the answer). So the answer is exact but where ``k_max`` cubes tie within half a voxel
        diagonal, and never more than the exact distance."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.zeros(len(pts))
        seen = self.contains(pts)
        tree, centres = self.unknown_index()
        if not seen.any() or tree is None:
            return out
        h = 0.5 * self.voxel
        todo = np.flatnonzero(seen)
        while len(todo):
            kk = int(min(k, len(centres)))
            chunk = max(1, (1 << 20) // kk)  # bounds the (points, k, 3) temporaries to ~25 MB
            again = []
            for j in range(0, len(todo), chunk):
                ids = todo[j:j + chunk]
                q = pts[ids]
                d, i = tree.query(q, k=kk)
                d, i = d.reshape(len(q), kk), i.reshape(len(q), kk)
                cube = np.linalg.norm(np.maximum(np.abs(q[:, None, :] - centres[i]) - h, 0.0), axis=2).min(axis=1)
                rest = d[:, -1] - h * np.sqrt(3.0)  # no cube beyond the k-th centre is nearer than this
                open_ = np.zeros(len(q), bool) if kk == len(centres) else rest < cube
                if k >= k_max:  # give up on exactness there: the bound
                    cube = np.where(open_, rest, cube)
                    open_[:] = False
                out[ids[~open_]] = np.maximum(cube[~open_], 0.0)
                again.append(ids[open_])
            todo, k = np.concatenate(again), k * 8
        return out

    def to_msg(self) -> dict:
        return {"origin": [float(x) for x in self.origin], "voxel": self.voxel,
                "shape": [int(x) for x in self.occ.shape],
                "bits": encode_array(np.packbits(self.occ.ravel()), "|u1")}

    @classmethod
    def from_msg(cls, m: Mapping, max_cells: int = 500_000_000) -> "ObservedGrid":
        try:
            origin = np.asarray(m["origin"], np.float64).reshape(3)
            voxel = float(m["voxel"])
            shape = tuple(int(x) for x in m["shape"])
        except (KeyError, TypeError, ValueError) as e:
            raise _bad(f"observed grid: {e}") from None
        if len(shape) != 3 or min(shape) < 1 or not voxel > 0 or not np.all(np.isfinite(origin)):
            raise _bad("observed grid: needs a positive voxel, a finite origin and a 3-d shape")
        n = int(np.prod(shape))
        if n > max_cells:
            raise ProtocolError("too_large", f"observed grid of {n} cells")
        bits = decode_array(m.get("bits"), "observed.bits", ("|u1",), ((n + 7) // 8,))
        occ = np.unpackbits(bits, count=n).astype(bool).reshape(shape)
        return cls(origin, voxel, occ)
