"""Rooms extruded from real room layouts, rendered along a trajectory ("layout" reader).

Sources (under $AISDF_DATA):

* AtlantaNet / MatterportLayout corner files (``label_cor/*.txt``): ``u v`` per line in a
  1024x512 equirectangular panorama, ceiling and floor corner alternating. Floor corner:
  lon = (u/1024 - 0.5) 2 pi, lat = (0.5 - v/512) pi, r = h_cam / tan(-lat),
  (x, y) = r (sin lon, cos lon); the ceiling is h_cam + mean(r tan(lat_ceiling)) above
  the floor. The camera height is unknown; ``camera_height=1.6`` (the usual guess) sets
  the scale. The panorama is the one waypoint.
* ZInD ``zind_data.json``: ``room`` names a complete room (default: the one with the
  most layout vertices); its primary panorama's ``layout_complete`` polygon, placed in
  the floor-plan frame (rotation, scale, translation) and scaled to metres with
  ``scale_meters_per_coordinate``; ceiling from ``ceiling_height``, camera height 1 local
  unit. Every panorama of the room is a waypoint. (ZInD's 2D axes are taken as a
  right-handed x, y; if they are mirrored the room is mirrored, the geometry is the same.)

The room: floor at z = 0, walls, flat ceiling, world z up; a closed mesh whose normals
face into the room (free space is the positive side: ``MeshScene.distance`` is a proper
room SDF). The trajectory: at each waypoint a full turn on a small circle, then a straight
walk to the nearest waypoint not yet visited that such a walk can reach keeping
``clearance`` from the walls (waypoints no walk reaches are left out); the camera
at the panorama's height, pitched ``pitch_deg`` (negative = down).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry import intrinsics
from .mesh import MeshRenderDataset

DEFAULT_K = intrinsics(525.0, 525.0, 319.5, 239.5)


# --- layouts -----------------------------------------------------------------------------


def atlanta_corners(path, camera_height: float = 1.6) -> dict:
    """AtlantaNet corner file -> {polygon (N, 2) m, ceiling, camera_height, waypoints}."""
    uv = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if len(uv) % 2 or len(uv) < 6:
        raise ValueError(f"{path}: expected ceiling/floor corner pairs, got {len(uv)} lines")
    lon = (uv[:, 0] / 1024.0 - 0.5) * 2 * np.pi
    lat = (0.5 - uv[:, 1] / 512.0) * np.pi
    pairs = np.arange(0, len(uv), 2)
    ceil_i = np.where(uv[pairs, 1] < uv[pairs + 1, 1], pairs, pairs + 1)
    floor_i = np.where(uv[pairs, 1] < uv[pairs + 1, 1], pairs + 1, pairs)
    r = camera_height / np.tan(-lat[floor_i])
    poly = np.stack([r * np.sin(lon[floor_i]), r * np.cos(lon[floor_i])], axis=1)
    ceiling = camera_height + float(np.mean(r * np.tan(lat[ceil_i])))
    return {"polygon": poly, "ceiling": ceiling, "camera_height": camera_height, "waypoints": np.zeros((1, 2))}


def zind_room(path, room: str | None = None, floor: str | None = None) -> dict:
    """ZInD ``zind_data.json`` -> {polygon, ceiling, camera_height, waypoints} in metres."""
    data = json.loads(Path(path).read_text())
    floors = data["merger"]
    floor = floor or sorted(floors)[0]
    rooms = floors[floor]
    panos = {r: [p for part in rv.values() for p in part.values()] for r, rv in rooms.items()}
    if room is None:
        room = max(panos, key=lambda r: max(len(p["layout_complete"]["vertices"]) for p in panos[r]))
    primary = next((p for p in panos[room] if p["is_primary"]), panos[room][0])
    m_per = data["scale_meters_per_coordinate"][floor]

    def to_plan(p, xy):
        t = p["floor_plan_transformation"]
        a = np.deg2rad(t["rotation"])
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return ((np.asarray(xy, dtype=np.float64) @ R.T) * t["scale"] + t["translation"]) * m_per

    unit = primary["floor_plan_transformation"]["scale"] * m_per  # metres per local unit
    poly = to_plan(primary, primary["layout_complete"]["vertices"])
    waypoints = np.array([to_plan(p, [0.0, 0.0]) for p in panos[room]])
    camera_height = unit * float(primary.get("camera_height", 1.0))
    return {
        "polygon": poly,
        "ceiling": unit * float(primary["ceiling_height"]),
        "camera_height": camera_height,
        "waypoints": waypoints,
        "room": room,
    }


# --- geometry ----------------------------------------------------------------------------


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    area2 = np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)
    return poly if area2 > 0 else poly[::-1].copy()


def triangulate_polygon(poly: np.ndarray) -> np.ndarray:
    """Ear clipping of a simple counter-clockwise polygon (N, 2) -> (N - 2, 3) indices."""
    idx = list(range(len(poly)))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3:
        n = len(idx)
        for k in range(n):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % n]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or degenerate corner
            others = [poly[j] for j in idx if j not in (i0, i1, i2)]
            if any(cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0 for p in others):
                continue
            tris.append((i0, i1, i2))
            idx.pop(k)
            break
        else:
            guard += 1
            if guard > 1:
                raise ValueError("polygon is not simple (ear clipping found no ear)")
            idx.pop(
                int(np.argmin([abs(cross(poly[idx[k - 1]], poly[idx[k]], poly[idx[(k + 1) % n]])) for k in range(n)]))
            )
    tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def extrude_room(polygon: np.ndarray, ceiling: float, floor: float = 0.0):
    """Floor polygon (N, 2) -> closed trimesh room (floor, walls, ceiling) with normals
    facing into the room."""
    import trimesh

    poly = _ccw(np.asarray(polygon, dtype=np.float64))
    n = len(poly)
    V = np.concatenate([np.c_[poly, np.full(n, floor)], np.c_[poly, np.full(n, ceiling)]])
    t = triangulate_polygon(poly)
    floor_f = t  # CCW seen from above: normal +z, into the room
    ceil_f = t[:, ::-1] + n  # normal -z
    i = np.arange(n)
    j = (i + 1) % n
    # CCW polygon: the room is left of p_i -> p_j; these windings give normals pointing left.
    walls = np.concatenate([np.stack([i, j + n, j], 1), np.stack([i, i + n, j + n], 1)])
    return trimesh.Trimesh(V, np.concatenate([floor_f, ceil_f, walls]), process=False)


def _seg_dist(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance from points (M, 2) to the polygon's boundary."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("mnk,nk->mn", p[:, None] - a, ab) / np.einsum("nk,nk->n", ab, ab), 0, 1)
    return np.linalg.norm(p[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)


def _inside(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    x, y = p[:, 0:1], p[:, 1:2]
    a, b = poly, np.roll(poly, -1, axis=0)
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (crosses & (x < xint)).sum(axis=1) % 2 == 1


def room_trajectory(
    polygon: np.ndarray,
    waypoints: np.ndarray,
    height: float,
    n_frames: int | None = None,
    step: float = 0.03,
    pitch_deg: float = -10.0,
    radius: float = 0.3,
    clearance: float = 0.25,
) -> np.ndarray:
    """Camera-to-world poses (n_frames, 4, 4): a turn at each reachable waypoint, straight
    walks between them; see the module docstring. Poses are evenly spaced in
    "effort" = metres walked + 0.5 x radians turned; ``n_frames`` defaults to effort / step
    (3 cm or 3.4 degrees per frame at 30 fps: 0.9 m/s, 100 deg/s)."""
    poly = _ccw(np.asarray(polygon, dtype=np.float64))
    clear = lambda q: _inside(q, poly).all() and (_seg_dist(q, poly) >= clearance).all()  # noqa: E731
    todo = [w for w in np.asarray(waypoints, dtype=np.float64).reshape(-1, 2) if clear(w[None])]
    route = todo[:1]
    todo = todo[1:]
    while todo:  # greedy tour: the nearest waypoint reachable by a clear straight walk
        todo.sort(key=lambda w: np.linalg.norm(w - route[-1]))
        nxt = next(
            (k for k, w in enumerate(todo) if clear(route[-1] + np.linspace(0, 1, 50)[:, None] * (w - route[-1]))), None
        )
        if nxt is None:
            break
        route.append(todo.pop(nxt))
    keys = []  # (x, y, yaw)
    yaw = 0.0
    for w in route:
        r = min(radius, 0.5 * (_seg_dist(w[None], poly)[0] - clearance))
        for th in np.linspace(0, 2 * np.pi, 37):
            keys.append((w[0] + r * np.cos(yaw + th), w[1] + r * np.sin(yaw + th), yaw + th))
        yaw += 2 * np.pi
    if not keys:
        raise ValueError("no waypoint lies inside the room with the required clearance")
    keys = np.array(keys)
    effort = np.concatenate(
        [[0], np.cumsum(np.linalg.norm(np.diff(keys[:, :2], axis=0), axis=1) + 0.5 * np.abs(np.diff(keys[:, 2])))]
    )
    n_frames = n_frames or int(np.ceil(effort[-1] / step)) + 1
    s = np.linspace(0, effort[-1], n_frames)
    x, y, yw = (np.interp(s, effort, keys[:, k]) for k in range(3))
    pitch = np.deg2rad(pitch_deg)
    fwd = np.stack([np.cos(yw) * np.cos(pitch), np.sin(yw) * np.cos(pitch), np.full_like(yw, np.sin(pitch))], 1)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = right, down, fwd
    T[:, :3, 3] = np.stack([x, y, np.full_like(x, height)], 1)
    return T


# --- the reader --------------------------------------------------------------------------


def _load_layout(path: Path, room: str | None, camera_height: float) -> tuple[dict, str]:
    if path.is_dir():
        js = sorted(path.rglob("zind_data.json"))
        if js:
            path = js[0]
        else:
            cors = sorted(path.rglob("label_cor/*.txt"))
            if room is not None:
                cors = [c for c in cors if c.stem.startswith(room)]
            if not cors:
                raise FileNotFoundError(f"{path}: no zind_data.json or label_cor/*.txt (room={room!r})")
            path = max(cors, key=lambda c: (len(c.read_text().split()), c.name))  # most corners
    if path.suffix == ".json":
        lay = zind_room(path, room)
        return lay, lay["room"]
    return atlanta_corners(path, camera_height), path.stem.split("_")[0]


class LayoutRoomDataset(MeshRenderDataset):
    """A room extruded from a real layout, rendered along ``room_trajectory``."""

    kind = "layout"

    def __init__(
        self,
        path,
        room: str | None = None,
        camera_height: float = 1.6,
        n_frames: int | None = None,
        pitch_deg: float = -10.0,
        K=None,
        size: tuple[int, int] = (480, 640),
        **kw,
    ):
        self.layout, room_name = _load_layout(Path(path), room, camera_height)
        lay = self.layout
        mesh = extrude_room(lay["polygon"], lay["ceiling"])
        traj = room_trajectory(
            lay["polygon"], lay["waypoints"], lay["camera_height"], n_frames=n_frames, pitch_deg=pitch_deg
        )
        super().__init__(
            None, trajectory=traj, K=DEFAULT_K if K is None else K, size=size, mesh=mesh, name=room_name, **kw
        )

    @classmethod
    def sniff(cls, path: Path) -> bool:
        if path.is_file():
            return path.name == "zind_data.json" or path.parent.name == "label_cor"
        return any(path.rglob("zind_data.json")) or any(path.rglob("label_cor/*.txt"))
