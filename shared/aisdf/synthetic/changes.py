"""Built-in scenes that change while they are walked, with the ground truth of every moment.

``ChangingSequence(building, change)`` is a ``SyntheticSequence`` whose depth frame ``i`` is
rendered from ``scene_at(i)``; ``gt_sdf(points, i)`` is the exact SDF of that scene. Changes:

* ``cart``: a cart, a box ``CART_SIZE`` (0.8 x 0.6 x 1.0 m) on the floor, stands where the
  walk sees it best (clear of the furniture and the walls, away from the camera's path).
  The walk is done twice over the same path: pass 1 (frames ``[0, n)``), a pause of
  ``pause_s`` at pass 1's last pose (the cart still there), pass 2 (the same ``n`` poses
  again). The cart is gone from pass 2's first frame on (``removed_at``).
* ``person``: a person, a box ``PERSON_SIZE`` (0.35 m along its way, 0.5 m across, 1.75 m
  high), walks ``PERSON_WALK_M`` at ``PERSON_SPEED`` m/s across the camera's view during a
  stretch of pass 1 (``person_frames``), then is gone; same two passes as the cart. The
  volume it swept is ``swept`` (one box).
* ``drift``: one pass; the poses the sequence reports (``frame(i)["T_WC"]``) carry an error
  growing linearly with the frame index to ``DRIFT_M`` (0.2 m, horizontal) and ``DRIFT_DEG``
  (2 degrees about the up axis, turning the camera about its own centre); the depth is
  rendered from the true poses (``true_poses``). ``corrections(frame_ids)`` gives the true
  poses, as a SLAM loop closure would send them at the end.

Placements depend only on the building, its seed and the walk, so a frontend process and a
benchmark build the same sequence from the same settings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import Boxes, polygon_contains, polygon_nearest
from .render import KinectNoise
from .scene import Scene, rot_z
from .sequence import KINECT_HFOV_DEG, SyntheticSequence

CHANGES = ("cart", "person", "drift")
CART_SIZE = (0.8, 0.6, 1.0)
PERSON_SIZE = (0.35, 0.5, 1.75)  # along its way, across, height
PERSON_WALK_M = 2.0
PERSON_SPEED = 0.8  # m/s
DRIFT_M = 0.20
DRIFT_DEG = 2.0


@dataclass(frozen=True)
class BoxPlacement:
    """One box in the scene's canonical frame: centre (3,), yaw (rad) and full size (3,)."""

    center: np.ndarray
    yaw: float
    size: np.ndarray

    @property
    def halves(self) -> np.ndarray:
        return np.asarray(self.size, dtype=np.float64) / 2

    def boxes(self) -> Boxes:
        return Boxes(self.center[None], rot_z(self.yaw)[None], self.halves[None])

    def grid(self, spacing: float = 0.05) -> np.ndarray:
        """Canonical points (N, 3) filling the box: a lattice ``spacing`` apart, half a step
        in from its faces."""
        axes = [np.arange(-h + spacing / 2, h, spacing) for h in self.halves]
        local = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        return local @ rot_z(self.yaw).T + self.center

    def sdf(self, points_canon: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of canonical points to this box (positive outside)."""
        return self.boxes().sdf(np.asarray(points_canon, dtype=np.float64).reshape(-1, 3))[:, 0]


def with_box(scene: Scene, box: BoxPlacement) -> Scene:
    """``scene`` with one more solid box (same room, same world frame)."""
    b = scene.boxes
    nb = box.boxes()
    boxes = Boxes(np.r_[b.centers, nb.centers], np.r_[b.rotations, nb.rotations], np.r_[b.halves, nb.halves])
    return Scene(scene.room, boxes, scene.T_W_canon, name=scene.name)


def _clearance(scene: Scene, box: BoxPlacement, spacing: float = 0.1) -> float:
    """How far ``box`` stays from the walls and the solids (not the floor it stands on): the
    smallest distance over a lattice filling it, to within about ``spacing`` / 2; negative
    when it overlaps one."""
    p = box.grid(spacing)
    d_wall, _ = polygon_nearest(p[:, :2], scene.room.polygon)
    d_wall = np.where(polygon_contains(p[:, :2], scene.room.polygon), d_wall, -d_wall)
    d_box = scene.boxes.sdf(p).min(axis=1) if len(scene.boxes) else np.full(len(p), np.inf)
    return float(np.minimum(d_wall, d_box).min())


def _dist_xy(points_xy: np.ndarray, box: BoxPlacement) -> np.ndarray:
    """Horizontal distance (N,) from canonical 2D points to the box's footprint."""
    local = (np.asarray(points_xy) - box.center[:2]) @ rot_z(box.yaw)[:2, :2]
    q = np.abs(local) - box.halves[:2]
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _visible(scene: Scene, poses_W: np.ndarray, K: np.ndarray, H: int, W: int, target_canon: np.ndarray,
             near: float = 0.6, far: float = 4.0, slack: float = 0.35) -> np.ndarray:
    """(F,) bool: ``target_canon`` (3,) (or (F, 3), one per pose) projects into the image of
    each pose, between ``near`` and ``far`` m ahead, with nothing of ``scene`` in front of it
    (``slack`` m short of it)."""
    tgt = np.broadcast_to(scene.to_world(np.atleast_2d(target_canon)), (len(poses_W), 3))
    R, t = poses_W[:, :3, :3], poses_W[:, :3, 3]
    pc = np.einsum("fji,fj->fi", R, tgt - t)  # camera frame
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]
    inview = (z > near) & (z < far) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    dist = np.linalg.norm(tgt - t, axis=1)
    d = (tgt - t) / np.maximum(dist, 1e-9)[:, None]
    free = np.zeros(len(poses_W), bool)
    if inview.any():
        hit = scene.raycast(t[inview], d[inview])
        free[inview] = hit >= dist[inview] - slack
    return inview & free


