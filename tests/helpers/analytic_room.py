"""An analytic scene for the mapping tests: a 4 x 3 x 2.5 m room with a box on its floor, its
exact SDF, depth frames rendered by ray/slab intersection, iSDF's evaluation points, and one
floor surfel."""

import numpy as np

from aisdf.mapping import Frame
from aisdf.structure.surfel_types import Surfels

ROOM_C, ROOM_H = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.5, 1.25])  # 4 x 3 x 2.5 m room
BOX_C, BOX_H = np.array([0.8, 0.6, -0.85]), np.array([0.4, 0.35, 0.4])  # a 0.8 m box on the floor


def box_sdf(p, c, h):
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def scene_sdf(p):
    """Exact SDF in free space: the room's inside is free, the box is solid."""
    return np.minimum(-box_sdf(p, ROOM_C, ROOM_H), box_sdf(p, BOX_C, BOX_H))


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def render(T_WC, K, H, W):
    """z-depth by ray/slab intersection: exit of the room box, entry of the obstacle box."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T_WC[:3, :3].T
    o = T_WC[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_room = np.maximum((ROOM_C - ROOM_H - o) / d, (ROOM_C + ROOM_H - o) / d).min(-1)
        b1, b2 = (BOX_C - BOX_H - o) / d, (BOX_C + BOX_H - o) / d
        tn, tf = np.minimum(b1, b2).max(-1), np.maximum(b1, b2).min(-1)
    hit = (tn <= tf) & (tn > 0)
    return np.where(hit, np.minimum(tn, t_room), t_room).astype(np.float32)  # dirs have z = 1


K_SMALL = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])


def room_frames(n=6, H=60, W=80, K=K_SMALL):
    frames = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([0.9 * np.cos(a) - 0.3, 0.7 * np.sin(a), 0.2])
        T = look_at(eye, eye + np.array([np.cos(a + 2.2), np.sin(a + 2.2), -0.35]))
        frames.append(Frame(k, float(k), render(T, K, H, W), K, T))
    return frames


def eval_points(frames, n, rng):
    """iSDF's protocol: random valid pixels, one point per ray uniform in [0.1, D + 0.1]."""
    pts = []
    for f in frames:
        H, W = f.depth.shape
        idx = rng.integers(0, H * W, n)
        u, v, D = idx % W, idx // W, f.depth.reshape(-1)[idx]
        z = rng.uniform(0.1, D + 0.1)
        p_C = np.stack([(u - f.K[0, 2]) / f.K[0, 0], (v - f.K[1, 2]) / f.K[1, 1], np.ones(n)], -1) * z[:, None]
        pts.append(p_C @ f.T_WC[:3, :3].T + f.T_WC[:3, 3])
    return np.concatenate(pts)


def floor_surfels():
    """One surfel on the room's floor (z = -1.25), normal up, 1 x 2 m."""
    return Surfels(center=[[0.0, 0.0, -1.25]], normal=[[0, 0, 1.0]], axis1=[[1.0, 0, 0]], axis2=[[0, 1.0, 0]],
                   extent=[[1.0, 2.0]], direction=[-1], keyframe=[0])

