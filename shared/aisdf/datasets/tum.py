"""TUM RGB-D: ``depth.txt`` + ``groundtruth.txt``, associated by timestamp.

::

    rgbd_dataset_freiburg1_xyz/
      depth.txt         "timestamp depth/<timestamp>.png" per line ('#' comments)
      depth/*.png       16-bit, metres = value / 5000, 0 = invalid
      groundtruth.txt   "timestamp tx ty tz qx qy qz qw": camera (optical centre) to world

Each depth image gets the pose interpolated (linear position, slerp rotation) between the
two ground-truth samples around its timestamp; images farther than ``max_dt`` (0.02 s,
the tolerance of TUM's associate.py) from any ground-truth sample, or outside the
ground-truth time span, are dropped. Intrinsics: TUM's published depth-registered
calibration chosen by the folder name (freiburg1/2/3), else the ROS default
(525, 525, 319.5, 239.5); override with ``K=``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..geometry import intrinsics
from .base import Dataset, read_depth_png

CAMERAS = {
    "freiburg1": intrinsics(517.3, 516.5, 318.6, 255.3),
    "freiburg2": intrinsics(520.9, 521.0, 325.1, 249.7),
    "freiburg3": intrinsics(535.4, 539.2, 320.1, 247.6),
}
DEFAULT_K = intrinsics(525.0, 525.0, 319.5, 239.5)


def _read_list(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def associate_poses(stamps: np.ndarray, gt: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``stamps`` from ground-truth rows ``t tx ty tz qx qy qz qw`` (sorted by t).
    Returns (kept indices into stamps, (M, 4, 4) poses)."""
    t = gt[:, 0]
    j = np.searchsorted(t, stamps)
    nearest = np.minimum(
        np.abs(stamps - t[np.clip(j - 1, 0, len(t) - 1)]), np.abs(stamps - t[np.clip(j, 0, len(t) - 1)])
    )
    keep = np.flatnonzero((stamps >= t[0]) & (stamps <= t[-1]) & (nearest <= max_dt))
    slerp = Slerp(t, Rotation.from_quat(gt[:, 4:8]))
    T = np.tile(np.eye(4), (len(keep), 1, 1))
    s = stamps[keep]
    T[:, :3, :3] = slerp(s).as_matrix()
    T[:, :3, 3] = np.stack([np.interp(s, t, gt[:, 1 + k]) for k in range(3)], axis=-1)
    return keep, T


class TUMDataset(Dataset):
    kind = "tum"

    def __init__(self, path, depth_scale: float = 5000.0, max_dt: float = 0.02, K=None):
        self.root = Path(path)
        self.name = self.root.name
        self.depth_scale = depth_scale
        rows = _read_list(self.root / "depth.txt")
        stamps = np.array([float(r[0]) for r in rows])
        gt = np.array([[float(x) for x in r[:8]] for r in _read_list(self.root / "groundtruth.txt")])
        gt = gt[np.argsort(gt[:, 0])]
        keep, self._T = associate_poses(stamps, gt, max_dt)
        if not len(keep):
            raise ValueError(f"{self.root}: no depth image within {max_dt} s of a ground-truth pose")
        self._files = [self.root / rows[k][1] for k in keep]
        self._stamps = stamps[keep]
        if K is None:
            K = next((k for name, k in CAMERAS.items() if name in self.root.name), DEFAULT_K)
        self.K = np.array(K, dtype=np.float64)
        self.H, self.W = read_depth_png(self._files[0], depth_scale).shape

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return (path / "depth.txt").is_file() and (path / "groundtruth.txt").is_file()

    def __len__(self) -> int:
        return len(self._files)

    def poses(self):
        return self._T.copy()

    def _load(self, i):
        return read_depth_png(self._files[i], self.depth_scale), self._T[i], i, self._stamps[i]
