"""Built-in procedural buildings: a plain registry ``BUILDINGS[name](seed) -> Scene``.

Every builder returns the scene in its canonical frame (z up, floor at z = 0, identity
``T_W_canon``); ``make_building`` places it in the world. The seed jitters furniture
positions by up to 0.15 m (furniture against a wall slides along it, never into it); the
room shape is fixed. Solids touch (legs under table tops, stacked boxes, shelves against
walls) but never interpenetrate.

Horizontal directions (canonical azimuth of wall / face normals, mod 180 degrees):
manhattan {0, 90}; atlanta (hexagon) {90, 150, 30} walls + {0} furniture; office
(non-convex, one 60-degree wall) {90, 0, 30} walls + {120} furniture; stairs {0, 90}.
Every pair of directions is at least 30 degrees apart.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .primitives import Boxes, Room
from .scene import Scene, rot_z

Box = tuple[np.ndarray, np.ndarray, np.ndarray]  # center, rotation, half size


class _Layout:
    """Collects boxes in the canonical frame; sizes are full sizes, ``z0`` the bottom."""

    def __init__(self, rng: np.random.Generator, jitter: float) -> None:
        self.rng, self.jitter, self.items = rng, jitter, []

    def j(self, scale: float = 1.0) -> float:
        return float(self.rng.uniform(-1, 1)) * self.jitter * scale

    def box(self, x, y, sx, sy, sz, z0=0.0, yaw=0.0) -> None:
        self.items.append((np.array([x, y, z0 + sz / 2]), rot_z(yaw), np.array([sx, sy, sz]) / 2))

    def local_box(self, origin, yaw, u, v, sx, sy, sz, z0=0.0) -> None:
        """A box centred at (u, v) in the frame at ``origin`` rotated by ``yaw``."""
        c = np.asarray(origin, dtype=float) + rot_z(yaw)[:2, :2] @ np.array([u, v])
        self.box(c[0], c[1], sx, sy, sz, z0, yaw)

    def table(self, x, y, sx, sy, height=0.74, yaw=0.0, top=0.04, leg=0.05) -> None:
        self.local_box((x, y), yaw, 0, 0, sx, sy, top, height - top)
        for a in (-1, 1):
            for b in (-1, 1):
                u, v = a * (sx / 2 - leg / 2 - 0.04), b * (sy / 2 - leg / 2 - 0.04)
                self.local_box((x, y), yaw, u, v, leg, leg, height - top)

    def chair(self, x, y, yaw=0.0, seat=0.45, leg=0.04) -> None:
        """Seat, four legs and a backrest on the chair's local -v side."""
        self.local_box((x, y), yaw, 0, 0, seat, seat, 0.05, 0.43)
        for a in (-1, 1):
            for b in (-1, 1):
                self.local_box((x, y), yaw, a * (seat / 2 - leg), b * (seat / 2 - leg), leg, leg, 0.43)
        self.local_box((x, y), yaw, 0, -seat / 2 + 0.02, seat, 0.04, 0.42, 0.48)

    def shelf(self, x, y, width, depth, height, n_boards=4, yaw=0.0, t=0.03) -> None:
        """Two sides, a back panel on the local -v side and ``n_boards`` boards."""
        for a in (-1, 1):
            self.local_box((x, y), yaw, a * (width / 2 - t / 2), 0, t, depth, height)
        self.local_box((x, y), yaw, 0, -depth / 2 + t / 4, width - 2 * t, t / 2, height)
        for k in range(n_boards):
            z = 0.1 + k * (height - 0.1 - t) / max(n_boards - 1, 1)
            self.local_box((x, y), yaw, 0, t / 4, width - 2 * t, depth - t / 2, t, z)

    def stairs(self, x, y, n, rise, run, width, yaw=0.0) -> None:
        """``n`` solid steps climbing along local +u from (x, y) (the first step's front edge)."""
        for k in range(n):
            self.local_box((x, y), yaw, (k + 0.5) * run, width / 2, run, width, (k + 1) * rise)

    def along_wall(self, poly, k, s, depth) -> tuple[np.ndarray, float]:
        """Point at fraction ``s`` of polygon edge ``k`` moved ``depth`` / 2 inwards, and the
        yaw that makes a box's local +v point into the room (its -v side on the wall)."""
        p0, p1 = poly[k], poly[(k + 1) % len(poly)]
        e = (p1 - p0) / np.linalg.norm(p1 - p0)
        n = np.array([-e[1], e[0]])
        return p0 + s * (p1 - p0) + n * depth / 2, float(np.arctan2(e[1], e[0]))

    def scene(self, poly, height, name) -> Scene:
        c, r, h = (np.array(v) for v in zip(*self.items)) if self.items else (np.zeros((0, 3)),) * 3
        return Scene(Room(np.asarray(poly, dtype=float), height), Boxes(c, r, h), name=name)


