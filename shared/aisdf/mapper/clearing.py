"""Free space clears: what a newer depth ray passes through is gone.

Every valid depth pixel of a keyframe says that the space along its ray, up to the measured
surface, is free. Anything the map holds there (a cart that was moved away, a person who
walked through the view) is contradicted by the newer keyframe and retired:

* **measured points** (``MeasuredSurface``): the voxels whose mean point ``CLEAR_PASSES``
  (``keyframes.clear_passes``, 2) newer keyframes in a row pass through are removed; a
  keyframe that measures a surface at the point (its window's depth within the test's
  tolerance of it) resets the count, so one view whose pose error moves a depth edge does not
  erase a surface the others keep measuring (7-Scenes' red kitchen, static: 20 % of the
  measured voxels cleared instead of 28 %; consecutive keyframes' poses tend to err alike, so
  two in a row is a modest guard, not a cure);
* **stored keyframes' pixels**: a stored keyframe's pixel whose 3-d point the new keyframe's
  rays pass through is set to no measurement (depth 0, in place: every submap's view of the
  keyframe shares the array), so training stops replaying the surface that has gone, and
  the networks learn the free space from the new rays;
* **global surfels**: a surfel of which more than half of the points the new keyframe can
  test are passed through is removed (the next keyframe that sees a surface there adds it
  again); its points are sampled every 10 cm over its rectangle.

The observed space is untouched: seen free is still seen.

**The test.** A world point P at camera depth z projects to pixel (u, v); it is passed
through when the keyframe measured, at that pixel, a surface farther than
z + ``margin`` + ``sigmas`` x sigma(d), with sigma(d) = 0.0012 + 0.0019 (d - 0.4)^2 m
(Nguyen et al. 2012, the Kinect v1 axial noise, the one the built-in scenes render with; it
grows with the square of the range: 3 sigma is 5 mm at 1 m, 2.9 cm at 3 m, 7.7 cm at 4 m).
The measured depth is the minimum over a window of pixels around (u, v) (2 pixels each side
from 320 pixels wide, 1 below): at a depth edge or at grazing angles the nearer neighbour
wins, so a surface that is still there is not cleared by a ray that only grazes it. A window
holding a pixel without depth tests nothing, with one exception for the measured points:
there such a window takes the minimum over the pixels it has, when (u, v) itself has a depth
and at least half of the window does. Depth cameras drop a band of pixels along depth edges,
and a window that tested nothing there kept whatever had stood in front of an edge (a person
passing in front of a table) in the measured points for good. The exception also clears a
few real edge voxels (the static office walked twice: 66 measured voxels of 8,230 instead of
35); the next stored keyframe that sees them measures them again, so they are not news
(below). Stored keyframes' pixels and surfels keep the strict test: a pixel cleared there is
gone for good (the office walked twice with the exception: 88 % of the pixels it cleared
lay within 2 cm of a true surface, against 20 % without). ``margin`` (5 cm by
default) covers the measured points' 10 cm voxel means, which sit off a curved or cornered
surface by up to a few centimetres, and a few centimetres of pose error.

**Real depth with estimated poses.** A pose's angular error moves a point's pixel by several
pixels at a depth edge, and the point is then tested against the background behind the edge;
a wider depth margin does not help. On 7-Scenes' red kitchen (Kinect v1 depth, KinectFusion
poses; 250 frames, 200 keyframes) the default window clears 26-28 % of the measured voxels and
7 % of the stored pixels of a static scene (5 cm margin; 10 cm: 21 % and 5 %). Between
frame pairs, the share of one frame's points another passes through falls 3-10x with a
window of about 0.5 degrees each side (``keyframes.clear_window_deg``, 6 pixels at 585 px
focal length); end to end, 0.5 degrees clears 14 % of the measured voxels and 3 % of the
stored pixels, and the whole intake takes a third of the time (142 s against 436 s for the
250 frames, fewer keyframes stored as news). What is left is not the window:
some frame pairs disagree by more than a degree. The default stays the pixel window, whose
figures on exact poses (the changing scenes) are measured; on estimated poses set 0.5, or
turn clearing off where the scene is known to be static
(docs/experiments/clearing-real-data.md).

Keyframes tested against the new one: those whose coverage voxels (``coverage``, the 10 cm
voxels of their sampled pixels) include or neighbour a measured voxel the new keyframe
cleared, so the cost follows what changed, not the number of keyframes; each is first
tested on a sample of its pixels, then at full resolution when anything was cleared.

A keyframe that clears a surface is never ``redundant`` (it brings news, even from the pose
of a stored keyframe): at least ``NEWS_VOXELS`` measured voxels holding ``min_hits`` pixels,
or a surfel. Clearing stray noisy pixels (voxels of one or two) is not news, so a parked
robot's keyframes stay redundant. Off with ``keyframes.clear_free_space = false``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .. import geometry
from ..observed import neighbourhood

SURFEL_SAMPLE_M = 0.1  # surfel points tested every this far over the rectangle
SURFEL_MAX_SAMPLES = 400  # ... at most this many per surfel (a coarser spacing beyond)
SURFEL_CLEAR_SHARE = 0.5  # a surfel goes when more than this share of its testable points is passed through
SURFEL_MIN_CLEARED = 4  # ... and at least this many of them
NEWS_VOXELS = 3  # a keyframe clearing this many measured voxels of surface (or a surfel) is news
CLEAR_PASSES = 2  # a measured voxel goes when this many newer keyframes in a row pass through it
HOLE_WINDOW_VALID = 0.5  # a window with holes tests when its own pixel and this share of it have a depth
KEYFRAME_SAMPLE = 4  # stored keyframes are screened on every 4th pixel in both directions


def depth_sigma(d: np.ndarray) -> np.ndarray:
    """Kinect v1 axial noise standard deviation (m) at depth d (m), Nguyen et al. 2012."""
    return 0.0012 + 0.0019 * (np.asarray(d, np.float64) - 0.4) ** 2


def window_radius(W: int, K: np.ndarray, window_deg: float | None = None) -> int:
    """Pixels each side of the window: ``window_deg`` degrees at the focal length (at least 1),
    else 2 from 320 pixels wide and 1 below."""
    if window_deg is None:
        return 2 if W >= 320 else 1
    return max(1, int(np.ceil(np.tan(np.radians(window_deg)) * float(np.asarray(K)[0, 0]) - 1e-9)))


class FreeSpace:
    """One keyframe's evidence of free space (module docstring): ``passed(points)``."""

    def __init__(self, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, max_depth: float = 12.0,
                 margin: float = 0.05, sigmas: float = 3.0, window_deg: float | None = None):
        depth = np.asarray(depth, np.float32)
        d = np.where(geometry.valid_depth(depth, max_depth), depth, 0.0).astype(np.float32)
        H, W = d.shape
        r = window_radius(W, K, window_deg)
        size = 2 * r + 1
        # the minimum over the window; the border adds nothing (as cv2.erode's default), holes as 0
        dmin = ndimage.minimum_filter(d, size=size, mode="nearest")
        # a window with holes: the minimum over its measured pixels when its own pixel has a depth
        # and at least HOLE_WINDOW_VALID of the window does (the hole band along a depth edge)
        valid = d > 0
        share = ndimage.uniform_filter(valid.astype(np.float32), size=size, mode="nearest")
        vmin = ndimage.minimum_filter(np.where(valid, d, np.inf).astype(np.float32), size=size, mode="nearest")
        holey = (dmin == 0) & valid & (share >= HOLE_WINDOW_VALID - 1e-6)
        self.dmin = dmin
        self.dmin_holes = np.where(holey, vmin, dmin).astype(np.float32)
        self.K = np.asarray(K, np.float64)
        T = np.asarray(T_WC, np.float64)
        self.R, self.t = T[:3, :3], T[:3, 3]
        self.margin, self.sigmas = float(margin), float(sigmas)

    def _lookup(self, points: np.ndarray, holes: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(z of each point in the camera, the window's minimum depth at its pixel; 0 = none)."""
        P = (np.asarray(points, np.float64).reshape(-1, 3) - self.t) @ self.R
        z = P[:, 2]
        H, W = self.dmin.shape
        d = np.zeros(len(P), np.float32)
        front = z > 1e-3
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(self.K[0, 0] * P[:, 0] / z + self.K[0, 2])
            v = np.rint(self.K[1, 1] * P[:, 1] / z + self.K[1, 2])
        inside = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        d[inside] = (self.dmin_holes if holes else self.dmin)[v[inside].astype(np.int64), u[inside].astype(np.int64)]
        return z, d

    def passed(self, points: np.ndarray, holes: bool = False) -> np.ndarray:
        """(N,) bool: the keyframe's rays pass through the point, beyond the noise; ``holes``
        also tests windows with holes (the measured points only, module docstring)."""
        return self.tested(points, holes)[0]

    def tested(self, points: np.ndarray, holes: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(passed, testable): testable points are in view with a depth in their window."""
        z, d = self._lookup(points, holes)
        testable = (d > 0) & (z > 1e-3)
        return testable & (d > z + self.margin + self.sigmas * depth_sigma(d)), testable

    def verdict(self, points: np.ndarray, holes: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(passed, confirmed): passed as ``passed``; confirmed where the window's depth lies
        within the same tolerance of the point (the keyframe measured a surface there). A point
        behind a nearer surface is neither."""
        z, d = self._lookup(points, holes)
        testable = (d > 0) & (z > 1e-3)
        tol = self.margin + self.sigmas * depth_sigma(d)
        return testable & (d > z + tol), testable & (np.abs(d - z) <= tol)


def clear_measured(measured, evidence: FreeSpace, passes: int = CLEAR_PASSES) -> tuple[np.ndarray, np.ndarray, int]:
    """Counts ``evidence``'s verdict on every measured voxel's mean point (windows with holes
    included; ``MeasuredSurface.note_evidence``) and removes the voxels (any count) passed
    through by ``passes`` keyframes in a row, none of them measuring a surface there; returns
    their keys (sorted), their mean points and how many of them held at least ``min_hits``
    pixels (surface, not a stray noisy pixel) and were passed through by a window without holes."""
    if measured is None or not len(measured):
        return np.zeros(0, np.int64), np.zeros((0, 3)), 0
    pts = measured.sums / measured.counts[:, None]
    passed, confirmed = evidence.verdict(pts, holes=True)
    gone = measured.note_evidence(passed, confirmed, passes)
    if not gone.any():
        return np.zeros(0, np.int64), np.zeros((0, 3)), 0
    # news counts only what a window without holes passes: the hole band along a real edge
    # flickers (cleared, measured again) and must not make a parked robot's keyframes news
    strict = evidence.passed(pts[gone])
    keys, pts = measured.keys[gone], pts[gone]
    solid = int(((measured.counts[gone] >= measured.min_hits) & strict).sum())
    measured.remove(gone)
    return keys, pts, solid


def candidate_keyframes(coverage, cleared_keys: np.ndarray) -> list[tuple[str, int]]:
    """Stored keyframes whose coverage voxels meet the cleared voxels or their neighbours."""
    if not len(cleared_keys):
        return []
    near = neighbourhood(cleared_keys)
    return [key for key, (vox, _) in coverage.views.items() if len(vox) and np.isin(vox, near).any()]


def clear_pixels(raw: np.ndarray, scale: float | None, K: np.ndarray, T_WC: np.ndarray,
                 evidence: FreeSpace) -> int:
    """Sets to 0 (in place) the pixels of a stored keyframe's depth (``raw``; metres =
    raw / ``scale``, or metres when ``scale`` is None) whose 3-d point ``evidence`` passes
    through; returns how many. Screened on a sample of the pixels first."""
    H, W = raw.shape
    K = np.asarray(K, np.float64)
    T = np.asarray(T_WC, np.float64)

    def points(v: np.ndarray, u: np.ndarray) -> np.ndarray:
        D = raw[v, u].astype(np.float64)
        if scale is not None:
            D = D / scale
        P = np.stack([(u - K[0, 2]) / K[0, 0] * D, (v - K[1, 2]) / K[1, 1] * D, D], axis=-1)
        return geometry.transform(T, P)

    s = KEYFRAME_SAMPLE
    v, u = np.nonzero(raw[s // 2::s, s // 2::s] > 0)
    if not len(v) or not evidence.passed(points(v * s + s // 2, u * s + s // 2)).any():
        return 0
    v, u = np.nonzero(raw > 0)
    gone = evidence.passed(points(v, u))
    raw[v[gone], u[gone]] = 0
    return int(gone.sum())


def surfel_samples(surfels) -> tuple[np.ndarray, np.ndarray]:
    """(points (M, 3), owner (M,)): points every ``SURFEL_SAMPLE_M`` over each rectangle
    (at most ``SURFEL_MAX_SAMPLES`` per surfel)."""
    pts, owner = [], []
    for i in range(len(surfels)):
        ext = np.asarray(surfels.extent[i], np.float64)
        n = np.maximum(1, np.ceil(ext / SURFEL_SAMPLE_M)).astype(int)
        while n[0] * n[1] > SURFEL_MAX_SAMPLES:
            n = np.maximum(1, (n * 0.8).astype(int))
        a = (np.arange(n[0]) + 0.5) / n[0] - 0.5
        b = (np.arange(n[1]) + 0.5) / n[1] - 0.5
        A, B = np.meshgrid(a * ext[0], b * ext[1], indexing="ij")
        p = (surfels.center[i][None] + A.reshape(-1, 1) * surfels.axis1[i][None]
             + B.reshape(-1, 1) * surfels.axis2[i][None])
        pts.append(p)
        owner.append(np.full(len(p), i))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(owner)


def surfels_passed(surfels, evidence: FreeSpace) -> np.ndarray:
    """(S,) bool: surfels more than half of whose testable points ``evidence`` passes through."""
    if not len(surfels):
        return np.zeros(0, bool)
    pts, owner = surfel_samples(surfels)
    passed, testable = evidence.tested(pts)
    n_pass = np.bincount(owner, passed, minlength=len(surfels))
    n_test = np.bincount(owner, testable, minlength=len(surfels))
    return (n_pass >= SURFEL_MIN_CLEARED) & (n_pass > SURFEL_CLEAR_SHARE * n_test)
