"""Is the TF chain right? A check of a source's first frames before mapping, with a verdict in
words.

A wrong chain, typically the camera_link -> optical rotation missing (REP-103: the optical
frame has z forward, x right, y down; the link frame x forward, y left, z up), gives poses that
are rigid and smooth but turned: the map would be built tilted by 90 degrees and, worse,
consecutive frames no longer agree. Two tests on up to ``n`` frames spread over the first
``window`` frames:

1. **Gravity** (assumes a fixed frame with z up, as REP-103 asks of map/odom): the image's
   "down" axis (the optical frame's +y) should point roughly along the fixed frame's -z. A
   camera on a robot or in a hand is roughly upright; the median angle over the frames should
   be below ``max_down_deg`` (70 degrees). With the optical rotation missing it is 90 degrees
   for a level camera (the link frame's +y is horizontal). But a fixed frame that is not z-up,
   or a camera pitched up, gets there with a right chain: alone, this is a warning, not a
   refusal. The share of surface normals (from the depth images) near the vertical is
   reported too.
2. **Depth consistency** (frame-agnostic): each frame's depth moved into the next sampled
   frame's camera with the poses must agree with that frame's depth better than with no motion
   at all. For pairs where the camera moved enough to tell (the no-motion residual, a median
   depth difference, is above 5 cm: well above depth noise), the posed residual must be at most
   0.7 times the no-motion one in at least half of the pairs.

``check_frames(frames)`` / ``check_source(src)`` -> :class:`TFCheck` (``ok``, ``message``,
figures, ``warning``). Only the depth test's evidence fails a source (the gravity test's
finding is given with it); a source that fails is refused by the frontend unless told
otherwise (``--no-tf-check``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..datasets.base import reprojection_residual
from ..geometry import normals_from_depth

UP = np.array([0.0, 0.0, 1.0])


@dataclass
class TFCheck:
    ok: bool
    message: str
    figures: dict = field(default_factory=dict)
    warning: str | None = None  # a finding that does not fail the check (the gravity test's alone)

    def __str__(self) -> str:
        return ("TF check passed: " if self.ok else "TF check FAILED: ") + self.message + (
            f" Warning: {self.warning}." if self.ok and self.warning else "")


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _vertical_share(frames: list[dict], up: np.ndarray, stride: int = 4, tol_deg: float = 10.0) -> float:
    """Share of valid normals within ``tol_deg`` of the vertical (floors, ceilings, tables)."""
    near, total = 0, 0
    for f in frames:
        d = np.asarray(f["depth"], np.float32)[::stride, ::stride]
        K = np.array(f["K"], np.float64)
        K[:2] /= stride
        n = normals_from_depth(d, K).reshape(-1, 3)
        n = n[np.isfinite(n).all(1) & (np.linalg.norm(n, axis=1) > 0.5)]
        if not len(n):
            continue
        nw = n @ np.asarray(f["T_WC"])[:3, :3].T
        near += int((np.abs(nw @ up) > np.cos(np.radians(tol_deg))).sum())
        total += len(nw)
    return near / total if total else float("nan")


def check_frames(frames: list[dict], up=UP, max_down_deg: float = 70.0, min_motion_m: float = 0.05,
                 gravity: bool = True) -> TFCheck:
    """The verdict on ``frames`` (dicts with depth, K, T_WC, in time order)."""
    if not frames:
        return TFCheck(False, "no frame could be placed, nothing to check")
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    figs: dict = {"frames": len(frames)}
    problems, tilted = [], None
    if gravity:
        downs = [_angle_deg(np.asarray(f["T_WC"])[:3, 1], -up) for f in frames]
        figs["image_down_vs_gravity_deg"] = round(float(np.median(downs)), 1)
        figs["optical_axis_elevation_deg"] = round(float(np.median(
            [90.0 - _angle_deg(np.asarray(f["T_WC"])[:3, 2], up) for f in frames])), 1)
        figs["vertical_normals_share"] = round(_vertical_share(frames, up), 3)
        if figs["image_down_vs_gravity_deg"] > max_down_deg:
            tilted = (
                f"the camera's image 'down' axis (optical +y) points {figs['image_down_vs_gravity_deg']:.0f} degrees "
                f"away from the fixed frame's down (-z) on median over {len(frames)} frames, and its viewing axis "
                f"is {figs['optical_axis_elevation_deg']:+.0f} degrees above the horizon: the camera would be lying "
                f"on its side or looking at the sky. The chain from the fixed frame to the image's frame is probably "
                f"missing the camera_link -> optical rotation (REP-103: z forward, x right, y down), or the fixed "
                f"frame is not z-up")
    pairs = []
    for a, b in zip(frames[:-1], frames[1:]):
        still = dict(b, T_WC=a["T_WC"])
        r_still, r_posed = reprojection_residual(a, still), reprojection_residual(a, b)
        if np.isfinite(r_still) and r_still > min_motion_m:
            pairs.append((r_posed, r_still))
    figs["moving_pairs"] = len(pairs)
    if pairs:
        posed, still = np.array(pairs).T
        figs["depth_residual_posed_cm"] = round(100 * float(np.median(posed)), 2)
        figs["depth_residual_no_motion_cm"] = round(100 * float(np.median(still)), 2)
        good = posed <= 0.7 * still
        figs["consistent_pairs"] = int(good.sum())
        if good.mean() < 0.5:
            problems.append(
                f"consecutive depth images disagree once placed with these poses: in {int((~good).sum())} of "
                f"{len(pairs)} moving pairs the poses explain the depth hardly better than no motion at all, or worse "
                f"(median "
                f"residual {figs['depth_residual_posed_cm']:.1f} cm posed vs {figs['depth_residual_no_motion_cm']:.1f}"
                f" cm unmoved): the camera's motion in the TF chain is not the motion the images see (a wrong or "
                f"missing rotation in the chain, typically the camera_link -> optical rotation of REP-103: z forward, x "
                f"right, y down; or poses of another frame)")
    if problems:  # the depth disagrees with the poses: refused, with the gravity test's finding
        return TFCheck(False, "; and ".join(([tilted] if tilted else []) + problems) + ".", figs)
    warning = None
    if tilted:
        warning = (f"the camera's image 'down' axis (optical +y) points {figs['image_down_vs_gravity_deg']:.0f} "
                   f"degrees away from the fixed frame's -z on median, its viewing axis "
                   f"{figs['optical_axis_elevation_deg']:+.0f} degrees above the horizon: the fixed frame is not "
                   f"z-up, or the camera is pitched up or on its side. " + (
                       "Mapped anyway: the depth images agree with the poses" if pairs else
                       "Mapped anyway, though too little motion in the first frames to test the depth against the "
                       "poses"))
    parts = []
    if gravity and not tilted:
        parts.append(f"image 'down' {figs['image_down_vs_gravity_deg']:.0f} deg from the fixed frame's -z, "
                     f"{100 * figs['vertical_normals_share']:.0f}% of surface normals vertical")
    if pairs:
        parts.append(f"poses explain the depth of {figs['consistent_pairs']}/{len(pairs)} moving pairs "
                     f"({figs['depth_residual_posed_cm']:.1f} cm vs {figs['depth_residual_no_motion_cm']:.1f} cm "
                     f"unmoved)")
    else:
        parts.append("too little motion in the first frames to test depth consistency")
    return TFCheck(True, "; ".join(parts) + f" (over {len(frames)} frames).", figs, warning)


def sample_indices(n_total: int, n: int = 12, window: int = 90) -> list[int]:
    m = min(n_total, window)
    return sorted(set(np.linspace(0, m - 1, min(n, m)).round().astype(int).tolist())) if m else []


def check_source(src, n: int = 12, window: int = 90, **kw) -> TFCheck:
    """``check_frames`` on up to ``n`` frames spread over the source's first ``window``."""
    return check_frames([src.frame(i) for i in sample_indices(len(src), n, window)], **kw)
