"""The Atlanta layout prior: flat surfaces predicted where no camera has looked.

An indoor scene's floor, ceiling and walls continue beyond what a keyframe framed. The map
knows their planes: the global surfel map's rectangles lie on Atlanta planes (the floor and
the ceiling orthogonal to the vertical, the walls on the horizontal directions). This module
groups the surfels into planes, extends each plane beyond its observed extent and keeps the
extension only in space no keyframe observed (``ObservedGrid``): observed space, free or
surface, always wins over a prediction, so a wall's plane carried across a doorway that was
seen open, or a cabinet's front carried across the room, leaves nothing there. What is left
is a set of predicted surface points (a lattice on each plane), which the served answer
treats like measured points: the distance to the nearest of them caps the answer
(:func:`aisdf.query.answer.served_answer`).

Which planes (each holding at least ``min_area`` of surfels):

* horizontal: only the floor (the lowest plane facing one way along the vertical) and the
  ceiling (the highest facing the other way). A table's top is furniture, not layout: never
  carried on.
* vertical: every plane. Walls run between the floor and the ceiling where those are known.

Where a plane's lattice point is predicted: within ``reach`` metres (in the plane) of its
surfels and inside the map's box grown by ``margin``; in unobserved space, joined to the
surfels through unobserved lattice points (or ones within ``bridge`` of a surfel, where the
surface's own voxels are observed); not past a line where another surface meets the plane
(another surfel within ``meet_tol``, or, in a second pass, another plane's prediction: the
floor ends at a wall's predicted stretch too); and not where space ``behind`` it was observed
(seen over a cabinet's top or past a shelf's side, the plane is furniture's face, not a
wall). The prediction is only as good as the assumption that the room is an Atlanta room;
``reach`` bounds how far one wrong plane can reach.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .surfel_types import Surfels


@dataclass(frozen=True)
class LayoutConfig:
    spacing: float = 0.05  # m between predicted points on a plane
    min_area: float = 0.1  # m^2 of surfels for a plane to count (small ones too: a wall seen in one corner still bounds the room)
    plane_tol: float = 0.05  # m: surfels whose offsets along one normal are this close share a plane
    reach: float = 1.5  # m beyond a plane's surfels, in the plane
    margin: float = 0.3  # m beyond the map's box
    meet_tol: float = 0.05  # m: another surfel this close to a plane meets it there
    bridge: float = 0.2  # m: observed lattice points this close to a surfel still join the extension to it
    max_cells: int = 20_000_000  # a plane's lattice beyond this is not predicted (a bound on time and memory)
    behind: tuple = (0.3, 0.45, 0.6)  # m behind a predicted point that must be unobserved (beyond observed's margin)
    max_points: int = 2_000_000  # a bound on the prediction's size (beyond it, evenly thinned)


@dataclass(eq=False)
class Plane:
    normal: np.ndarray  # (3,) unit, towards free space
    offset: float  # normal . x on the plane
    direction: int  # surfel direction (-1: horizontal plane)
    members: np.ndarray  # surfel indices
    area: float


def planes(s: Surfels, tol: float) -> list[Plane]:
    """Surfels grouped into planes: same direction, normals the same way, offsets along the
    normal within ``tol`` of their neighbours (single linkage, in offset order)."""
    out: list[Plane] = []
    if s is None or not len(s):
        return out
    area = s.extent[:, 0] * s.extent[:, 1]
    for d in np.unique(s.direction):
        for side in (1, -1):
            idx = np.flatnonzero(s.direction == d)
            if not len(idx):
                continue
            ref = s.normal[idx[np.argmax(area[idx])]]
            idx = idx[side * (s.normal[idx] @ ref) > 0]
            if not len(idx):
                continue
            n = side * ref
            off = np.einsum("ij,j->i", s.center[idx], n)
            order = np.argsort(off)
            idx, off = idx[order], off[order]
            cuts = np.flatnonzero(np.diff(off) > tol) + 1
            for grp, o in zip(np.split(idx, cuts), np.split(off, cuts)):
                a = area[grp]
                normal = np.sum(s.normal[grp] * a[:, None], 0)
                normal /= np.linalg.norm(normal)
                out.append(Plane(normal, float(np.average(o, weights=a)), int(d), grp, float(a.sum())))
    return out


def infer_vertical(s: Surfels) -> np.ndarray | None:
    """The Atlanta vertical's axis from the surfels on horizontal planes (``direction`` -1),
    their normals (up or down) area-weighted and turned one way; None when there are none."""
    h = np.flatnonzero(s.direction < 0)
    if not len(h):
        return None
    n, a = s.normal[h], (s.extent[h, 0] * s.extent[h, 1])[:, None]
    ref = n[np.argmax(a)]
    v = np.sum(np.where((n @ ref)[:, None] < 0, -n, n) * a, 0)
    return v / np.linalg.norm(v)


def _basis(n: np.ndarray, vertical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-plane unit axes: for a wall, along the floor and up; else any two."""
    u = np.cross(vertical, n)
    if np.linalg.norm(u) < 1e-6:  # a horizontal plane
        a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(n, a)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return u, v / np.linalg.norm(v)