def place_cart(scene: Scene, poses_W: np.ndarray, K: np.ndarray, H: int, W: int, step: float = 0.2,
               clearance: float = 0.15, camera_margin: float = 0.5) -> BoxPlacement:
    """Where the cart stands: on a ``step`` lattice of the floor, ``clearance`` m clear of
    every surface, its footprint ``camera_margin`` m from the camera's path, at the place the
    most frames (every 10th) see its centre unoccluded; axis-aligned with the canonical frame."""
    poly = scene.room.polygon
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    cam_xy = scene.to_canon(poses_W[:, :3, 3])[:, :2]
    sub = poses_W[::10]
    size = np.asarray(CART_SIZE, dtype=np.float64)
    best, best_score = None, -1
    for x in np.arange(lo[0] + step, hi[0], step):
        for y in np.arange(lo[1] + step, hi[1], step):
            box = BoxPlacement(np.array([x, y, size[2] / 2]), 0.0, size)
            if _dist_xy(cam_xy, box).min() < camera_margin or _clearance(scene, box) < clearance:
                continue
            score = int(_visible(scene, sub, K, H, W, box.center).sum())
            if score > best_score:
                best, best_score = box, score
    if best is None:
        raise RuntimeError(f"no place for a cart in {scene.name!r}")
    return best