def manhattan(seed: int = 0) -> Scene:
    """6 x 5 x 2.7 m room: table on four legs, two chairs, a cabinet, boxes, a shelf."""
    L = _Layout(np.random.default_rng([seed, 11]), 0.15)
    poly = np.array([[0, 0], [6, 0], [6, 5], [0, 5]], dtype=float)
    tx, ty = 3.0 + L.j(), 2.5 + L.j()
    L.table(tx, ty, 1.4, 0.8, 0.75)
    L.chair(tx - 0.3, ty - 0.75, 0.0)
    L.chair(tx + 0.3, ty + 0.75, np.pi)
    L.box(1.2 + L.j(), 0.225, 0.9, 0.45, 0.9)  # cabinet against the y = 0 wall
    L.box(4.7 + L.j(), 4.7, 0.5, 0.6, 0.5)
    yb = 4.0 + L.j()
    L.box(0.4, yb, 0.8, 0.6, 0.3)
    L.box(0.4, yb, 0.4, 0.4, 0.3, z0=0.3)  # stacked on the previous one
    L.shelf(*L.along_wall(poly, 1, 0.3 + L.j(0.2), 0.35)[0], 1.0, 0.35, 1.9, 5, np.pi / 2)
    return L.scene(poly, 2.7, "manhattan")


def atlanta(seed: int = 0) -> Scene:
    """Elongated hexagon (walls at 60 degrees to each other), 7 x 5.2 x 2.8 m, furniture
    aligned with the horizontal walls."""
    L = _Layout(np.random.default_rng([seed, 12]), 0.15)
    s3 = 1.5 * np.sqrt(3.0)  # slanted walls at exactly 60 degrees
    poly = np.array([[1.5, 0], [5.5, 0], [7.0, s3], [5.5, 2 * s3], [1.5, 2 * s3], [0.0, s3]])
    tx, ty = 3.5 + L.j(), 2.6 + L.j()
    L.table(tx, ty, 1.6, 0.9, 0.74)
    L.chair(tx, ty - 0.8, 0.0)
    L.box(2.6 + L.j(), 0.25, 1.2, 0.5, 1.0)  # sideboard on the bottom wall
    L.shelf(4.4 + L.j(), 2 * s3 - 0.175, 1.0, 0.35, 2.0, 4, np.pi)
    L.box(2.0 + L.j(), 4.8, 0.5, 0.5, 0.45)
    L.box(5.6 + L.j(), 1.3 + L.j(), 0.6, 0.4, 0.35)
    return L.scene(poly, 2.8, "atlanta")


