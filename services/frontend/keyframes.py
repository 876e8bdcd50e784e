"""Keyframe selection by motion and overlap. Pure numpy."""

from __future__ import annotations

import numpy as np

from aisdf import geometry

from .config import KeyframeConfig


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def overlap(depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray, kf_depth: np.ndarray, kf_K: np.ndarray,
            kf_T_WC: np.ndarray, stride: int = 4, rel_tol: float = 0.1) -> float:
    """Share of this frame's valid points (every ``stride`` pixels) that the keyframe saw:
    they project inside it with a measured depth within ``rel_tol`` (relative)."""
    d = depth[::stride, ::stride]
    Ks = K.copy()
    Ks[:2] /= stride
    Ks[:2, 2] = K[:2, 2] / stride
    pts = geometry.backproject(d, Ks).reshape(-1, 3)
    pts = pts[np.isfinite(pts[:, 0])]
    if len(pts) == 0:
        return 0.0
    p_K = geometry.transform(geometry.invert(kf_T_WC) @ T_WC, pts)
    z = p_K[:, 2]
    front = z > 1e-6
    u = np.round(kf_K[0, 0] * p_K[:, 0] / np.where(front, z, 1) + kf_K[0, 2]).astype(np.int64)
    v = np.round(kf_K[1, 1] * p_K[:, 1] / np.where(front, z, 1) + kf_K[1, 2]).astype(np.int64)
    H, W = kf_depth.shape
    inside = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    seen = np.zeros(len(pts), bool)
    dz = kf_depth[v[inside], u[inside]]
    seen[inside] = (dz > 0) & (np.abs(dz - z[inside]) <= rel_tol * z[inside])
    return float(seen.mean())


class KeyframeSelector:
    """Decides whether each frame is a keyframe; remembers the last keyframe."""

    def __init__(self, cfg: KeyframeConfig | None = None):
        self.cfg = cfg or KeyframeConfig()
        self.last: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None  # stamp, depth, K, T_WC
        self.last_reason = ""

    def is_keyframe(self, stamp: float, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray) -> bool:
        c = self.cfg
        reason = ""
        if c.all_frames:
            reason = "all"
        elif self.last is None:
            reason = "first"
        else:
            t0, d0, K0, T0 = self.last
            rel = geometry.invert(T0) @ T_WC
            if stamp - t0 >= c.max_interval_s:
                reason = "interval"
            elif np.linalg.norm(rel[:3, 3]) >= c.translation_m:
                reason = "translation"
            elif rotation_angle_deg(rel[:3, :3]) >= c.rotation_deg:
                reason = "rotation"
            elif overlap(depth, K, T_WC, d0, K0, T0, c.overlap_stride) < c.min_overlap:
                reason = "overlap"
        if reason:
            self.last = (stamp, depth, K, T_WC)
            self.last_reason = reason
        return bool(reason)
