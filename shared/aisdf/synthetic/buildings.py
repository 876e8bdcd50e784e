"""Built-in procedural buildings: a plain registry ``BUILDINGS[name](seed) -> Scene``.

Every builder returns the scene in its canonical frame (z up, floor at z = 0, identity
``T_W_canon``); ``make_building`` places it in the world. The seed jitters furniture
positions by up to 0.15 m (furniture against a wall slides along it, never into it); the
room shape is fixed. Every box is labelled (``Scene.kinds``: "wall" for the floor's interior
walls and lintels, the layout; "table", "chair", "shelf", "cabinet", "box", "stairs" for the
furniture, see scene.py); every building has furniture. Solids touch (legs under table tops, stacked boxes, shelves against
walls) but never interpenetrate.

Horizontal directions (canonical azimuth of wall / face normals, mod 180 degrees):
manhattan {0, 90}; atlanta (hexagon) {90, 150, 30} walls + {0} furniture; office
(non-convex, one 60-degree wall) {90, 0, 30} walls + {120} furniture; stairs {0, 90};
floor (a corridor, seven rooms behind doors, a wing turned 42 degrees) {0, 90, 42, 132}.
Every pair of directions is at least 30 degrees apart.

Buildings with a ``FloorPlan`` (``PLANS``: named room regions and a walk through every
room) are walked by ``trajectory.make_walk`` instead of the closed loop of
``make_trajectory``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import wraps
from typing import Callable

import numpy as np

from .primitives import Boxes, Room, polygon_contains
from .scene import Scene, rot_z

Box = tuple[np.ndarray, np.ndarray, np.ndarray]  # center, rotation, half size


def _piece(kind: str):
    """A ``_Layout`` method whose boxes are all labelled ``kind`` (a table's top and legs, ...)."""
    def deco(fn):
        @wraps(fn)
        def labelled(self, *a, **k):
            before, self.kind = self.kind, kind
            try:
                return fn(self, *a, **k)
            finally:
                self.kind = before
        return labelled
    return deco


class _Layout:
    """Collects boxes in the canonical frame; sizes are full sizes, ``z0`` the bottom."""

    def __init__(self, rng: np.random.Generator, jitter: float) -> None:
        self.rng, self.jitter, self.items = rng, jitter, []
        self.kinds: list[str] = []  # one label per item (scene.py); ``kind``: the default
        self.kind = "box"

    def j(self, scale: float = 1.0) -> float:
        return float(self.rng.uniform(-1, 1)) * self.jitter * scale

    def box(self, x, y, sx, sy, sz, z0=0.0, yaw=0.0, kind: str | None = None) -> None:
        self.items.append((np.array([x, y, z0 + sz / 2]), rot_z(yaw), np.array([sx, sy, sz]) / 2))
        self.kinds.append(kind or self.kind)

    def local_box(self, origin, yaw, u, v, sx, sy, sz, z0=0.0, kind: str | None = None) -> None:
        """A box centred at (u, v) in the frame at ``origin`` rotated by ``yaw``."""
        c = np.asarray(origin, dtype=float) + rot_z(yaw)[:2, :2] @ np.array([u, v])
        self.box(c[0], c[1], sx, sy, sz, z0, yaw, kind)

    @_piece("table")
    def table(self, x, y, sx, sy, height=0.74, yaw=0.0, top=0.04, leg=0.05) -> None:
        self.local_box((x, y), yaw, 0, 0, sx, sy, top, height - top)
        for a in (-1, 1):
            for b in (-1, 1):
                u, v = a * (sx / 2 - leg / 2 - 0.04), b * (sy / 2 - leg / 2 - 0.04)
                self.local_box((x, y), yaw, u, v, leg, leg, height - top)

    @_piece("chair")
    def chair(self, x, y, yaw=0.0, seat=0.45, leg=0.04) -> None:
        """Seat, four legs and a backrest on the chair's local -v side."""
        self.local_box((x, y), yaw, 0, 0, seat, seat, 0.05, 0.43)
        for a in (-1, 1):
            for b in (-1, 1):
                self.local_box((x, y), yaw, a * (seat / 2 - leg), b * (seat / 2 - leg), leg, leg, 0.43)
        self.local_box((x, y), yaw, 0, -seat / 2 + 0.02, seat, 0.04, 0.42, 0.48)

    @_piece("shelf")
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
            self.local_box((x, y), yaw, (k + 0.5) * run, width / 2, run, width, (k + 1) * rise, kind="stairs")

    def along_wall(self, poly, k, s, depth) -> tuple[np.ndarray, float]:
        """Point at fraction ``s`` of polygon edge ``k`` moved ``depth`` / 2 inwards, and the
        yaw that makes a box's local +v point into the room (its -v side on the wall)."""
        p0, p1 = poly[k], poly[(k + 1) % len(poly)]
        e = (p1 - p0) / np.linalg.norm(p1 - p0)
        n = np.array([-e[1], e[0]])
        return p0 + s * (p1 - p0) + n * depth / 2, float(np.arctan2(e[1], e[0]))

    def scene(self, poly, height, name) -> Scene:
        c, r, h = (np.array(v) for v in zip(*self.items)) if self.items else (np.zeros((0, 3)),) * 3
        return Scene(Room(np.asarray(poly, dtype=float), height), Boxes(c, r, h), name=name, kinds=tuple(self.kinds))


def manhattan(seed: int = 0) -> Scene:
    """6 x 5 x 2.7 m room: table on four legs, two chairs, a cabinet, boxes, a shelf."""
    L = _Layout(np.random.default_rng([seed, 11]), 0.15)
    poly = np.array([[0, 0], [6, 0], [6, 5], [0, 5]], dtype=float)
    tx, ty = 3.0 + L.j(), 2.5 + L.j()
    L.table(tx, ty, 1.4, 0.8, 0.75)
    L.chair(tx - 0.3, ty - 0.75, 0.0)
    L.chair(tx + 0.3, ty + 0.75, np.pi)
    L.box(1.2 + L.j(), 0.225, 0.9, 0.45, 0.9, kind="cabinet")  # cabinet against the y = 0 wall
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
    L.box(2.6 + L.j(), 0.25, 1.2, 0.5, 1.0, kind="cabinet")  # sideboard on the bottom wall
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
    L.local_box(c, yaw, 0, 0, 0.8, 0.45, 1.0, kind="cabinet")
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
    L.box((x1 + 7.0) / 2, 0.5, 7.0 - x1, 1.0, n * rise, kind="stairs")  # landing
    L.table(1.5 + L.j(), 2.8 + L.j(), 1.2, 0.7, 0.74)
    L.box(0.3, 0.3, 0.6, 0.6, 0.5)  # in the corners
    L.box(6.6, 3.6, 0.8, 0.8, 0.8)
    return L.scene(poly, 3.0, "stairs")


# ------------------------------------------------------------------ a multi-room floor

WING_DEG = 42.0  # the east wing is turned this much against the main wing
WING_LEN = 12.5  # length of the east wing along its corridor (m)
_T_WALL = 0.12  # interior wall thickness (m); boxes sit on the room side of each wall line
_DOOR_W, _DOOR_H = 1.0, 2.1  # door openings: width, height (a lintel closes the wall above)


@dataclass(frozen=True)
class Visit:
    """One room of a walk: enter through the door, look around at ``look``, leave the way
    it came. Canonical 2D points: ``corridor`` (in front of the door, on the corridor's
    centre line), ``door`` (the opening's centre), ``look`` (where the camera turns round)."""

    room: str
    corridor: np.ndarray
    door: np.ndarray
    look: np.ndarray


@dataclass(frozen=True)
class FloorPlan:
    """Named regions (canonical polygons, counter-clockwise) and the walk through them:
    ``start`` and ``end`` on the corridor, ``visits`` in order, ``route`` extra corridor
    points walked between visits (keyed by the index of the visit they precede; -1 = after
    the last one)."""

    regions: dict[str, np.ndarray]
    start: np.ndarray
    visits: tuple[Visit, ...]
    end: np.ndarray
    route: dict[int, tuple[np.ndarray, ...]] = field(default_factory=dict)

    def region_of(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) canonical points -> (N,) region index into ``names`` (-1: none)."""
        out = np.full(len(xy), -1)
        for i, poly in enumerate(self.regions.values()):
            out[(out < 0) & polygon_contains(np.asarray(xy, dtype=float), poly)] = i
        return out

    @property
    def names(self) -> list[str]:
        return list(self.regions)


class _Frame2D:
    """A room's local 2D frame: ``origin`` and ``yaw`` (rad); local u, v -> canonical x, y."""

    def __init__(self, origin, yaw: float) -> None:
        self.o, self.yaw = np.asarray(origin, dtype=float), float(yaw)
        self.R = rot_z(yaw)[:2, :2]

    def __call__(self, u: float, v: float) -> np.ndarray:
        return self.o + self.R @ np.array([u, v], dtype=float)


def _wall(L: _Layout, a, b, height: float, doors=(), side: float = 1.0, t: float = _T_WALL) -> None:
    """A wall from ``a`` to ``b`` (2D) of thickness ``t`` on the ``side`` (+1 left of a->b,
    -1 right) of the line, with door openings centred at the given distances from ``a``
    (each ``_DOOR_W`` wide, a lintel above ``_DOOR_H``)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    length = float(np.linalg.norm(b - a))
    yaw = float(np.arctan2(*(b - a)[::-1]))
    f = _Frame2D(a, yaw)
    cuts = [0.0]
    for s in sorted(doors):
        cuts += [s - _DOOR_W / 2, s + _DOOR_W / 2]
    cuts.append(length)
    for k in range(0, len(cuts), 2):
        s0, s1 = cuts[k], cuts[k + 1]
        if s1 - s0 > 1e-6:
            L.local_box(f.o, yaw, (s0 + s1) / 2, side * t / 2, s1 - s0, t, height, kind="wall")
    for s in doors:
        L.local_box(f.o, yaw, s, side * t / 2, _DOOR_W, t, height - _DOOR_H, z0=_DOOR_H, kind="wall")


def _floor_geometry() -> dict:
    """The floor's fixed lines (canonical, metres): the main wing (x in [0, 12]; rooms 1-3
    south of the corridor y in [4.5, 6.5], rooms 4-5 north of it) and the east wing turned
    ``WING_DEG`` about O = (12, 4.5) (its corridor v in [0, 2], rooms 6-7 at v in [-4.5, 0],
    u along the wing up to ``WING_LEN``)."""
    a = np.radians(WING_DEG)
    d, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    O = np.array([12.0, 4.5])
    wing = lambda u, v: O + u * d + v * n  # noqa: E731
    # Where the wing's outer south wall (v = -4.5) meets y = 0, and its north wall (v = 2) y = 6.5.
    s0 = wing(0, -4.5)
    P1 = s0 + (-s0[1] / d[1]) * d
    q0 = wing(0, 2.0)
    Q = q0 + ((6.5 - q0[1]) / d[1]) * d
    return dict(d=d, n=n, O=O, wing=wing, P1=P1, Q=Q, P2=wing(WING_LEN, -4.5), P3=wing(WING_LEN, 2.0))


def floor_plan() -> FloorPlan:
    """Rooms and corridor of ``floor`` as canonical polygons, and the walk's visits."""
    g = _floor_geometry()
    O, wing, P1, P2, P3, Q = g["O"], g["wing"], g["P1"], g["P2"], g["P3"], g["Q"]
    box = lambda x0, y0, x1, y1: np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)  # noqa: E731
    regions = {
        "corridor": np.array([[0, 4.5], O, wing(WING_LEN, 0), P3, Q, [0, 6.5]], dtype=float),
        "room1": box(0, 0, 4, 4.5), "room2": box(4, 0, 8, 4.5), "room3": box(8, 0, 12, 4.5),
        "room4": box(0, 6.5, 5.5, 11.5), "room5": box(5.5, 6.5, Q[0], 11.5),
        "room6": np.array([[12, 0], P1, wing(5.5, -4.5), wing(5.5, 0), O], dtype=float),
        "room7": np.array([wing(5.5, -4.5), P2, wing(WING_LEN, 0), wing(5.5, 0)], dtype=float),
    }
    hinge = wing(0, 1.0)
    hinge = hinge + ((5.5 - hinge[1]) / g["d"][1]) * g["d"]  # both corridors' centre lines meet here
    main = lambda x, side, depth: (  # noqa: E731
        np.array([x, 5.5]), np.array([x, 4.5 if side < 0 else 6.5]), np.array([x, 5.5 + side * (1.0 + depth)]))
    wvis = lambda u: (wing(u, 1.0), wing(u, 0.0), wing(u, -2.25))  # noqa: E731
    visits = (
        Visit("room1", *main(1.4, -1, 2.25)), Visit("room4", *main(2.75, +1, 2.5)),
        Visit("room2", *main(6.0, -1, 2.25)), Visit("room5", *main(8.5, +1, 2.5)),
        Visit("room3", *main(10.6, -1, 2.25)),
        Visit("room6", *wvis(2.8)), Visit("room7", *wvis(8.7)),
    )
    return FloorPlan(regions, np.array([0.9, 5.5]), visits, wing(WING_LEN - 1.0, 1.0), {5: (hinge,)})


