"""A procedural indoor scene with exact ground truth, in any world frame. Pure numpy.

The geometry is built in a canonical z-up frame (floor at z = 0) from a ``Room`` and
``Boxes`` (see primitives.py) and placed in the WORLD frame by the rigid transform
``T_W_canon``; every public method takes and returns world coordinates.

SDF exactness: free space is the room's interior minus the boxes, and the scene's SDF
is the minimum of the room's and the boxes' signed distances. For points in free space
that is the EXACT Euclidean distance to the nearest surface. For points inside a wall or
a solid it is minus the distance to that primitive's own surface (covered faces included:
inside a cabinet standing on the floor its bottom face counts), so its magnitude is a lower
bound on the true distance to free space, exact where no other solid, wall or floor
touches the nearest face.

Labels (``kinds``: one string per box, or None for an unlabelled scene): ``"wall"`` for the
building's own walls built from boxes (the floor's interior walls and the lintels over its
doors), else what the box belongs to (``"table"``, ``"chair"``, ``"shelf"``, ``"cabinet"``,
``"box"``, ``"stairs"``). The *layout* is what an Atlanta room layout holds: the room
prism's walls, floor and ceiling and the ``LAYOUT_KINDS`` boxes (walls). Everything else is
*furniture*, the clutter a layout must not flatten, the staircase included (a layout of
vertical walls between one floor and one ceiling has no place for its steps).
``furniture_distance`` is the signed distance to the furniture alone; ``nearest_kind`` names
the primitive whose surface is nearest. Labels change no geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry import invert, rotate, transform
from ..structure.surfel_types import Surfels
from .primitives import Boxes, Room
from .raycast import face_axes, raycast

LAYOUT_KINDS = frozenset({"wall"})  # box kinds that belong to the layout (with the room prism)
ROOM_KIND = "room"  # ``nearest_kind`` of the room prism (walls, floor, ceiling)
CHUNK = 32768  # points per vectorised block (bounds memory to ~B * CHUNK * 3 floats)
_Z = np.array([0.0, 0.0, 1.0])


def rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _chunks(n: int):
    for i in range(0, max(n, 1), CHUNK):
        yield slice(i, min(i + CHUNK, n))


@dataclass(frozen=True, eq=False, repr=False)
class Scene:
    """Room + solid boxes, placed in the world by ``T_W_canon`` (4x4)."""

    room: Room
    boxes: Boxes
    T_W_canon: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "scene"
    kinds: tuple[str, ...] | None = None  # one label per box (module docstring); None: unlabelled

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_W_canon", np.asarray(self.T_W_canon, dtype=np.float64))
        object.__setattr__(self, "T_canon_W", invert(self.T_W_canon))
        if self.kinds is not None:
            kinds = tuple(str(k) for k in self.kinds)
            if len(kinds) != len(self.boxes):
                raise ValueError(f"kinds: one label per box, got {len(kinds)} for {len(self.boxes)} boxes")
            object.__setattr__(self, "kinds", kinds)

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, {len(self.room.polygon)} walls, {len(self.boxes)} boxes)"

    def with_frame(self, T_W_canon: np.ndarray) -> "Scene":
        """The same scene placed in the world by another transform."""
        return replace(self, T_W_canon=T_W_canon)

    # -- frames ------------------------------------------------------------------------
    @property
    def up_W(self) -> np.ndarray:
        """(3,) unit world up vector (the canonical +z)."""
        return self.T_W_canon[:3, 2].copy()

    def to_canon(self, points_W: np.ndarray) -> np.ndarray:
        return transform(self.T_canon_W, np.asarray(points_W, dtype=np.float64).reshape(-1, 3))

    def to_world(self, points_canon: np.ndarray) -> np.ndarray:
        return transform(self.T_W_canon, np.asarray(points_canon, dtype=np.float64).reshape(-1, 3))

    # -- distance ----------------------------------------------------------------------
    def _sdf_arg(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Canonical points -> (sdf, nearest primitive: -1 room or box index, room gradient)."""
        room_sdf, room_grad = self.room.sdf_grad(p)
        d, arg = self.boxes.nearest(p, room_sdf)
        return d, arg, room_grad

    def sdf(self, points_W: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N,) signed distance in metres, positive in free space."""
        p = self.to_canon(points_W)
        out = np.empty(len(p))
        for s in _chunks(len(p)):
            out[s] = self._sdf_arg(p[s])[0]
        return out

    def sdf_and_gradient(self, points_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) and its analytic gradient (N, 3), world frame (unit length
        wherever the SDF is differentiable)."""
        p = self.to_canon(points_W)
        sdf, g = np.empty(len(p)), np.empty((len(p), 3))
        for s in _chunks(len(p)):
            ps = p[s]
            d, arg, gs = self._sdf_arg(ps)
            isbox = arg >= 0
            if isbox.any():
                gs[isbox] = self.boxes.grad(ps[isbox], arg[isbox])
            sdf[s], g[s] = d, gs
        return sdf, rotate(self.T_W_canon, g)

    def gradient(self, points_W: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) analytic SDF gradient in the world frame."""
        return self.sdf_and_gradient(points_W)[1]

    def raycast(self, origins_W: np.ndarray, dirs_W: np.ndarray, return_normals: bool = False):
        """Distance along unit ``dirs_W`` (N, 3) from ``origins_W`` (N, 3) or (3,) to the
        first surface, (N,), inf for none. Exact (analytic) for every ray.

        With ``return_normals``, also the unit surface normals (N, 3) in the world frame,
        oriented against the ray (zero where nothing is hit).
        """
        Rc, tc = self.T_canon_W[:3, :3], self.T_canon_W[:3, 3]
        d = Rc @ np.asarray(dirs_W, dtype=np.float64).reshape(-1, 3).T
        o = np.asarray(origins_W, dtype=np.float64)
        if o.ndim == 2 and len(o) and (o == o[0]).all():
            o = o[0]
        o = Rc @ o + tc if o.ndim == 1 else Rc @ o.T + tc[:, None]
        t, face = self.raycast_canon(o, d)
        if not return_normals:
            return t
        n = self.face_axes[face]
        n *= -np.sign(np.einsum("ni,in->n", n, d) + 1e-300)[:, None]
        n[face < 0] = 0.0
        return t, rotate(self.T_W_canon, n)

    def raycast_canon(self, o: np.ndarray, d: np.ndarray, candidates: list[np.ndarray] | None = None):
        """Canonical-frame raycast, component-wise rays (see raycast.py): origins (3, N) or
        one (3,), unit directions (3, N) -> t (N,), face id (N,) into ``face_axes``."""
        return raycast(self.room, self.boxes, o, d, candidates)

    @property
    def face_axes(self) -> np.ndarray:
        """(F, 3) canonical unit normal axis (unsigned) of each face id ``raycast_canon`` returns."""
        if "_face_axes" not in self.__dict__:
            object.__setattr__(self, "_face_axes", face_axes(self.room, self.boxes))
        return self.__dict__["_face_axes"]

    # -- labels: layout and furniture ---------------------------------------------------
    def _labelled(self) -> tuple[str, ...]:
        if self.kinds is None:
            raise ValueError(f"scene {self.name!r} has no labels (kinds): layout and furniture are unknown")
        return self.kinds

    @property
    def furniture_mask(self) -> np.ndarray:
        """(B,) bool: which boxes are furniture (not ``LAYOUT_KINDS``). ValueError if unlabelled."""
        return np.array([k not in LAYOUT_KINDS for k in self._labelled()], dtype=bool)

    @property
    def furniture(self) -> Boxes:
        """The furniture boxes alone (canonical frame)."""
        if "_furniture" not in self.__dict__:
            m = self.furniture_mask
            b = self.boxes
            object.__setattr__(self, "_furniture", Boxes(b.centers[m], b.rotations[m], b.halves[m]))
        return self.__dict__["_furniture"]

    def furniture_distance(self, points_W: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N,) exact signed distance (m) to the nearest furniture box,
        positive outside every one, negative inside one; +inf where the scene has no furniture."""
        p = self.to_canon(points_W)
        out = np.empty(len(p))
        for s in _chunks(len(p)):
            out[s] = self.furniture.nearest(p[s], np.full(s.stop - s.start, np.inf))[0]
        return out

    def nearest_kind(self, points_W: np.ndarray) -> np.ndarray:
        """(N,) label of the primitive the SDF takes each point's distance from (its nearest
        surface for points in free space): ``ROOM_KIND`` for the room prism, else its box's kind."""
        labels = np.array(self._labelled() + (ROOM_KIND,), dtype=object)
        p = self.to_canon(points_W)
        arg = np.empty(len(p), dtype=np.int64)
        for s in _chunks(len(p)):
            arg[s] = self._sdf_arg(p[s])[1]
        return labels[arg]  # -1 (the room) picks the last label

    def nearest_is_furniture(self, points_W: np.ndarray) -> np.ndarray:
        """(N,) bool: the primitive nearest each point is furniture (``nearest_kind``)."""
        k = self.nearest_kind(points_W)
        return np.array([x != ROOM_KIND and x not in LAYOUT_KINDS for x in k], dtype=bool)

    # -- extent and visualisation -------------------------------------------------------
    def _corners_canon(self) -> np.ndarray:
        poly, h = self.room.polygon, self.room.height
        pts = [np.c_[poly, np.zeros(len(poly))], np.c_[poly, np.full(len(poly), h)]]
        return np.concatenate(pts)

    def bounds(self) -> np.ndarray:
        """(2, 3) world axis-aligned bounding box [min, max] of the room."""
        c = self.to_world(self._corners_canon())
        return np.stack([c.min(axis=0), c.max(axis=0)])

    def mesh(self):
        """A ``trimesh.Trimesh`` of every surface in the world frame (not watertight)."""
        from .meshing import scene_mesh_canon

        m = scene_mesh_canon(self.room, self.boxes)
        m.apply_transform(self.T_W_canon)
        return m

    # -- structure ground truth ----------------------------------------------------------
    def _horizontal_normals_canon(self, include_solids: bool) -> np.ndarray:
        n = [np.c_[self.room.edge_normals, np.zeros(len(self.room.polygon))]]
        if include_solids:
            for R in self.boxes.rotations:
                for j in range(3):
                    if abs(R[2, j]) < 1e-6:
                        n.append(R[:, j][None])
        return np.concatenate(n)

    def atlanta_truth(self, include_solids: bool = True, tol_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """The true Atlanta frame: ``vertical_W`` (3,) and ``horizontal_W`` (M, 3).

        One unit horizontal direction per distinct vertical-plane normal (opposite normals
        merged, directions within ``tol_deg`` merged), walls first in polygon order, then
        the vertical faces of upright boxes if ``include_solids``. Representatives have
        their canonical azimuth in [0, 180) degrees.
        """
        ang = np.degrees(np.arctan2(*self._horizontal_normals_canon(include_solids)[:, 1::-1].T)) % 180.0
        keep: list[float] = []
        for a in ang:
            if all(min(abs(a - b), 180 - abs(a - b)) > tol_deg for b in keep):
                keep.append(float(a))
        r = np.radians(keep)
        hor = np.c_[np.cos(r), np.sin(r), np.zeros(len(r))]
        return self.up_W, rotate(self.T_W_canon, hor)

    def planes_truth(self) -> Surfels:
        """The true planar faces as world-frame rectangles (``Surfels``, keyframe = -1).

        Walls (one per polygon edge, full height), floor and ceiling (the polygon's
        bounding rectangle along the first wall; larger than the room if it is not a
        rectangle), and the faces of every box whose centre is not covered by another
        solid or a wall (e.g. box bottoms resting on the floor are left out). Normals
        point to free space. ``direction``: -1 vertical, k for ``atlanta_truth()[1][k]``,
        -2 for faces matching no Atlanta direction.
        """
        poly, h = self.room.polygon, self.room.height
        c, n, a1, a2, ext = [], [], [], [], []

        def add(ci, ni, u, v, e):
            c.append(ci), n.append(ni), a1.append(u), a2.append(v), ext.append(e)

        for k, nk in enumerate(self.room.edge_normals):
            p0, p1 = poly[k], poly[(k + 1) % len(poly)]
            u = np.r_[p1 - p0, 0.0]
            add(np.r_[(p0 + p1) / 2, h / 2], np.r_[nk, 0.0], u / np.linalg.norm(u), _Z, (np.linalg.norm(u), h))
        e0 = np.r_[poly[1] - poly[0], 0.0]
        u = e0 / np.linalg.norm(e0)
        v = np.cross(_Z, u)
        pu, pv = poly @ u[:2], poly @ v[:2]
        mid = (pu.min() + pu.max()) / 2 * u + (pv.min() + pv.max()) / 2 * v
        size = (pu.max() - pu.min(), pv.max() - pv.min())
        add(mid, _Z, u, v, size)
        add(mid + h * _Z, -_Z, u, v, size)
        bx = self.boxes
        for b in range(len(bx)):
            R, e = bx.rotations[b], bx.halves[b]
            for j in range(3):
                for s in (1.0, -1.0):
                    nj = s * R[:, j]
                    ci = bx.centers[b] + nj * e[j]
                    if self._sdf_arg(ci[None] + 1e-3 * nj)[0][0] <= 0:
                        continue
                    k1, k2 = (j + 1) % 3, (j + 2) % 3
                    add(ci, nj, R[:, k1], R[:, k2], (2 * e[k1], 2 * e[k2]))
        T = self.T_W_canon
        n_W = rotate(T, np.array(n))
        vert, hor = self.atlanta_truth()
        cosv = n_W @ vert
        cosh = np.abs(n_W @ hor.T)
        tol = np.cos(np.radians(1.0))
        direction = np.where(np.abs(cosv) > tol, -1, np.where(cosh.max(axis=1) > tol, cosh.argmax(axis=1), -2))
        return Surfels(
            center=transform(T, np.array(c)), normal=n_W, axis1=rotate(T, np.array(a1)),
            axis2=rotate(T, np.array(a2)), extent=np.array(ext), direction=direction,
            keyframe=np.full(len(c), -1),
        )