def predict(surfels: Surfels | None, observed, bounds: np.ndarray | None, vertical: np.ndarray | None = None,
            cfg: LayoutConfig = LayoutConfig()) -> np.ndarray:
    """(P, 3) predicted surface points: the layout planes' lattices beyond what was observed.
    ``observed``: an ``ObservedGrid`` (None: nothing is predicted, as nothing says where the
    camera has looked); ``bounds``: (2, 3) the map's box; ``vertical``: the Atlanta vertical
    (default: the axis of the surfels facing along it, :func:`infer_vertical`; its sign does
    not matter: the floor and the ceiling are the two extreme planes either way)."""
    if surfels is None or not len(surfels) or observed is None:
        return np.zeros((0, 3))
    up = infer_vertical(surfels) if vertical is None else np.asarray(vertical, np.float64)
    if up is None:
        return np.zeros((0, 3))
    up = up / np.linalg.norm(up)
    box = np.asarray(bounds if bounds is not None else observed.bounds, np.float64).reshape(2, 3)
    lo, hi = box[0] - cfg.margin, box[1] + cfg.margin
    ps = [p for p in planes(surfels, cfg.plane_tol) if p.area >= cfg.min_area]
    horiz = [p for p in ps if p.direction < 0 or abs(p.normal @ up) > 0.9]
    walls = [p for p in ps if p not in horiz]
    floor = ceiling = None
    ups = [p for p in horiz if p.normal @ up > 0]
    downs = [p for p in horiz if p.normal @ up < 0]
    if ups:
        h = np.array([p.offset * np.sign(p.normal @ up) for p in ups])
        floor = ups[int(np.argmin(h))]
    if downs:
        h = np.array([-p.offset for p in downs])  # the height of a down-facing plane: -offset
        ceiling = downs[int(np.argmax(h))]
    z_floor = None if floor is None else floor.offset
    z_ceil = None if ceiling is None else -ceiling.offset
    keep = [p for p in (floor, ceiling) if p is not None] + walls
    samples, owner = _surfel_samples(surfels, cfg.spacing)

    def lattices(predicted: list[np.ndarray] | None) -> list[np.ndarray]:
        out = []
        for i, p in enumerate(keep):
            mine = np.zeros(len(surfels), bool)
            mine[p.members] = True
            other = samples[~mine[owner]]
            if predicted is not None:  # the other planes' predictions meet this one too
                other = np.concatenate([other] + [q for j, q in enumerate(predicted) if j != i])
            other = other[np.abs(other @ p.normal - p.offset) <= cfg.meet_tol]
            # walls run from the floor to the ceiling, where those are known
            heights = (z_floor, z_ceil) if p in walls else (None, None)
            q = _lattice(surfels, p, up, lo, hi, observed, other, heights, cfg)
            # Nothing was seen behind a wall: where space behind the plane was observed (over
            # a cabinet's top, past a shelf's side), the plane is furniture's face, not layout.
            for depth in cfg.behind:
                q = q[~observed.contains(q - depth * p.normal)]
            out.append(q)
        return out

    # Twice: the second time a plane also ends where another plane's prediction meets it (the
    # floor at a wall's predicted stretch: beyond it lies the next room, not this one).
    pts = lattices(lattices(None))
    out = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(out) > cfg.max_points:
        out = out[np.linspace(0, len(out) - 1, cfg.max_points).astype(np.int64)]
    return out


def _surfel_samples(s: Surfels, h: float) -> tuple[np.ndarray, np.ndarray]:
    """(points (M, 3) on the surfels' rectangles, ``h`` apart; the surfel of each (M,))."""
    pts, own = [], []
    for i in range(len(s)):
        n1, n2 = (max(2, int(np.ceil(e / h)) + 1) for e in s.extent[i])
        a = np.linspace(-0.5, 0.5, n1) * s.extent[i, 0]
        b = np.linspace(-0.5, 0.5, n2) * s.extent[i, 1]
        A, B = np.meshgrid(a, b, indexing="ij")
        pts.append(s.center[i] + A.reshape(-1, 1) * s.axis1[i] + B.reshape(-1, 1) * s.axis2[i])
        own.append(np.full(n1 * n2, i))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(own)


