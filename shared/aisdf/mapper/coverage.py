"""The mapper bounded in time: a keyframe that adds nothing new is not stored, and beyond a
whole-map bound the stored keyframe that adds least is evicted.

A front end sends a keyframe at least every ``max_interval_s`` (5 s), so a robot parked for
a day would add 17,280 keyframes, each one the same view. Here each stored keyframe is
summarised by the 10 cm voxels its valid depth pixels fall in (a few thousand pixels,
back-projected; masked pixels are invalid depth), and the voxels of all stored keyframes are
counted. A new keyframe is **redundant** when

* at least ``redundant_share`` (0.95) of its sampled valid pixels fall in voxels that stored
  keyframes observed, and
* a stored keyframe within ``redundant_distance_m`` and ``redundant_angle_deg`` of its pose
  sees the same space (at least half of those pixels fall in that keyframe's own voxels):
  the robot stands still, or came back to where it stood.

A redundant keyframe is acknowledged as any other (it counts as seen: its sender does not
resend it) but it is not stored, trained on or pooled: the mapper counts it as
``redundant``. A walk through new space is never redundant (its pixels fall in new voxels).

Eviction (the submap mapper, ``max_keyframes_total``): beyond the bound, the stored keyframe
whose voxels are best covered by the others (the largest share of its voxels that another
stored keyframe also observed; the oldest on a tie) is removed from every submap's training
store and from the map's keyframes. The newest two, those waiting for the grid and the last
keyframe of any submap are never evicted. What the map learnt from it stays: the networks,
the measured points, the observed space, the surfels and the box are kept as they are.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from pydantic import Field

from .. import geometry
from ..config import Model
from ..observed import pack_keys

VOXEL_M = 0.1  # the voxels of the coverage test (those of the measured points)
SAMPLE_PIXELS = 4800  # about this many pixels of a keyframe are back-projected (a regular stride)
SAME_SPACE_SHARE = 0.5  # a nearby stored keyframe "sees the same space" when it holds this share
SCORE_VOXELS = 256  # eviction scores a keyframe on about this many of its voxels (evenly spread)


class KeyframePolicy(Model):
    """Which keyframes the mapper keeps (``keyframes.*`` of the mapper's configuration)."""

    skip_redundant: bool = Field(True, description="a keyframe that adds nothing new (below) is acknowledged "
                                 "but not stored or trained on, and counted as redundant")
    redundant_share: float = Field(0.95, gt=0, le=1, description="... at least this share of its valid pixels "
                                   "fall in 10 cm voxels stored keyframes observed ...")
    redundant_distance_m: float = Field(0.1, ge=0, description="... and a stored keyframe that sees the same space "
                                        "is within this distance ...")
    redundant_angle_deg: float = Field(10.0, ge=0, le=180, description="... and this rotation of its pose")
    clear_free_space: bool = Field(True, description="a keyframe's rays retire the measured points, stored "
                                   "keyframes' pixels and surfels they pass through (aisdf.mapper.clearing)")
    clear_margin_m: float = Field(0.05, ge=0, description="... beyond the measured surface minus this margin ...")
    clear_sigmas: float = Field(3.0, ge=0, description="... and this many depth-noise standard deviations "
                                "(Kinect v1, Nguyen et al.: grows with the square of the range)")
    clear_window_deg: float | None = Field(None, ge=0, le=10, description="the depth a point is tested against "
                                           "is the minimum over a window this many degrees each side of its pixel "
                                           "(the pose's angular error: 0.5 for a SLAM system's poses on real depth); "
                                           "None: 2 pixels each side from 320 wide, 1 below")
    clear_passes: int = Field(2, ge=1, le=255, description="a measured point goes when this many newer "
                              "keyframes in a row pass through it, none measuring a surface there (1: the "
                              "first one; more keeps a surface that a pose's error makes one view miss)")
    max_keyframes_total: int = Field(2000, ge=4, description="keyframes the submap mapper stores over the whole "
                                     "map; beyond, the one best covered by the others is evicted (what the map "
                                     "learnt from it stays)")


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """(n,) rotation angles (degrees) of (n, 3, 3) rotations."""
    tr = np.trace(R, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


class KeyframeCoverage:
    """The voxels each stored keyframe observed, their counts, and the two decisions of the
    module docstring (``is_redundant``, ``most_redundant``). Rebuilt from the stored keyframes
    on restore (the same pixels, the same voxels)."""

    def __init__(self, policy: KeyframePolicy | None = None, max_depth: float = 12.0):
        self.policy = policy or KeyframePolicy()
        self.max_depth = float(max_depth)
        self.views: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}  # key -> (sorted voxels, T_WC)
        self._score: dict[tuple[str, int], np.ndarray] = {}  # key -> the voxels eviction scores it on
        self.keys = np.zeros(0, np.int64)  # sorted union of the views' voxels
        self.counts = np.zeros(0, np.int64)  # views observing each
        self._last: tuple[object, np.ndarray] | None = None  # (the frame last tested, its pixel voxels)

    def __len__(self) -> int:
        return len(self.views)

    def pixel_voxels(self, frame) -> np.ndarray:
        """(N,) int64 voxel keys of a regular sample of the frame's valid pixels."""
        if self._last is not None and self._last[0] is frame:
            return self._last[1]
        depth = frame.metres()
        H, W = depth.shape
        s = max(1, int(np.sqrt(H * W / SAMPLE_PIXELS)))
        d = depth[::s, ::s].astype(np.float64)
        v, u = np.nonzero(geometry.valid_depth(d, self.max_depth))
        K = np.asarray(frame.K, np.float64)
        D = d[v, u]
        P = np.stack([(u * s - K[0, 2]) / K[0, 0] * D, (v * s - K[1, 2]) / K[1, 1] * D, D], axis=-1)
        P = geometry.transform(np.asarray(frame.T_WC, np.float64), P)
        k = pack_keys(np.floor(P / VOXEL_M).astype(np.int64))
        self._last = (frame, k)
        return k

    def _count(self, k: np.ndarray) -> np.ndarray:
        if not len(self.keys):
            return np.zeros(len(k), np.int64)
        i = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
        return np.where(self.keys[i] == k, self.counts[i], 0)

    def is_redundant(self, frame) -> bool:
        """Does the frame add nothing new (module docstring)? False with ``skip_redundant`` off."""
        p = self.policy
        if not p.skip_redundant or not self.views:
            return False
        k = self.pixel_voxels(frame)
        if not len(k) or float(np.mean(self._count(k) > 0)) < p.redundant_share:
            return False
        T = np.asarray(frame.T_WC, np.float64)
        poses = np.stack([t for _, t in self.views.values()])
        near = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1) <= p.redundant_distance_m
        near &= _angle_deg(np.swapaxes(poses[:, :3, :3], 1, 2) @ T[:3, :3]) <= p.redundant_angle_deg
        views = list(self.views.values())
        for i in np.flatnonzero(near)[::-1]:  # the newest first
            if float(np.mean(np.isin(k, views[i][0], assume_unique=False))) >= SAME_SPACE_SHARE:
                return True
        return False

    def add(self, key: tuple[str, int], frame) -> None:
        """A stored keyframe's voxels into the counts."""
        if key in self.views:
            return
        new = np.unique(self.pixel_voxels(frame))
        self._last = None
        self.views[key] = (new, np.asarray(frame.T_WC, np.float64).copy())
        self._score[key] = new[:: max(1, len(new) // SCORE_VOXELS)]
        i = np.searchsorted(self.keys, new)
        held = np.zeros(len(new), bool)
        if len(self.keys):
            held = self.keys[np.minimum(i, len(self.keys) - 1)] == new
        self.counts[i[held]] += 1
        self.keys = np.insert(self.keys, i[~held], new[~held])
        self.counts = np.insert(self.counts, i[~held], np.ones(int((~held).sum()), np.int64))

    def remove(self, key: tuple[str, int]) -> None:
        """A keyframe no longer stored: its voxels out of the counts."""
        view = self.views.pop(key, None)
        self._score.pop(key, None)
        if view is None or not len(view[0]):
            return
        i = np.searchsorted(self.keys, view[0])
        self.counts[i] -= 1
        keep = self.counts > 0
        self.keys, self.counts = self.keys[keep], self.counts[keep]

    def most_redundant(self, candidates: Iterable[tuple[str, int]]) -> tuple[str, int] | None:
        """Of ``candidates`` (stored keys), the one whose voxels others observe most (largest
        share of its voxels counted at least twice, on an even sample of them: the cost does not
        grow with the image); the first of them on a tie."""
        cands = [c for c in candidates if c in self.views]
        if not cands:
            return None
        vox = [self._score[c] for c in cands]
        lens = np.array([len(v) for v in vox])
        if not lens.sum():
            return cands[0]
        allv = np.concatenate(vox)
        shared = (self._count(allv) >= 2).astype(np.float64)
        starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
        sums = np.add.reduceat(shared, np.minimum(starts, len(allv) - 1))
        sums = np.where(lens > 0, sums, 0.0)
        share = np.where(lens > 0, sums / np.maximum(lens, 1), 1.0)
        return cands[int(np.argmax(share))]

    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.counts.nbytes + sum(v.nbytes + t.nbytes for v, t in self.views.values()))