def office(seed: int = 0) -> Scene:
    """Non-convex Atlanta office (7 x 4.7 x 2.7 m, one wall at 60 degrees to the others,
    one reflex corner): two desks, chairs, a shelf, a cabinet on the slanted wall, boxes."""
    L = _Layout(np.random.default_rng([seed, 13]), 0.12)
    h2 = 3.0 + np.sqrt(3.0)  # the 60-degree wall from (5, 3) to (4, h2)
    poly = np.array([[0, 0], [7, 0], [7, 3], [5, 3], [4, h2], [0, h2]])
    x1 = 1.6 + L.j()
    L.table(x1, 0.35, 1.4, 0.7, 0.74)
    L.chair(x1 + L.j(), 0.95, np.pi)
    x2, y2 = 3.4 + L.j(), 2.1 + L.j()
    L.table(x2, y2, 1.2, 0.7, 0.74)
    L.chair(x2 + 0.2, y2 + 0.6, np.pi)
    L.shelf(0.175, 3.3 + L.j(), 1.0, 0.35, 2.0, 5, -np.pi / 2)
    c, yaw = L.along_wall(poly, 3, 0.5 + L.j(0.5), 0.45)
    L.local_box(c, yaw, 0, 0, 0.8, 0.45, 1.0)
    yb = 0.5 + L.j()
    L.box(6.75, yb, 0.5, 0.6, 0.45)
    L.box(6.75, yb, 0.35, 0.35, 0.3, z0=0.45)  # stacked on the previous one
    L.box(1.0 + L.j(), 4.35, 0.6, 0.6, 0.6)
    return L.scene(poly, 2.7, "office")


def stairs(seed: int = 0) -> Scene:
    """7 x 4 x 3 m room with a 7-step staircase (rise 0.17 m, run 0.28 m, 1 m wide) along
    the y = 0 wall up to a landing, plus a table and boxes."""
    L = _Layout(np.random.default_rng([seed, 14]), 0.12)
    poly = np.array([[0, 0], [7, 0], [7, 4], [0, 4]], dtype=float)
    n, rise, run = 7, 0.17, 0.28
    x0 = 3.0 + L.j()
    L.stairs(x0, 0.0, n, rise, run, 1.0)
    x1 = x0 + n * run
    L.box((x1 + 7.0) / 2, 0.5, 7.0 - x1, 1.0, n * rise)  # landing
    L.table(1.5 + L.j(), 2.8 + L.j(), 1.2, 0.7, 0.74)
    L.box(0.3, 0.3, 0.6, 0.6, 0.5)  # in the corners
    L.box(6.6, 3.6, 0.8, 0.8, 0.8)
    return L.scene(poly, 3.0, "stairs")


BUILDINGS: dict[str, Callable[[int], Scene]] = {
    "manhattan": manhattan,
    "atlanta": atlanta,
    "stairs": stairs,
    "office": office,
}


def random_world_frame(seed: int, tilt_deg: tuple[float, float] = (20.0, 70.0), offset: float = 2.0) -> np.ndarray:
    """A rigid T_W_canon whose up (canonical +z) is tilted by ``tilt_deg`` from the world
    z axis, with a random azimuth, yaw and offset (uniform in +-``offset`` metres)."""
    rng = np.random.default_rng([seed, 1])
    tilt = np.radians(rng.uniform(*tilt_deg))
    az = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(az), np.sin(az), 0.0])
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_tilt = np.eye(3) + np.sin(tilt) * Kx + (1 - np.cos(tilt)) * Kx @ Kx
    T = np.eye(4)
    T[:3, :3] = R_tilt @ rot_z(rng.uniform(0, 2 * np.pi))
    T[:3, 3] = rng.uniform(-offset, offset, 3)
    return T


def make_building(name: str = "office", seed: int = 0, world_frame: str = "tilted") -> Scene:
    """``BUILDINGS[name](seed)`` placed in the world: ``"tilted"`` (random_world_frame(seed):
    the world up is not a coordinate axis) or ``"identity"`` (world = canonical, z up)."""
    if name not in BUILDINGS:
        raise KeyError(f"unknown building {name!r}; choose from {sorted(BUILDINGS)}")
    frames = {"tilted": lambda: random_world_frame(seed), "identity": lambda: np.eye(4)}
    if world_frame not in frames:
        raise ValueError(f"world_frame must be one of {sorted(frames)}, got {world_frame!r}")
    return BUILDINGS[name](seed).with_frame(frames[world_frame]())
