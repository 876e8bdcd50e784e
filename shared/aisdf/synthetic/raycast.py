"""Exact analytic raycasting against a ``Room`` and ``Boxes`` in the canonical frame.

Rays are stored component-wise for speed: unit directions ``d`` (3, N), origins ``o``
(3, N) or one shared origin (3,). Results are the distance ``t`` (N,) along the ray to
the first surface with ``t > 0`` (inf for none) and the id of the face hit (N,): room
faces first (walls 0..M-1, floor M, ceiling M+1), then 3b + k for the faces of box b
normal to its axis k (see ``face_axes``).
"""

from __future__ import annotations

import numpy as np

from .primitives import Boxes, Room, polygon_contains


def face_axes(room: Room, boxes: Boxes) -> np.ndarray:
    """(M + 2 + 3B, 3) the unit normal axis of every face id (sign not fixed)."""
    return np.concatenate([room.face_axes, boxes.face_axes])


def room_raycast(room: Room, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays with the room's walls, floor and ceiling: (t, face id).

    Exact for any origin: from inside the prism the first boundary crossing is the exit
    (no in-polygon tests needed); rays from elsewhere check each face's extent.
    """
    n, h, poly = d.shape[1], room.height, room.polygon
    M = len(poly)
    shared = o.ndim == 1
    inside = room.contains(o[None])[0] if shared else room.contains(o.T)
    ox, oy, oz = o
    dx, dy, dz = d
    t, face = np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
    e = np.roll(poly, -1, axis=0) - poly
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(M):  # walls: o + t d = a + s e in 2D, 0 <= s <= 1
            aox, aoy = poly[k, 0] - ox, poly[k, 1] - oy
            inv = 1.0 / (dx * e[k, 1] - dy * e[k, 0])
            tk = (aox * e[k, 1] - aoy * e[k, 0]) * inv
            sk = (aox * dy - aoy * dx) * inv
            ok = (sk >= 0) & (sk <= 1) & (tk > 0) & (tk < t)
            if not (shared and inside):
                zk = oz + tk * dz
                ok &= inside | ((zk >= 0) & (zk <= h))
            t[ok], face[ok] = tk[ok], k
        for k, tz in ((M, -oz / dz), (M + 1, (h - oz) / dz)):  # floor, ceiling
            ok = (tz > 0) & (tz < t)
            if not (shared and inside):
                ox_, oy_ = np.broadcast_to(ox, (n,)), np.broadcast_to(oy, (n,))
                cand = np.flatnonzero(ok & ~np.broadcast_to(inside, (n,)))
                xy = np.c_[ox_[cand] + tz[cand] * dx[cand], oy_[cand] + tz[cand] * dy[cand]]
                ok[cand[~polygon_contains(xy, poly)]] = False
            t[ok], face[ok] = tz[ok], k
    return t, face


def box_candidates(boxes: Boxes, o: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
    """Per box, the indices of the rays that may hit it (bounding-sphere test)."""
    r = boxes.radii * (1 + 1e-9) + 1e-9
    out = []
    for j in range(len(boxes)):
        if o.ndim == 1:
            w = boxes.centers[j] - o
            b, ww = w @ d, w @ w
        else:
            w = boxes.centers[j][:, None] - o
            b, ww = np.einsum("in,in->n", w, d), np.einsum("in,in->n", w, w)
        out.append(np.flatnonzero((ww - b * b <= r[j] ** 2) & (b >= -r[j])))
    return out


def boxes_raycast(
    boxes: Boxes, o: np.ndarray, d: np.ndarray, t: np.ndarray, face: np.ndarray,
    face_offset: int, candidates: list[np.ndarray] | None = None,
) -> None:
    """Lower ``t`` / set ``face`` (in place) where a box surface is hit nearer than ``t``.

    Slab test per box on its ``candidates`` rays (default: ``box_candidates``). A ray
    starting inside a box hits the box's exit face.
    """
    if len(boxes) == 0 or d.shape[1] == 0:
        return
    if candidates is None:
        candidates = box_candidates(boxes, o, d)
    for j, idx in enumerate(candidates):
        if len(idx) == 0:
            continue
        Rt, e, c = boxes.rotations[j].T, boxes.halves[j][:, None], boxes.centers[j]
        dl = Rt @ d[:, idx]  # (3, n) directions in the box frame
        ol = (Rt @ (o - c))[:, None] if o.ndim == 1 else Rt @ (o[:, idx] - c[:, None])
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            t1, t2 = (-e - ol) * inv, (e - ol) * inv
        lo, hi = np.fmin(t1, t2), np.fmax(t1, t2)  # NaN (ray in a face's plane) -> the other
        tn = np.maximum(np.maximum(lo[0], lo[1]), lo[2])
        tf = np.minimum(np.minimum(hi[0], hi[1]), hi[2])
        tj = np.where(tn > 0, tn, tf)
        hit = (tf >= tn) & (tj > 0) & (tj < t[idx])
        if not hit.any():
            continue
        k = np.where(tn[hit] > 0, np.argmax(lo[:, hit], axis=0), np.argmin(hi[:, hit], axis=0))
        sel = idx[hit]
        t[sel], face[sel] = tj[hit], face_offset + 3 * j + k


def raycast(room: Room, boxes: Boxes, o: np.ndarray, d: np.ndarray,
            candidates: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays with any surface of the scene: (t (N,), face id (N,), -1 = none)."""
    t, face = room_raycast(room, o, d)
    boxes_raycast(boxes, o, d, t, face, len(room.polygon) + 2, candidates)
    return t, face
