"""A client written from protocol.md alone: zenoh, msgpack and numpy, no aisdf import.

It owns a scene the project has never seen (a box room in a rotated, offset world
frame with a pillar), renders exact depth for it, publishes keyframes, and asks
query/sdf and map/surfels, checking answers against its own analytic truth.
"""

from __future__ import annotations

import json
import math

import msgpack
import numpy as np
import zenoh

ENC = zenoh.Encoding("application/msgpack")


def arr(a, dtype):
    a = np.ascontiguousarray(np.asarray(a, dtype=np.dtype(dtype)))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def unarr(m):
    return np.frombuffer(m["data"], dtype=np.dtype(m["dtype"])).reshape(m["shape"])


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


class BoxRoom:
    """Room [0,a]x[0,b]x[0,h] (z up in the room frame) with a square pillar; the world
    frame is the room frame rotated about a tilted axis and shifted."""

    def __init__(self, a=4.2, b=3.4, h=2.6, pillar=((2.8, 1.1), 0.25)):
        self.lo, self.hi = np.zeros(3), np.array([a, b, h])
        (px, py), r = pillar
        self.p_lo, self.p_hi = np.array([px - r, py - r, 0.0]), np.array([px + r, py + r, h])
        self.R_WR = rot([0.3, -0.5, 0.8], 1.1)  # world from room: up is no world axis
        self.t_WR = np.array([5.0, -2.0, 1.0])

    def to_room(self, p_W):
        return (p_W - self.t_WR) @ self.R_WR

    def sdf(self, p_W):
        p = self.to_room(np.asarray(p_W, float))
        d_room = np.min(np.concatenate([p - self.lo, self.hi - p], axis=1), axis=1)
        q = np.maximum(self.p_lo - p, p - self.p_hi)
        outside = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        return np.minimum(d_room, outside)

    def raycast(self, o_R, d_R):
        """Distance along unit room-frame rays from inside the room to the first surface."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = np.where(d_R > 0, (self.hi - o_R) / d_R, np.inf)
            t_lo = np.where(d_R < 0, (self.lo - o_R) / d_R, np.inf)
            t = np.minimum(t_hi, t_lo).min(axis=1)
            t1 = (self.p_lo - o_R) / d_R
            t2 = (self.p_hi - o_R) / d_R
            tn = np.minimum(t1, t2).max(axis=1)
            tf = np.maximum(t1, t2).min(axis=1)
        hit = (tn <= tf) & (tn > 0)
        return np.where(hit, np.minimum(t, tn), t)

    def render(self, T_WC, K, H, W):
        v, u = np.mgrid[0:H, 0:W].astype(float)
        dirs_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        T_RC = np.eye(4)
        T_RC[:3, :3] = self.R_WR.T @ T_WC[:3, :3]
        T_RC[:3, 3] = self.to_room(T_WC[:3, 3][None])[0]
        d_R = dirs_C @ T_RC[:3, :3].T
        n = np.linalg.norm(d_R, axis=1)
        t = self.raycast(np.broadcast_to(T_RC[:3, 3], d_R.shape), d_R / n[:, None])
        depth = (t / n).reshape(H, W)  # z-depth
        depth[~np.isfinite(depth)] = 0
        return depth.astype(np.float32)

    def poses(self, n=24):
        """A camera at 1.3 m turning on the spot twice (level, then looking down)."""
        out = []
        for i in range(n):
            yaw = 2 * math.pi * i / (n // 2)
            pitch = -0.15 if i < n // 2 else -0.55
            # camera looks along room +x rotated by yaw; OpenCV: z forward, y down.
            fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
            down = np.array([0, 0, -1.0])
            x = np.cross(down, fwd)
            x /= np.linalg.norm(x)
            y = np.cross(fwd, x)
            R_RC = np.stack([x, y, fwd], axis=1)
            c_R = np.array([1.4 + 0.3 * math.cos(yaw), 1.7 + 0.3 * math.sin(yaw), 1.3])
            T = np.eye(4)
            T[:3, :3] = self.R_WR @ R_RC
            T[:3, 3] = self.R_WR @ c_R + self.t_WR
            out.append(T)
        return out

    def wall_normals_W(self):
        """Unit normals of the room's planes in the world frame: vertical, then x and y walls."""
        return self.R_WR[:, 2], self.R_WR[:, 0], self.R_WR[:, 1]


def open_session(connect, listen=None):
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        c.insert_json5("listen/endpoints", json.dumps(listen))
    return zenoh.open(c)


def keyframe_payload(frame_id, stamp, depth_m, K, T_WC, as_u2=True):
    msg = {"v": 1, "frame_id": frame_id, "stamp": stamp, "K": arr(K, "<f8"), "T_WC": arr(T_WC, "<f8"),
           "sensor": "stranger-cam"}
    if as_u2:
        msg["depth"] = arr(np.round(depth_m * 1000), "<u2")
        msg["depth_scale"] = 1000.0
    else:
        msg["depth"] = arr(depth_m, "<f4")
    return msgpack.packb(msg, use_bin_type=True)


def request(session, key, msg: dict | bytes, timeout=10.0):
    """Returns ("ok", map) or ("err", map)."""
    payload = msg if isinstance(msg, bytes) else msgpack.packb(msg, use_bin_type=True)
    for r in session.get(key, payload=payload, encoding=ENC, timeout=timeout):
        if r.ok is not None:
            return "ok", msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)
        return "err", msgpack.unpackb(r.err.payload.to_bytes(), raw=False)
    return "timeout", None


def query_sdf(session, ns, points, gradient=False, source=None, timeout=10.0):
    msg = {"v": 1, "points": arr(points, "<f8"), "gradient": gradient}
    if source:
        msg["source"] = source
    return request(session, f"{ns}/query/sdf", msg, timeout)
