"""Triangle meshes of a scene's surfaces, for visualisation (canonical frame)."""

from __future__ import annotations

import numpy as np

from .primitives import Boxes, Room, _cross2


def ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangulate a simple counter-clockwise polygon (M, 2) -> (M - 2, 3) vertex indices."""
    idx = list(range(len(poly)))
    tris = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(poly) ** 2:
        guard += 1
        for i in range(len(idx)):
            a, b, c = idx[i - 1], idx[i], idx[(i + 1) % len(idx)]
            pa, pb, pc = poly[a], poly[b], poly[c]
            if _cross2(pb - pa, pc - pb) <= 0:  # reflex corner: not an ear
                continue
            others = [poly[j] for j in idx if j not in (a, b, c)]
            if any(
                _cross2(pb - pa, p - pa) > 0 and _cross2(pc - pb, p - pb) > 0 and _cross2(pa - pc, p - pc) > 0
                for p in others
            ):
                continue
            tris.append((a, b, c))
            idx.pop(i)
            break
    tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def _box_mesh(center: np.ndarray, R: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    v = center + (s * half) @ R.T
    f = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )
    return v, f


def scene_mesh_canon(room: Room, boxes: Boxes):
    """Floor, ceiling and walls (faces towards the room's interior) plus every box."""
    import trimesh

    poly, h = room.polygon, room.height
    m = len(poly)
    tri = ear_clip(poly)
    verts = [np.c_[poly, np.zeros(m)], np.c_[poly, np.full(m, h)]]
    faces = [tri, tri[:, ::-1] + m]
    k = np.arange(m)
    k1 = (k + 1) % m
    faces.append(np.c_[k, k1 + m, k1])
    faces.append(np.c_[k, k + m, k1 + m])
    n = 2 * m
    for b in range(len(boxes)):
        v, f = _box_mesh(boxes.centers[b], boxes.rotations[b], boxes.halves[b])
        verts.append(v)
        faces.append(f + n)
        n += len(v)
    return trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
