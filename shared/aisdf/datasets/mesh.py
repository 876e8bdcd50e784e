"""Render a depth sequence from any mesh along a trajectory ("mesh" reader).

``open_dataset("mesh", path, ...)`` where ``path`` is a mesh file, or a folder holding one
(``*_mesh.ply`` preferred, else the only ``.ply``/``.obj``), a trajectory (``traj.txt``: 16
numbers per line, row-major 4x4 camera-to-world; or a Redwood ``.log``) and optionally a
NICE-SLAM ``cam_params.json`` (fx fy cx cy w h), all searched recursively. That covers
$AISDF_DATA/replica-office0-nvblox (the Replica office mesh and its 2000 poses).

Options: ``trajectory`` (file or (N, 4, 4) array), ``K`` and ``size=(H, W)`` (default:
cam_params.json, else 640x480 with fx = fy = 525), ``stride`` (every n-th pose),
``noise``: an object with ``apply(depth, K, cos_incidence, key)`` such as
``aisdf.synthetic.render.KinectNoise`` (key = (frame index,); incidence from the depth
image's normals), or a callable ``(depth, rng) -> depth`` whose rng is seeded by
(seed, frame index); either way frames are reproducible. ``backend`` of
``aisdf.datasets.raycast`` (auto, open3d, numpy), ``max_frames``.
The depth is z-depth in metres, 0 where the ray leaves the mesh.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..geometry import intrinsics, normals_from_depth, ray_dirs_C
from .base import Dataset, load_trajectory
from .raycast import MeshScene
from .redwood import read_log

FPS = 30.0
DEFAULT_K = intrinsics(525.0, 525.0, 319.5, 239.5)
DEFAULT_SIZE = (480, 640)
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb")

NoiseFn = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def _find_mesh(root: Path) -> Path:
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)
    pref = [p for p in files if p.stem.endswith("_mesh")]
    if pref or len(files) == 1:
        return (pref or files)[0]
    raise FileNotFoundError(f"{root}: expected one mesh file (or one *_mesh.ply), found {[p.name for p in files]}")


def _load_poses(traj) -> np.ndarray:
    if isinstance(traj, (str, Path)):
        p = Path(traj)
        return read_log(p)[1] if p.suffix == ".log" else load_trajectory(p)
    T = np.asarray(traj, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"trajectory must be (N, 4, 4), got {T.shape}")
    return T


class MeshRenderDataset(Dataset):
    """Depth rendered from a mesh along a trajectory."""

    kind = "mesh"

    def __init__(
        self,
        path=None,
        trajectory=None,
        K=None,
        size: tuple[int, int] | None = None,
        stride: int = 1,
        max_frames: int | None = None,
        noise=None,  # NoiseFn, or an object with .apply (KinectNoise)
        seed: int = 0,
        backend: str = "auto",
        mesh=None,
        name: str | None = None,
        fps: float = FPS,
    ):
        root = Path(path) if path is not None else None
        cam = None
        if mesh is None:
            if root is None:
                raise ValueError("give a mesh file or folder, or mesh=")
            self.mesh_path = root if root.is_file() else _find_mesh(root)
            self._mesh = None
            self.scene = MeshScene.from_file(self.mesh_path, backend=backend)
        else:
            self.mesh_path = None
            self._mesh = mesh
            self.scene = MeshScene.from_trimesh(mesh, backend=backend)
        if root is not None and root.is_dir():
            if trajectory is None:
                trajectory = next(iter(sorted(root.rglob("traj.txt"))), None) or next(
                    iter(sorted(root.rglob("*.log"))), None
                )
            cams = sorted(root.rglob("cam_params.json"))
            cam = json.loads(cams[0].read_text())["camera"] if cams else None
        if trajectory is None:
            raise FileNotFoundError(f"no trajectory given or found under {root}")
        poses = _load_poses(trajectory)
        self._index = np.arange(0, len(poses), stride)[:max_frames]
        self._poses = poses
        if K is None:
            K = intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"]) if cam else DEFAULT_K
        if size is None:
            size = (int(cam["h"]), int(cam["w"])) if cam else DEFAULT_SIZE
        self.K = np.asarray(K, dtype=np.float64)
        self.H, self.W = int(size[0]), int(size[1])
        self.noise, self.seed, self.fps = noise, seed, fps
        self.name = name or (root.stem if root is not None else "mesh")

    @classmethod
    def sniff(cls, path: Path) -> bool:
        if path.is_file():
            return path.suffix.lower() in MESH_SUFFIXES
        try:
            _find_mesh(path)
        except FileNotFoundError:
            return False
        return any(path.rglob("traj.txt"))

    def __len__(self) -> int:
        return len(self._index)

    def poses(self) -> np.ndarray:
        return self._poses[self._index].copy()

    def gt_mesh(self):
        return self._mesh if self._mesh is not None else super().gt_mesh()

    def render(self, T_WC: np.ndarray) -> np.ndarray:
        """Noise-free depth from any pose, (H, W) float32."""
        return self.scene.render_depth(self.K, T_WC, self.H, self.W)

    def _load(self, i):
        k = int(self._index[i])
        T = self._poses[k]
        depth = self.render(T)
        if hasattr(self.noise, "apply"):  # aisdf.synthetic.render.KinectNoise and the like
            depth = self.noise.apply(depth, self.K, cos_incidence=_cos_incidence(depth, self.K), key=(k,))
        elif self.noise is not None:
            depth = self.noise(depth, np.random.default_rng([self.seed, k]))
        return depth, T, k, k / self.fps


def _cos_incidence(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each pixel's ray and the depth image's normal (1 where
    the normal is undefined)."""
    n = normals_from_depth(depth, K)
    rays = ray_dirs_C(K, *depth.shape)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    c = np.abs(np.einsum("hwc,hwc->hw", n, rays))
    return np.where(np.isfinite(c), c, 1.0)