@dataclass(frozen=True)
class PersonWalk:
    """A person crossing the view: from ``start`` to ``end`` (canonical floor points, (2,))
    during frames ``[first, last]`` at ``speed`` m/s (``fps`` frames a second)."""

    start: np.ndarray
    end: np.ndarray
    first: int
    last: int
    fps: float
    speed: float = PERSON_SPEED

    @property
    def yaw(self) -> float:
        d = self.end - self.start
        return float(np.arctan2(d[1], d[0]))

    def at(self, i: int) -> BoxPlacement | None:
        """The person's box at frame ``i`` (None outside its stretch)."""
        if not self.first <= i <= self.last:
            return None
        length = float(np.linalg.norm(self.end - self.start))
        s = min(self.speed * (i - self.first) / self.fps, length) / length
        xy = self.start + s * (self.end - self.start)
        return BoxPlacement(np.r_[xy, PERSON_SIZE[2] / 2], self.yaw, np.asarray(PERSON_SIZE, dtype=np.float64))

    @property
    def swept(self) -> BoxPlacement:
        """The volume the person swept (a box: its way, lengthened by its depth)."""
        length = float(np.linalg.norm(self.end - self.start))
        mid = (self.start + self.end) / 2
        return BoxPlacement(np.r_[mid, PERSON_SIZE[2] / 2], self.yaw,
                            np.array([length + PERSON_SIZE[0], PERSON_SIZE[1], PERSON_SIZE[2]]))


def place_person(scene: Scene, poses_W: np.ndarray, K: np.ndarray, H: int, W: int, fps: float,
                 clearance: float = 0.1, camera_margin: float = 0.5) -> PersonWalk:
    """A crossing of ``PERSON_WALK_M`` m, across the view of a frame between 20 % and 60 % of
    the walk, 1.6-2.6 m ahead of it: its swept volume ``clearance`` m clear of the walls and
    the solids and ``camera_margin`` m from the camera's path from 1 s before the crossing to
    1 s after it; the one whose person is seen unoccluded in the most frames of its stretch."""
    n = len(poses_W)
    cam_xy = scene.to_canon(poses_W[:, :3, 3])[:, :2]
    frames = int(round(PERSON_WALK_M / PERSON_SPEED * fps))
    best, best_score = None, -1
    for c in range(int(0.2 * n), max(int(0.6 * n), int(0.2 * n) + 1), 15):
        Tc = scene.T_canon_W @ poses_W[c]
        fwd = Tc[:3, 2].copy()
        fwd[2] = 0.0
        if np.linalg.norm(fwd) < 1e-6:
            continue
        fwd /= np.linalg.norm(fwd)
        right = np.array([-fwd[1], fwd[0]])
        for ahead in (1.6, 2.0, 2.3, 2.6):
            mid = cam_xy[c] + ahead * fwd[:2]
            first = c - frames // 2
            if first < 0 or first + frames >= n:
                continue
            walk = PersonWalk(mid - right * PERSON_WALK_M / 2, mid + right * PERSON_WALK_M / 2, first,
                              first + frames, fps)
            sw = walk.swept
            near = cam_xy[max(walk.first - int(fps), 0):walk.last + int(fps) + 1]
            if _dist_xy(near, sw).min() < camera_margin or _clearance(scene, sw) < clearance:
                continue
            idx = np.arange(walk.first, walk.last + 1, 3)
            centres = np.array([walk.at(int(i)).center for i in idx])
            centres[:, 2] = 1.0
            score = int(_visible(scene, poses_W[idx], K, H, W, centres, near=0.6, far=4.0).sum())
            if score > best_score:
                best, best_score = walk, score
    if best is None:
        raise RuntimeError(f"no crossing for a person in {scene.name!r}")
    return best


def drift_poses(poses_W: np.ndarray, up_W: np.ndarray, drift_m: float = DRIFT_M, drift_deg: float = DRIFT_DEG,
                seed: int = 0) -> np.ndarray:
    """``poses_W`` (n, 4, 4) with an error growing linearly in the frame index to ``drift_m``
    (a horizontal offset in a direction drawn from ``seed``) and ``drift_deg`` (about
    ``up_W``, the camera turning about its own centre) at the last frame."""
    n = len(poses_W)
    up = np.asarray(up_W, dtype=np.float64) / np.linalg.norm(up_W)
    a = np.random.default_rng([seed, 41]).uniform(0, 2 * np.pi)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    direction = np.cos(a) * e1 + np.sin(a) * e2
    s = np.arange(n) / max(n - 1, 1)
    out = np.array(poses_W, dtype=np.float64, copy=True)
    Kx = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
    for i in range(n):
        th = np.radians(drift_deg) * s[i]
        R = np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx
        out[i, :3, :3] = R @ poses_W[i, :3, :3]
        out[i, :3, 3] = poses_W[i, :3, 3] + drift_m * s[i] * direction
    return out


