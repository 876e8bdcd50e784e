"""Replica renders: ReplicaCAD in iSDF's layout, and NICE-SLAM's Replica (same layout).

::

    sequence/
      results/depth000000.png   16-bit; metres = value / scale; 0 = invalid
      results/ndepth000000.png  (ReplicaCAD only) the noisy variant, ``noisy=True``
      traj.txt                  one row-major 4x4 camera-to-world per line, OpenCV camera

* ``replicacad`` (isdf-reference.md): scale 3276.75, 1200x680, fx = fy = 600,
  cx = 599.5, cy = 339.5, 30 fps.
* ``replica`` (NICE-SLAM, e.g. $AISDF_DATA/replica-office0-nvblox/replica/office0):
  the same, but scale 6553.5 and the camera from ``cam_params.json`` in the sequence
  folder or its parent; the ground-truth mesh is ``../<sequence>_mesh.ply`` when present.

Frames are those with both a depth image and a trajectory row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import ClassVar

from ..geometry import intrinsics
from .base import Dataset, load_trajectory, numbered, read_depth_png

FPS = 30.0


class ReplicaCADDataset(Dataset):
    kind = "replicacad"
    default_scale = 3276.75
    default_camera: ClassVar[dict] = {"fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "w": 1200, "h": 680}

    def __init__(self, path, noisy: bool = False, depth_scale: float | None = None, mesh_path=None):
        self.root = Path(path)
        self.name = self.root.name
        cam = dict(self.default_camera)
        scale = self.default_scale
        for p in (self.root / "cam_params.json", self.root.parent / "cam_params.json"):
            if p.exists():
                c = json.loads(p.read_text()).get("camera", {})
                cam.update({k: c[k] for k in cam if k in c})
                scale = float(c.get("scale", scale))
                break
        self.depth_scale = float(depth_scale or scale)
        self.K = intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"])
        self.H, self.W = int(cam["h"]), int(cam["w"])
        self._T = load_trajectory(self.root / "traj.txt")
        prefix = "ndepth" if noisy else "depth"
        files = numbered((self.root / "results").iterdir(), prefix + r"(\d+)\.png")
        self._depth = [(i, f) for i, f in files if i < len(self._T)]
        if not self._depth:
            raise FileNotFoundError(f"{self.root}/results has no {prefix}NNNNNN.png with a pose")
        if mesh_path is None:
            cand = self.root.parent / f"{self.root.name}_mesh.ply"
            mesh_path = cand if cand.exists() else None
        self.mesh_path = Path(mesh_path) if mesh_path else None

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return (
            (path / "traj.txt").is_file()
            and any((path / "results").glob("depth*.png"))
            and cls._camera_file(path) is None
        )

    @staticmethod
    def _camera_file(path: Path):
        for p in (path / "cam_params.json", path.parent / "cam_params.json"):
            if p.exists():
                return p
        return None

    def __len__(self) -> int:
        return len(self._depth)

    def poses(self):
        return self._T[[i for i, _ in self._depth]]

    def _load(self, i):
        fid, f = self._depth[i]
        return read_depth_png(f, self.depth_scale), self._T[fid], fid, fid / FPS


class ReplicaDataset(ReplicaCADDataset):
    """NICE-SLAM's Replica renders (scale and camera from ``cam_params.json``)."""

    kind = "replica"
    default_scale = 6553.5

    @classmethod
    def sniff(cls, path: Path) -> bool:
        return (
            (path / "traj.txt").is_file()
            and any((path / "results").glob("depth*.png"))
            and cls._camera_file(path) is not None
        )
