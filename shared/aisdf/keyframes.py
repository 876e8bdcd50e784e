"""Keyframe selection by motion and overlap (the frontend's, and the benchmarks'). Pure numpy."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from . import geometry, protocol
from .config import Model


class KeyframeConfig(Model):
    """Keyframe selection by motion and overlap (a frame is a keyframe when any test fires)."""

    translation_m: float = Field(0.3, gt=0, description="camera moved this far since the last keyframe")
    rotation_deg: float = Field(20.0, gt=0, description="camera turned this much since the last keyframe")
    min_overlap: float = Field(0.7, ge=0, le=1, description="share of the frame's points the last keyframe saw")
    max_interval_s: float = Field(5.0, gt=0, description="a keyframe at least this often (iSDF forces one every 5 s)")
    overlap_stride: int = Field(4, ge=1, description="pixel stride of the overlap test")
    all_frames: bool = Field(False, description="send every frame as a keyframe")


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


def keyframe_message(frame: dict, sensor: str = "depth", depth_encoding: str = "f4") -> protocol.Keyframe:
    """The wire keyframe of a source's frame (dict of frame_id, stamp, depth, K, T_WC, and
    optionally mask: (H, W), nonzero = a pixel to ignore, sent as 1.10's ``mask``): depth as
    ``f4`` metres or ``u2`` millimetres (what the frontend sends)."""
    depth = np.asarray(frame["depth"], dtype=np.float32)
    scale = None
    if depth_encoding == "u2":
        depth = np.clip(np.round(np.nan_to_num(depth) * 1000.0), 0, 65535).astype(np.uint16)
        scale = 1000.0
    mask = frame.get("mask")
    if mask is not None:
        mask = (np.asarray(mask) != 0).astype(np.uint8)
    return protocol.Keyframe(int(frame["frame_id"]), float(frame["stamp"]), depth, np.asarray(frame["K"], np.float64),
                             np.asarray(frame["T_WC"], np.float64), scale, sensor, mask)
