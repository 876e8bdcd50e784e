"""7-Scenes and 3DMatch: ``frame-XXXXXX.depth.png`` + ``frame-XXXXXX.pose.txt``.

::

    seq/frame-000000.depth.png   16-bit millimetres; 0 and 65535 (raw 7-Scenes) = invalid
    seq/frame-000000.pose.txt    4x4 camera-to-world, OpenCV camera
    camera-intrinsics.txt        3x3 K, in the sequence folder or its parent (3DMatch)

A folder of ``seq-XX`` sub-folders (a 3DMatch scene) reads them all, in order. Without an
intrinsics file the 7-Scenes depth camera is assumed: fx = fy = 585, cx = 320, cy = 240.
Frame ids are the numbers in the names (plus 1,000,000 x the sequence's index when a
scene's sequences are read together); stamps are id / 30 (Kinect v1 at 30 Hz).
"""

from __future__ import annotations

from pathlib import Path

from ..geometry import intrinsics
from .base import Dataset, numbered, read_depth_png, read_intrinsics, read_matrix

FPS = 30.0
SEVEN_SCENES_K = intrinsics(585.0, 585.0, 320.0, 240.0)
INVALID = (65535,)
SEQ_STRIDE = 1_000_000


def _frame_dirs(root: Path) -> list[Path]:
    if any(root.glob("frame-*.depth.png")):
        return [root]
    return sorted(d for d in root.glob("seq-*") if d.is_dir() and any(d.glob("frame-*.depth.png")))


class SevenScenesDataset(Dataset):
    kind = "7scenes"

    def __init__(self, path, depth_scale: float = 1000.0, K=None):
        self.root = Path(path)
        self.name = self.root.name
        self.depth_scale = depth_scale
        dirs = _frame_dirs(self.root)
        if not dirs:
            raise FileNotFoundError(f"{self.root}: no frame-XXXXXX.depth.png here or in seq-*/")
        self._frames = []
        for s, d in enumerate(dirs):  # ids stay unique across sequences: seq index * SEQ_STRIDE + n
            for n, f in numbered(d.iterdir(), r"frame-(\d+)\.depth\.png"):
                self._frames.append((s * SEQ_STRIDE + n, f, d / f"frame-{n:06d}.pose.txt"))
        if K is None:
            for p in (
                dirs[0] / "camera-intrinsics.txt",
                self.root / "camera-intrinsics.txt",
                self.root.parent / "camera-intrinsics.txt",
            ):
                if p.exists():
                    K = read_intrinsics(p)
                    break
        self.K = SEVEN_SCENES_K.copy() if K is None else K
        self.H, self.W = read_depth_png(self._frames[0][1], depth_scale).shape

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return bool(_frame_dirs(path))

    def __len__(self) -> int:
        return len(self._frames)

    def _load(self, i):
        fid, f, pose = self._frames[i]
        return read_depth_png(f, self.depth_scale, INVALID), read_matrix(pose).reshape(4, 4), fid, fid / FPS
