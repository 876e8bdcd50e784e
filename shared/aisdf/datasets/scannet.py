"""ScanNet, as exported by ScanNet's SensReader (the layout iSDF reads).

::

    scene0000_00/
      frames/depth/0.png ... {i}.png        16-bit, millimetres, 0 = invalid
      frames/pose/0.txt ... {i}.txt          4x4 camera-to-world (rows), OpenCV camera
      frames/intrinsic/intrinsic_depth.txt   4x4 (the 3x3 K in its top-left)
      scene0000_00_vh_clean.ply              optional mesh (not watertight: use unsigned GT)

ScanNet marks lost tracking with non-finite poses (``-inf``); those frames are dropped.
Stamps are frame index / 30 (ScanNet records at 30 Hz).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import Dataset, numbered, read_depth_png, read_intrinsics, read_matrix

FPS = 30.0


class ScanNetDataset(Dataset):
    kind = "scannet"

    def __init__(self, path, depth_scale: float = 1000.0, mesh_path=None):
        self.root = Path(path)
        frames = self.root / "frames" if (self.root / "frames").is_dir() else self.root
        self.name = self.root.name
        self.depth_scale = depth_scale
        self.K = read_intrinsics(frames / "intrinsic" / "intrinsic_depth.txt")
        depth = numbered((frames / "depth").iterdir(), r"(\d+)\.png")
        self._frames = []
        for i, f in depth:
            T = read_matrix(frames / "pose" / f"{i}.txt").reshape(4, 4)
            if np.all(np.isfinite(T)):
                self._frames.append((i, f, T))
        if not self._frames:
            raise FileNotFoundError(f"{frames}: no depth frame with a finite pose")
        self.H, self.W = read_depth_png(self._frames[0][1], depth_scale).shape
        if mesh_path is None:
            cands = sorted(self.root.glob("*_vh_clean_2.ply")) + sorted(self.root.glob("*_vh_clean.ply"))
            mesh_path = cands[0] if cands else None
        self.mesh_path = Path(mesh_path) if mesh_path else None

    @classmethod
    def sniff(cls, path: Path) -> bool:
        frames = path / "frames" if (path / "frames").is_dir() else path
        return (frames / "intrinsic" / "intrinsic_depth.txt").is_file() and (frames / "depth").is_dir()

    def __len__(self) -> int:
        return len(self._frames)

    def poses(self) -> np.ndarray:
        return np.stack([T for _, _, T in self._frames])

    def _load(self, i):
        fid, f, T = self._frames[i]
        return read_depth_png(f, self.depth_scale), T, fid, fid / FPS
