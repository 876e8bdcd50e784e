"""The AiSDF generic on-disk format: any posed depth sequence, in a folder.

::

    my_sequence/
      intrinsics.txt       depth camera: one line "fx fy cx cy", or a 3x3 matrix (3 lines)
      depth/000000.png     16-bit PNG per frame; metres = value / depth_scale; 0 = invalid
      depth/000001.png     (any number of digits; the number is the frame id; sorted by it)
      poses/000000.txt     4x4 camera-to-world matrix, row-major, one row per line
      ...                  OR instead of poses/: one poses.txt, 16 numbers (row-major 4x4)
                           per line, one line per depth image in frame-id order
      timestamps.txt       optional: one time in seconds per line, in frame-id order
      meta.json            optional (or meta.yaml): {"depth_scale": 1000, "fps": 30,
                           "name": "my_sequence", "mesh": "mesh.ply"}
      mesh.ply             optional ground-truth mesh (any format trimesh reads)

* Camera: OpenCV convention (x right, y down, z forward); poses map camera to world
  (``T_WC``); the world's up axis is free.
* ``depth_scale`` defaults to 1000 (millimetres). Use 5000 (0.2 mm steps, up to 13 m) or
  higher for finer steps; the maximum depth is 65535 / depth_scale.
* Stamps: ``timestamps.txt`` when present, else frame id / fps (fps defaults to 30).
* The mesh: ``meta.mesh`` (relative to the folder) when given, else ``mesh.ply`` when it
  exists.

``write_generic(path, frames, K)`` exports any sequence (e.g. another reader's frames) in
this format; ``open_dataset("generic", path)`` reads it back.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .base import Dataset, numbered, read_depth_png, read_intrinsics, read_matrix, write_depth_png

DEFAULT_DEPTH_SCALE = 1000.0
DEFAULT_FPS = 30.0


def _read_meta(root: Path) -> dict:
    if (root / "meta.json").exists():
        return json.loads((root / "meta.json").read_text())
    for name in ("meta.yaml", "meta.yml"):
        if (root / name).exists():
            import yaml

            return yaml.safe_load((root / name).read_text()) or {}
    return {}


class GenericDataset(Dataset):
    """Reader of the generic format (module docstring)."""

    kind = "generic"

    def __init__(self, path, depth_scale: float | None = None, fps: float | None = None):
        self.root = Path(path)
        meta = _read_meta(self.root)
        self.depth_scale = float(depth_scale or meta.get("depth_scale", DEFAULT_DEPTH_SCALE))
        self.fps = float(fps or meta.get("fps", DEFAULT_FPS))
        self.name = str(meta.get("name", self.root.name))
        self.K = read_intrinsics(self.root / "intrinsics.txt")
        self._depth = numbered((self.root / "depth").iterdir(), r"(\d+)\.png")
        if not self._depth:
            raise FileNotFoundError(f"{self.root}/depth has no NNNNNN.png files")
        if (self.root / "poses").is_dir():
            poses = dict(numbered((self.root / "poses").iterdir(), r"(\d+)\.txt"))
            missing = [i for i, _ in self._depth if i not in poses]
            if missing:
                raise FileNotFoundError(f"{self.root}/poses lacks frames {missing[:5]}")
            self._poses = np.stack([read_matrix(poses[i]).reshape(4, 4) for i, _ in self._depth])
        else:
            rows = np.loadtxt(self.root / "poses.txt", dtype=np.float64, ndmin=2)
            if rows.shape != (len(self._depth), 16):
                raise ValueError(f"poses.txt: expected {len(self._depth)} lines of 16 numbers, got {rows.shape}")
            self._poses = rows.reshape(-1, 4, 4)
        if (self.root / "timestamps.txt").exists():
            self._stamps = np.loadtxt(self.root / "timestamps.txt", dtype=np.float64, ndmin=1)
            if len(self._stamps) != len(self._depth):
                raise ValueError("timestamps.txt must have one line per depth image")
        else:
            self._stamps = np.array([i / self.fps for i, _ in self._depth])
        mesh = meta.get("mesh") or ("mesh.ply" if (self.root / "mesh.ply").exists() else None)
        self.mesh_path = self.root / mesh if mesh else None
        h, w = read_depth_png(self._depth[0][1], self.depth_scale).shape
        self.H, self.W = h, w

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return (path / "intrinsics.txt").is_file() and (path / "depth").is_dir()

    def __len__(self) -> int:
        return len(self._depth)

    def poses(self) -> np.ndarray:
        return self._poses.copy()

    def _load(self, i):
        fid, f = self._depth[i]
        return read_depth_png(f, self.depth_scale), self._poses[i], fid, self._stamps[i]


def write_generic(
    path,
    frames: Iterable[dict],
    K: np.ndarray,
    depth_scale: float = DEFAULT_DEPTH_SCALE,
    name: str | None = None,
    mesh_path=None,
) -> Path:
    """Write ``frames`` (dicts with depth, T_WC, and optionally frame_id, stamp) in the
    generic format under ``path``; ``mesh_path`` is copied in as ``mesh.ply``-like file.
    Returns the folder."""
    root = Path(path)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    (root / "poses").mkdir(exist_ok=True)
    K = np.asarray(K, dtype=np.float64)
    np.savetxt(root / "intrinsics.txt", [[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]], fmt="%.10g")
    stamps = []
    for n, f in enumerate(frames):
        fid = int(f.get("frame_id", n))
        write_depth_png(root / "depth" / f"{fid:06d}.png", f["depth"], depth_scale)
        np.savetxt(root / "poses" / f"{fid:06d}.txt", np.asarray(f["T_WC"], dtype=np.float64), fmt="%.17g")
        stamps.append(float(f.get("stamp", fid / DEFAULT_FPS)))
    np.savetxt(root / "timestamps.txt", np.array(stamps), fmt="%.9f")
    meta = {"depth_scale": depth_scale, "name": name or root.name}
    if mesh_path is not None:
        import shutil

        dst = root / ("mesh" + Path(mesh_path).suffix)
        shutil.copyfile(mesh_path, dst)
        meta["mesh"] = dst.name
    (root / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return root