def _lattice(s: Surfels, p: Plane, up: np.ndarray, lo: np.ndarray, hi: np.ndarray, observed,
             other: np.ndarray, heights: tuple, cfg: LayoutConfig) -> np.ndarray:
    """Plane ``p``'s predicted points: the lattice points that carry its surfels on into
    unobserved space: within ``reach`` of its surfels (in the plane), inside the box [lo, hi]
    and the ``heights`` (along ``up``; None: unbounded), not observed, and joined to the
    surfels through lattice points that are unobserved (or within ``bridge`` of a surfel,
    where the observed voxels of the surface itself lie) and not where another surface meets
    the plane (``other``: points of other surfels, or predictions, on it). A plane stops where
    it meets observed space or another surface, and what lies beyond is not predicted."""
    u, v = _basis(p.normal, up)
    corners = s.corners()[p.members].reshape(-1, 3)
    cu, cv = corners @ u, corners @ v
    # the box's extent in the plane's coordinates (its corners projected)
    bc = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    bu, bv = bc @ u, bc @ v
    u0, u1 = max(cu.min() - cfg.reach, bu.min()), min(cu.max() + cfg.reach, bu.max())
    v0, v1 = max(cv.min() - cfg.reach, bv.min()), min(cv.max() + cfg.reach, bv.max())
    h = cfg.spacing
    nu, nv = int(np.ceil((u1 - u0) / h)) + 1, int(np.ceil((v1 - v0) / h)) + 1
    if u1 <= u0 or v1 <= v0 or nu * nv > cfg.max_cells:
        return np.zeros((0, 3))
    # rasterise each surfel rectangle (its corners' box in (u, v): surfels on Atlanta planes are
    # axis-aligned in a wall's (along, up) coordinates; a floor's may be turned, and its box then
    # covers a little more)
    covered = np.zeros((nu, nv), bool)
    ru, rv = s.corners()[p.members] @ u, s.corners()[p.members] @ v
    iu0 = np.clip(np.floor((ru.min(1) - u0) / h).astype(int), 0, nu - 1)
    iu1 = np.clip(np.ceil((ru.max(1) - u0) / h).astype(int), 0, nu - 1)
    iv0 = np.clip(np.floor((rv.min(1) - v0) / h).astype(int), 0, nv - 1)
    iv1 = np.clip(np.ceil((rv.max(1) - v0) / h).astype(int), 0, nv - 1)
    for a, b, c, d in zip(iu0, iu1, iv0, iv1):
        covered[a:b + 1, c:d + 1] = True
    dist = ndimage.distance_transform_edt(~covered, sampling=h)
    gu, gv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    q = (p.offset * p.normal)[None] + (u0 + gu.ravel() * h)[:, None] * u[None] + (
        v0 + gv.ravel() * h)[:, None] * v[None]
    seen = observed.contains(q).reshape(nu, nv)
    inside = np.all((q >= lo) & (q <= hi), axis=1)
    hq = q @ up
    if heights[0] is not None:
        inside &= hq >= heights[0] - h
    if heights[1] is not None:
        inside &= hq <= heights[1] + h
    inside = inside.reshape(nu, nv)
    # Where another surface meets the plane (a cabinet's top at its front's edge, the next wall
    # at a corner, the floor at a wall's foot) the plane ends: those cells block.
    met = np.zeros((nu, nv), bool)
    if len(other):
        iu = np.round((other @ u - u0) / h).astype(np.int64)
        iv = np.round((other @ v - v0) / h).astype(np.int64)
        ok = (iu >= 0) & (iu < nu) & (iv >= 0) & (iv < nv)
        met[iu[ok], iv[ok]] = True
        met = ndimage.binary_dilation(met)
    # The observed cells by the surfels' edges bridge to the unobserved space beyond, but not
    # around the end of a line where another surface meets the plane.
    bridge = dist <= cfg.bridge
    if met.any():
        bridge &= ndimage.distance_transform_edt(~met, sampling=h) > cfg.bridge
    passable = inside & (dist <= cfg.reach) & (covered | ~seen | bridge) & ~met
    lab, _ = ndimage.label(passable)
    joined = np.isin(lab, np.unique(lab[covered & passable])) & (lab > 0)
    return q[(joined & ~seen).ravel()]