class ChangingSequence(SyntheticSequence):
    """A ``SyntheticSequence`` of ``building`` with one ``change`` (see the module docstring).

    ``n_frames`` is one pass of the walk; ``cart`` and ``person`` walk it twice with a
    ``pause_s`` pause between the passes (``len(self) == 2 n + pause``), ``drift`` once.
    ``pass_frames`` (n), ``pause_frames``; ``pass_of(i)`` is 1 or 2 (0 in the pause).
    """

    def __init__(
        self, building: str = "office", change: str = "cart", n_frames: int = 900, H: int = 120, W: int = 160,
        fps: float = 30.0, noise: KinectNoise | bool | None = KinectNoise(), seed: int = 0,
        hfov_deg: float = KINECT_HFOV_DEG, speed: float | None = None, world_frame: str = "tilted",
        pause_s: float = 10.0,
    ) -> None:
        if change not in CHANGES:
            raise ValueError(f"unknown change {change!r}; choose from {list(CHANGES)}")
        super().__init__(building, n_frames, H, W, fps, noise, seed, hfov_deg, speed, world_frame)
        self.change = change
        self.pass_frames = len(self.poses)
        self.true_poses = self.poses
        self.cart: BoxPlacement | None = None
        self.person: PersonWalk | None = None
        self.pause_frames = 0
        if change == "drift":
            self.sent_poses = drift_poses(self.poses, self.scene.up_W, seed=seed)
            return
        self.pause_frames = int(round(pause_s * fps))
        base = self.poses
        self.poses = np.concatenate([base, np.repeat(base[-1:], self.pause_frames, axis=0), base])
        self.true_poses = self.poses
        self.sent_poses = self.poses
        if change == "cart":
            self.cart = place_cart(self.scene, base, self.K, H, W)
            self._with_cart = with_box(self.scene, self.cart)
        else:
            self.person = place_person(self.scene, base, self.K, H, W, fps)
        if self.walk_s is not None:
            self.walk_s = len(self.poses) / fps

    @property
    def removed_at(self) -> int | None:
        """The first frame without the cart (pass 2's first frame), None without a cart."""
        return self.pass_frames + self.pause_frames if self.cart is not None else None

    def pass_of(self, i: int) -> int:
        if i < self.pass_frames:
            return 1
        return 0 if i < self.pass_frames + self.pause_frames else 2

    def scene_at(self, i: int) -> Scene:
        if self.cart is not None:
            return self._with_cart if i < self.removed_at else self.scene
        if self.person is not None:
            box = self.person.at(i)
            return self.scene if box is None else with_box(self.scene, box)
        return self.scene

    def frame(self, i: int) -> dict:
        f = super().frame(i)
        if self.change == "drift":
            f["T_WC"] = self.sent_poses[i].copy()
        return f

    def true_frame(self, i: int) -> dict:
        """Frame ``i`` with its true pose (the same depth)."""
        f = super().frame(i)
        f["T_WC"] = self.true_poses[i].copy()
        return f

    def corrections(self, frame_ids) -> dict[int, np.ndarray]:
        """{frame_id: true T_WC (4, 4)} for the given frames: what a loop closure sends."""
        return {int(i): self.true_poses[int(i)].copy() for i in frame_ids}

    def gt_sdf(self, points_W: np.ndarray, i: int | None = None) -> np.ndarray:
        """Exact SDF (N,) of world points in the scene of frame ``i`` (default: the last)."""
        return self.scene_at(len(self) - 1 if i is None else int(i)).sdf(points_W)

    def box_points(self, box: BoxPlacement, spacing: float = 0.05) -> np.ndarray:
        """World points (N, 3) filling ``box`` (its ``grid``)."""
        return self.scene.to_world(box.grid(spacing))
