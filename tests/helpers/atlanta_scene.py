"""Analytic Atlanta test scenes for test_atlanta / test_surfels / test_surfel_map.

A convex room (a floor-plan polygon extruded between floor and ceiling) with box
obstacles whose sides follow the room's directions, built z-up in a *scene* frame and
moved into an arbitrarily rotated and translated *world* frame. Depth is rendered by
exact ray-plane intersection, with Kinect-like Gaussian noise growing with depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from aisdf.geometry import intrinsics, ray_dirs_C


def kinect_sigma(z: np.ndarray) -> np.ndarray:
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


@dataclass
class Box:
    center: np.ndarray  # scene frame
    yaw_deg: float
    half: np.ndarray  # (3,) half extents along (yaw dir, its left, up)

    def axes(self) -> np.ndarray:
        y = np.radians(self.yaw_deg)
        return np.array([[np.cos(y), np.sin(y), 0.0], [-np.sin(y), np.cos(y), 0.0], [0.0, 0.0, 1.0]])  # rows


@dataclass
class Scene:
    polygon: np.ndarray  # (V, 2) convex, counter-clockwise, scene frame
    height: float
    boxes: list[Box] = field(default_factory=list)
    T_WS: np.ndarray = field(default_factory=lambda: np.eye(4))  # scene -> world

    # ------------------------------------------------------------------ geometry (scene frame)
    def room_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Inward normals n (F,3) and offsets d: the room is {x: n.x >= d}."""
        ns, ds = [np.array([0, 0, 1.0]), np.array([0, 0, -1.0])], [0.0, -self.height]
        P = self.polygon
        for i in range(len(P)):
            a, b = P[i], P[(i + 1) % len(P)]
            t = (b - a) / np.linalg.norm(b - a)
            n = np.array([-t[1], t[0], 0.0])  # left of the edge = inside (CCW)
            ns.append(n)
            ds.append(float(n[:2] @ a))
        return np.array(ns), np.array(ds)

    def wall_angles_deg(self) -> np.ndarray:
        """Horizontal directions (mod 180) of walls and box sides, scene frame."""
        n, _ = self.room_planes()
        a = np.degrees(np.arctan2(n[2:, 1], n[2:, 0])) % 180
        b = [(bx.yaw_deg + k) % 180 for bx in self.boxes for k in (0, 90)]
        return np.unique(np.round(np.concatenate([a, b]), 6))

    def faces(self) -> list[dict]:
        """Every planar face: scene-frame normal (outward from the solid = into free space), offset, kind."""
        out = []
        n, d = self.room_planes()
        for i in range(len(n)):
            out.append({"kind": "room", "i": i, "normal": n[i], "offset": d[i]})
        for bi, bx in enumerate(self.boxes):
            R = bx.axes()
            for k in range(3):
                for s in (-1, 1):
                    nn = s * R[k]
                    out.append({"kind": "box", "box": bi, "axis": k, "normal": nn,
                                "offset": float(nn @ bx.center + bx.half[k])})
        return out

    def on_face(self, x_S: np.ndarray, face: dict, tol_plane: float, tol_in: float) -> np.ndarray:
        """Points (N,3) in the scene frame lying on ``face`` (within tolerances)."""
        on = np.abs(x_S @ face["normal"] - face["offset"]) <= tol_plane
        if face["kind"] == "room":
            n, d = self.room_planes()
            keep = np.arange(len(n)) != face["i"]
            inside = np.all(x_S @ n[keep].T - d[keep] >= -tol_in, axis=1)
        else:
            bx = self.boxes[face["box"]]
            loc = (x_S - bx.center) @ bx.axes().T
            inside = np.all(np.abs(loc) <= bx.half + tol_in, axis=1)
        return on & inside

    def on_any_face(self, x_W: np.ndarray, tol_plane: float = 0.03, tol_in: float = 0.01) -> np.ndarray:
        x_S = self.to_scene(x_W)
        return np.any([self.on_face(x_S, f, tol_plane, tol_in) for f in self.faces()], axis=0)

    # ------------------------------------------------------------------ frames
    def to_scene(self, x_W: np.ndarray) -> np.ndarray:
        T = np.linalg.inv(self.T_WS)
        return x_W @ T[:3, :3].T + T[:3, 3]

    def vertical_W(self) -> np.ndarray:
        return self.T_WS[:3, :3] @ np.array([0, 0, 1.0])

    def horizontal_W(self, angle_deg: float) -> np.ndarray:
        a = np.radians(angle_deg)
        return self.T_WS[:3, :3] @ np.array([np.cos(a), np.sin(a), 0.0])

    def pose(self, pos_S, yaw_deg: float, pitch_deg: float = -15.0, roll_deg: float = 0.0) -> np.ndarray:
        """T_WC of an OpenCV camera at pos_S (scene frame) looking along yaw, pitched (negative = down)."""
        y, p = np.radians(yaw_deg), np.radians(pitch_deg)
        z = np.array([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), np.sin(p)])
        x = np.cross(z, [0, 0, 1.0]); x /= np.linalg.norm(x)
        yv = np.cross(z, x)
        R = np.stack([x, yv, z], axis=1) @ Rotation.from_rotvec([0, 0, np.radians(roll_deg)]).as_matrix()
        T = np.eye(4); T[:3, :3] = R; T[:3, 3] = pos_S
        return self.T_WS @ T

    # ------------------------------------------------------------------ rendering
    def render(self, T_WC: np.ndarray, K: np.ndarray, H: int, W: int, rng: np.random.Generator | None = None,
               noise: float = 1.0, max_depth: float = 6.0, dropout: float = 0.02) -> np.ndarray:
        """Depth (H, W) in metres (0 = invalid); noise sigma = noise * Kinect sigma(z)."""
        T_SC = np.linalg.inv(self.T_WS) @ T_WC
        dirs = ray_dirs_C(K, H, W).reshape(-1, 3) @ T_SC[:3, :3].T  # z_C = 1 along these
        o = T_SC[:3, 3]
        n, d = self.room_planes()
        nd = dirs @ n.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - n @ o)[None] / nd
        t = np.where(nd < 0, t, np.inf).min(axis=1)  # leaving the convex room
        for bx in self.boxes:
            R = bx.axes()
            lo_o = R @ (o - bx.center)
            ld = dirs @ R.T
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-bx.half - lo_o) / ld
                t2 = (bx.half - lo_o) / ld
            tn = np.nanmax(np.minimum(t1, t2), axis=1)
            tf = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tn <= tf) & (tn > 0)
            t = np.where(hit & (tn < t), tn, t)
        z = t.reshape(H, W)
        if rng is not None and noise > 0:
            z = z + rng.normal(size=z.shape) * noise * kinect_sigma(z)
        if rng is not None and dropout > 0:
            z[rng.random(z.shape) < dropout] = 0
        z[~np.isfinite(z) | (z > max_depth) | (z < 0.1)] = 0
        return z