def floor(seed: int = 0) -> Scene:
    """A building floor, 24.3 x 14.4 x 2.7 m: a corridor with seven rooms behind door
    openings (1 m wide, 2.1 m high); rooms 1-5 in the main wing, rooms 6-7 in an east wing
    turned 42 degrees (room 6 fills the wedge between the wings); furniture in every room
    (desks, chairs, shelves, cabinets, boxes) aligned with its walls, and two cabinets in
    the corridor. Walls between rooms are 12 cm boxes with lintels over the doors, so the
    SDF stays the exact minimum of the outer walls' and the solids' distances. Horizontal
    directions {0, 90, 42, 132} degrees. ``floor_plan()`` names the rooms' regions."""
    L = _Layout(np.random.default_rng([seed, 15]), 0.12)
    g = _floor_geometry()
    O, wing, P1, P2, P3, Q, h = g["O"], g["wing"], g["P1"], g["P2"], g["P3"], g["Q"], 2.7
    wy = float(np.arctan2(g["d"][1], g["d"][0]))
    poly = np.array([[0, 0], P1, P2, P3, Q, [Q[0], 11.5], [0, 11.5]], dtype=float)
    plan = floor_plan()
    door = {v.room: v.door for v in plan.visits}
    # Walls (boxes on the rooms' side of the corridor lines).
    _wall(L, (0, 4.5), O, h, [door[r][0] for r in ("room1", "room2", "room3")], side=-1)
    _wall(L, (0, 6.5), Q, h, [door[r][0] for r in ("room4", "room5")], side=+1)
    _wall(L, O, wing(WING_LEN, 0), h, [float((door[r] - O) @ g["d"]) for r in ("room6", "room7")], side=-1)
    for x in (4.0, 8.0):
        L.box(x, 4.5 / 2 - 0.06, _T_WALL, 4.5 - 0.12, h, kind="wall")
    L.box(12.0 + _T_WALL / 2, 2.25, _T_WALL, 4.5, h, kind="wall")  # room 3 | room 6 (also fills the corner at O)
    L.box(5.5, 9.0 + 0.06, _T_WALL, 5.0 - 0.12, h, kind="wall")  # room 4 | room 5
    c = wing(5.5, -2.25 - 0.06)
    L.local_box(c, wy, 0, 0, _T_WALL, 4.5 - 0.12, h, kind="wall")  # room 6 | room 7
    j = L.j
    # Rooms 1-3 (south; local frame: u along -x, v along -y from the corridor wall).
    for k, (x1, du) in enumerate(((4.0, 2.6), (8.0, 2.0), (12.0, 1.4))):
        F = _Frame2D((x1, 4.5), np.pi)
        far = 0.9 if du > 2.0 else 3.1  # the side away from the door
        p = F(far + j(), 3.95)
        L.table(*p, 1.3, 0.7, 0.74, np.pi)
        L.chair(*F(far + j(), 3.35), np.pi)  # facing the desk, its back towards the door
        if k != 1:  # a shelf on the back wall, or a cabinet on the side wall
            L.shelf(*F(4.0 - far + j(0.5), 4.5 - 0.175), 1.0, 0.35, 1.9, 5, 0.0)
        else:
            L.box(*F(0.42, 3.6 + j()), 0.6, 0.9, 0.9, kind="cabinet")
        L.box(*F(far + j(0.5), 0.55), 0.5, 0.5, 0.5 + 0.1 * k)  # in the front corner away from the door
    # Rooms 4-5 (north; local frame = canonical, origin at the corridor wall).
    F4 = _Frame2D((0.0, 6.5), 0.0)
    L.table(*F4(1.6 + j(), 3.6 + j()), 1.6, 0.9, 0.74)
    L.chair(*F4(1.2 + j(0.5), 2.85), 0.0)
    L.chair(*F4(2.0 + j(0.5), 4.3), np.pi)
    L.shelf(*F4(5.5 - 0.06 - 0.175, 2.4 + j()), 1.2, 0.35, 2.0, 5, np.pi / 2)
    L.box(*F4(0.45, 0.5 + 0.12 + j(0.5)), 0.7, 0.7, 0.6)
    F5 = _Frame2D((5.5, 6.5), 0.0)
    L.table(*F5(4.4 + j(), 3.7 + j()), 0.8, 1.6, 0.74)
    L.chair(*F5(3.75, 3.7 + j(0.5)), -np.pi / 2)
    L.box(*F5(0.06 + 0.3 + 0.12, 3.2 + j()), 0.6, 1.2, 1.0, kind="cabinet")  # cabinet against the room 4 wall
    sb = F5(0.8 + j(), 4.8)
    L.box(*sb, 0.9, 0.4, 0.75, kind="cabinet")  # sideboard on the north wall
    L.box(*sb, 0.4, 0.3, 0.3, z0=0.75)  # something on it
    # Rooms 6-7 (the wing; local u along the wing, v into the room from the corridor wall).
    Fw = _Frame2D(O, wy)  # wing frame: canonical = O + u d + v n
    L.table(*Fw(4.3 + j(), -3.65), 1.4, 0.7, 0.74, wy)
    L.chair(*Fw(4.3 + j(0.5), -3.05), wy + np.pi)
    L.box(*Fw(0.8 + j(0.5), -0.12 - 0.225), 0.8, 0.45, 1.1, yaw=wy, kind="cabinet")  # cabinet by the corridor wall
    L.box(12.0 + 0.12 + 0.3, 0.6 + j(), 0.6, 0.6, 0.7)  # in the wedge, against the room 3 wall
    L.box(12.0 + 0.12 + 0.3, 0.6, 0.4, 0.4, 0.35, z0=0.7)
    L.table(*Fw(10.2 + j(), -3.3 + j()), 1.6, 0.9, 0.74, wy)
    L.chair(*Fw(10.2 + j(0.5), -2.55), wy + np.pi)
    L.chair(*Fw(9.9 + j(0.5), -4.05 + 0.0), wy)
    L.shelf(*Fw(WING_LEN - 0.175, -3.4 + j()), 1.2, 0.35, 2.0, 4, wy + np.pi / 2)
    L.box(*Fw(6.4 + j(0.5), -4.275), 0.8, 0.45, 0.8, yaw=wy)
    # Corridor: two cabinets against walls, away from the doors.
    L.box(4.0 + j(), 6.5 - 0.2, 0.8, 0.4, 1.0, kind="cabinet")
    L.local_box(wing(5.8 + j(), 2.0), wy, 0, -0.2, 0.8, 0.4, 1.0, kind="cabinet")
    return L.scene(poly, h, "floor")


BUILDINGS: dict[str, Callable[[int], Scene]] = {
    "manhattan": manhattan,
    "atlanta": atlanta,
    "stairs": stairs,
    "office": office,
    "floor": floor,
}

# Buildings walked room by room (``trajectory.make_walk``): name -> its plan (canonical frame).
PLANS: dict[str, Callable[[], FloorPlan]] = {"floor": floor_plan}


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
