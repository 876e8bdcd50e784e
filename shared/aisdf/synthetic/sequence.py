"""A posed depth stream through a built-in building, rendered lazily frame by frame."""

from __future__ import annotations

import numpy as np

from ..geometry import intrinsics
from .buildings import make_building
from .render import KinectNoise, render_depth
from .trajectory import make_trajectory

KINECT_HFOV_DEG = 62.7  # Kinect v1 depth camera: f = 525 px at 640 x 480


def pinhole_K(W: int, H: int, hfov_deg: float = KINECT_HFOV_DEG) -> np.ndarray:
    """Square-pixel intrinsics with horizontal field of view ``hfov_deg``, principal point at
    the image centre ((W - 1) / 2, (H - 1) / 2) in the integer-pixel-centre convention."""
    f = (W / 2) / np.tan(np.radians(hfov_deg) / 2)
    return intrinsics(f, f, (W - 1) / 2, (H - 1) / 2)


class SyntheticSequence:
    """``n_frames`` depth frames along ``make_trajectory`` through ``make_building(building)``.

    ``frame(i)`` renders on demand (nothing is cached): a dict with frame_id, stamp (s),
    depth (H, W) float32 metres (0 = no measurement), K (3, 3) and T_WC (4, 4). Noise is
    deterministic per (noise.seed, seed, i), whatever the access order; ``noise=None`` (or
    False) gives exact depth, True the default ``KinectNoise()``. ``gt_sdf`` is the scene's exact SDF (world frame).
    """

    def __init__(
        self, building: str = "office", n_frames: int = 600, H: int = 120, W: int = 160,
        fps: float = 30.0, noise: KinectNoise | bool | None = KinectNoise(), seed: int = 0,
        hfov_deg: float = KINECT_HFOV_DEG, speed: float = 0.4, world_frame: str = "tilted",
    ) -> None:
        if isinstance(noise, bool):  # config flags: True = the default model, False = exact depth
            noise = KinectNoise() if noise else None
        self.building, self.seed, self.fps, self.noise = building, seed, fps, noise
        self.H, self.W = H, W
        self.scene = make_building(building, seed, world_frame)
        self.K = pinhole_K(W, H, hfov_deg)
        self.poses = make_trajectory(self.scene, n_frames, seed, fps=fps, speed=speed)

    def __len__(self) -> int:
        return len(self.poses)

    def frame(self, i: int) -> dict:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range [0, {len(self)})")
        T_WC = self.poses[i]
        depth = render_depth(self.scene, T_WC, self.K, self.H, self.W, self.noise, (self.seed, i))
        return dict(frame_id=i, stamp=i / self.fps, depth=depth, K=self.K.copy(), T_WC=T_WC.copy())

    def __getitem__(self, i: int) -> dict:
        return self.frame(i)

    def __iter__(self):
        return (self.frame(i) for i in range(len(self)))

    def gt_sdf(self, points_W: np.ndarray) -> np.ndarray:
        """Exact signed distance (N,) of world points (N, 3), positive in free space."""
        return self.scene.sdf(points_W)

    def gt_gradient(self, points_W: np.ndarray) -> np.ndarray:
        """Analytic SDF gradient (N, 3) in the world frame."""
        return self.scene.gradient(points_W)