def camera(H: int) -> np.ndarray:
    """Kinect-like intrinsics scaled to H in {120, 240, 480}."""
    s = H / 480
    return intrinsics(525 * s, 525 * s, 319.5 * s, 239.5 * s)


def random_T_WS(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


def atlanta_room(seed: int = 0, boxes: bool = True) -> Scene:
    """Pentagon room, walls at 0, 31, 90, 149 degrees (30-60 degrees apart), a cabinet and a table."""
    poly = np.array([[0.0, 0.0], [5.0, 0.0], [6.5, 2.5], [5.0, 5.0], [0.0, 5.0]])
    bxs = [Box(np.array([0.45, 2.5, 0.45]), 0.0, np.array([0.3, 0.6, 0.45])),  # cabinet on the left wall
           Box(np.array([2.8, 3.6, 0.73]), 0.0, np.array([0.5, 0.35, 0.02]))] if boxes else []  # table top
    return Scene(poly, 2.8, bxs, random_T_WS(seed))


def manhattan_room(seed: int = 0) -> Scene:
    poly = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 4.0], [0.0, 4.0]])
    return Scene(poly, 2.7, [], random_T_WS(seed))


def trajectory(scene: Scene, n: int, seed: int = 0) -> list[np.ndarray]:
    """n camera poses inside the room, turning around, looking slightly down."""
    rng = np.random.default_rng(seed)
    c = scene.polygon.mean(axis=0)
    poses = []
    for k in range(n):
        pos = np.array([c[0] + rng.uniform(-0.8, 0.8), c[1] + rng.uniform(-0.8, 0.8), rng.uniform(1.1, 1.5)])
        yaw = 360.0 * k / n + rng.uniform(-10, 10)
        poses.append(scene.pose(pos, yaw, rng.uniform(-25, -5), rng.uniform(-3, 3)))
    return poses
