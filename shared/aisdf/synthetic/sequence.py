"""A posed depth stream through a built-in building, rendered lazily frame by frame."""

from __future__ import annotations

import numpy as np

from ..geometry import intrinsics
from .buildings import PLANS, make_building
from .render import KinectNoise, render_depth
from .trajectory import make_trajectory, make_walk

KINECT_HFOV_DEG = 62.7  # Kinect v1 depth camera: f = 525 px at 640 x 480


def pinhole_K(W: int, H: int, hfov_deg: float = KINECT_HFOV_DEG) -> np.ndarray:
    """Square-pixel intrinsics with horizontal field of view ``hfov_deg``, principal point at
    the image centre ((W - 1) / 2, (H - 1) / 2) in the integer-pixel-centre convention."""
    f = (W / 2) / np.tan(np.radians(hfov_deg) / 2)
    return intrinsics(f, f, (W - 1) / 2, (H - 1) / 2)


class SyntheticSequence:
    """``n_frames`` depth frames along ``make_trajectory`` through ``make_building(building)``
    (for a building with a floor plan, ``buildings.PLANS``: along ``make_walk``, room by room,
    at the walk's own pace; frames after its end hold the last pose).

    ``frame(i)`` renders on demand (nothing is cached): a dict with frame_id, stamp (s),
    depth (H, W) float32 metres (0 = no measurement), K (3, 3) and T_WC (4, 4). Noise is
    deterministic per (noise.seed, seed, i), whatever the access order; ``noise=None`` (or
    False) gives exact depth, True the default ``KinectNoise()``. ``gt_sdf`` is the scene's exact SDF (world frame).

    With a floor plan: ``plan`` (canonical regions), ``visits`` {room: (t_in, t_out)} in
    stream seconds, ``walk_s`` (the walk's duration) and ``region_of(points_W)``; otherwise
    ``plan`` is None and ``visits`` empty. ``speed`` (m/s) defaults to the trajectory's own
    (0.4 for the loop, 0.6 for the walk).
    """

    def __init__(
        self, building: str = "office", n_frames: int = 600, H: int = 120, W: int = 160,
        fps: float = 30.0, noise: KinectNoise | bool | None = KinectNoise(), seed: int = 0,
        hfov_deg: float = KINECT_HFOV_DEG, speed: float | None = None, world_frame: str = "tilted",
    ) -> None:
        if isinstance(noise, bool):  # config flags: True = the default model, False = exact depth
            noise = KinectNoise() if noise else None
        self.building, self.seed, self.fps, self.noise = building, seed, fps, noise
        self.H, self.W = H, W
        self.scene = make_building(building, seed, world_frame)
        self.K = pinhole_K(W, H, hfov_deg)
        self.plan = PLANS[building]() if building in PLANS else None
        self.visits: dict[str, tuple[float, float]] = {}
        self.walk_s: float | None = None
        if self.plan is not None:
            kw = {} if speed is None else {"speed": speed}
            self.poses, self.visits, self.walk_s = make_walk(self.scene, self.plan, n_frames, seed, fps=fps, **kw)
        else:
            self.poses = make_trajectory(self.scene, n_frames, seed, fps=fps, speed=0.4 if speed is None else speed)

    def __len__(self) -> int:
        return len(self.poses)

    def frame(self, i: int) -> dict:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range [0, {len(self)})")
        T_WC = self.poses[i]
        depth = render_depth(self.scene_at(i), T_WC, self.K, self.H, self.W, self.noise, (self.seed, i))
        return dict(frame_id=i, stamp=i / self.fps, depth=depth, K=self.K.copy(), T_WC=T_WC.copy())

    def scene_at(self, i: int):
        """The scene frame ``i`` is rendered from (the same for every frame here; a changing
        scene, ``changes.ChangingSequence``, answers per frame)."""
        return self.scene

    def __getitem__(self, i: int) -> dict:
        return self.frame(i)

    def __iter__(self):
        return (self.frame(i) for i in range(len(self)))

    def gt_sdf(self, points_W: np.ndarray) -> np.ndarray:
        """Exact signed distance (N,) of world points (N, 3), positive in free space."""
        return self.scene.sdf(points_W)

    def region_of(self, points_W: np.ndarray) -> np.ndarray:
        """(N,) index into ``plan.names`` of the region holding each world point (-1: none)."""
        if self.plan is None:
            raise ValueError(f"building {self.building!r} has no floor plan")
        return self.plan.region_of(self.scene.to_canon(points_W)[:, :2])

    def gt_gradient(self, points_W: np.ndarray) -> np.ndarray:
        """Analytic SDF gradient (N, 3) in the world frame."""
        return self.scene.gradient(points_W)
