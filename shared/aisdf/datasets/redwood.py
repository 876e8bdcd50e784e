"""ICL-NUIM (augmented, Choi et al.) and Redwood: depth images + an Open3D/Redwood ``.log``.

::

    sequence/
      depth/00000.png             16-bit millimetres (scale 1000), 0 = invalid
      trajectory.log              or test_scene/trajectory.log, or ``trajectory=...``
      camera_primesense.json      optional Open3D intrinsics (column-major 3x3 list)

A ``.log`` holds 5 lines per frame: ``id id id+1`` then a row-major 4x4 camera-to-world
pose (OpenCV camera). The first number is the frame id; it names the depth image with
that number. Without an intrinsics file the PrimeSense default is used (fx = fy = 525,
cx = 319.5, cy = 239.5, what augmented ICL-NUIM uses). Stamps are id / 30.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry import intrinsics
from .base import Dataset, numbered, read_depth_png

FPS = 30.0
PRIMESENSE_K = intrinsics(525.0, 525.0, 319.5, 239.5)
_LOG_NAMES = ("trajectory.log", "test_scene/trajectory.log")
_K_NAMES = ("camera_primesense.json", "camera_intrinsic.json", "intrinsic.json")


def read_log(path) -> tuple[np.ndarray, np.ndarray]:
    """A Redwood/Open3D ``.log`` -> (ids (N,) int, poses (N, 4, 4))."""
    rows = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip()]
    if len(rows) % 5:
        raise ValueError(f"{path}: a .log has 5 lines per frame, got {len(rows)} lines")
    ids = np.array([int(rows[k][0]) for k in range(0, len(rows), 5)])
    poses = np.array([[[float(x) for x in rows[k + r]] for r in range(1, 5)] for k in range(0, len(rows), 5)])
    return ids, poses


def write_log(path, poses: np.ndarray, ids=None) -> None:
    """Write (N, 4, 4) poses as a ``.log`` (ids default to 0..N-1)."""
    ids = range(len(poses)) if ids is None else ids
    with open(path, "w") as f:
        for i, T in zip(ids, poses, strict=True):
            f.write(f"{i} {i} {i + 1}\n")
            for r in T:
                f.write(" ".join(f"{x:.10f}" for x in r) + "\n")


def _open3d_intrinsics(path: Path) -> tuple[np.ndarray, int, int]:
    d = json.loads(path.read_text())
    K = np.array(d["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T  # stored column-major
    return K, int(d["height"]), int(d["width"])


class RedwoodDataset(Dataset):
    kind = "redwood"

    def __init__(self, path, trajectory=None, depth_scale: float = 1000.0, K=None):
        self.root = Path(path)
        self.name = self.root.name
        self.depth_scale = depth_scale
        log = (
            Path(trajectory)
            if trajectory
            else next((self.root / n for n in _LOG_NAMES if (self.root / n).exists()), None)
        )
        if log is None:
            raise FileNotFoundError(f"{self.root}: no trajectory.log (pass trajectory=...)")
        ids, poses = read_log(log)
        files = dict(numbered((self.root / "depth").iterdir(), r"(\d+)\.png"))
        self._frames = [(int(i), files[int(i)], T) for i, T in zip(ids, poses, strict=True) if int(i) in files]
        if not self._frames:
            raise FileNotFoundError(f"{self.root}/depth: no image numbered like the ids in {log}")
        if K is None:
            kf = next((self.root / n for n in _K_NAMES if (self.root / n).exists()), None)
            K = _open3d_intrinsics(kf)[0] if kf else PRIMESENSE_K.copy()
        self.K = np.asarray(K, dtype=np.float64)
        self.H, self.W = read_depth_png(self._frames[0][1], depth_scale).shape

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return (path / "depth").is_dir() and any((path / n).exists() for n in _LOG_NAMES)

    def __len__(self) -> int:
        return len(self._frames)

    def poses(self):
        return np.stack([T for _, _, T in self._frames])

    def _load(self, i):
        fid, f, T = self._frames[i]
        return read_depth_png(f, self.depth_scale), T, fid, fid / FPS
