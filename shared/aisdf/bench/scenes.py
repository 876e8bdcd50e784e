"""The benchmark's scenes: a plain registry of factories, each giving a posed depth stream
and the field it is scored against.

* ``manhattan``, ``atlanta``, ``stairs``: the built-in synthetic buildings
  (``aisdf.synthetic``) with Kinect-like noise; ground truth is the exact analytic SDF and
  gradient. The world frame is tilted, so "up" is not a world axis.
* ``floor``: the synthetic multi-room floor (a corridor, seven rooms, a wing turned 42
  degrees), walked room by room; its ``n_frames`` are spread over the whole walk (about
  200 s: 600 frames = 3 fps) unless ``fps`` is given.
* ``replica-office``: the Replica office mesh rendered along its 2000-pose trajectory
  (``open_dataset("mesh")``) with ``KinectNoise``; ground truth is the mesh's signed
  distance (pseudo-normal sign: the mesh's normals face the rooms), either exact
  point-to-mesh (``MeshSDF``) or iSDF's 1 cm trilinear grid (``GridSDF``, cached).
* ``7scenes-redkitchen``: 250 real Kinect v1 frames. There is no mesh: the field is a
  *reference, not truth* (``reference.py``): all frames fused at high resolution, the
  unsigned distance to that surface, as iSDF did for ScanNet (points on [0.1, D]).

``make_scene(name, opts, data)`` -> ``BenchScene``. ``opts`` are the profile's options for
that scene (sizes, strides, ground-truth mode), ``data`` the shared data folder.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import intrinsics

SYNTHETIC = ("manhattan", "atlanta", "stairs", "floor")
REFERENCE_LABEL = "reference, not truth"


@dataclass
class BenchScene:
    """A stream of frames (``len``, ``frame(i)`` -> dict with frame_id, stamp, depth, K,
    T_WC) and the field it is evaluated against."""

    name: str
    frames: Any
    gt_sdf: Callable[[np.ndarray], np.ndarray]
    gt_grad: Callable[[np.ndarray], np.ndarray] | None  # None: central differences, 1 cm
    gt_kind: str  # "exact" | "mesh" | "reference"
    gt_label: str  # shown in every table and figure
    signed: bool
    up: np.ndarray  # (3,) world up, unit
    up_source: str
    bounds: np.ndarray  # (2, 3) world box holding the scene (voxel map, meshes)
    max_depth: float = 5.0
    info: dict = field(default_factory=dict)

    @property
    def far_margin(self) -> float:
        """Evaluation points on [0.1, D + 0.1] for a signed field, [0.1, D] for an unsigned one
        (isdf-reference.md: ReplicaCAD vs ScanNet)."""
        return 0.1 if self.signed else 0.0

    @property
    def is_reference(self) -> bool:
        return self.gt_kind == "reference"

    def __len__(self) -> int:
        return len(self.frames)

    def describe(self) -> dict:
        return {"name": self.name, "frames": len(self.frames), "ground_truth": self.gt_label, "gt_kind": self.gt_kind,
                "signed": self.signed, "eval_depth_range": f"[0.1, D + {self.far_margin}]",
                "up": np.round(self.up, 4).tolist(), "up_source": self.up_source,
                "bounds": np.round(self.bounds, 3).tolist(), **self.info}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def camera_up(poses: np.ndarray) -> np.ndarray:
    """Mean camera up (-y of the OpenCV camera) over poses (N, 4, 4): a rough world up."""
    return _unit(-np.asarray(poses)[:, :3, 1].mean(axis=0))


# ------------------------------------------------------------------ synthetic


def synthetic_scene(name: str, opts: dict, data: Path | None) -> BenchScene:
    from ..synthetic import PLANS, SyntheticSequence
    from ..synthetic.trajectory import walk_duration

    n_frames = int(opts.get("n_frames", 300))
    fps = 30.0 if name not in PLANS else n_frames / walk_duration(PLANS[name]())  # a walk: all of it
    seq = SyntheticSequence(building=name, n_frames=n_frames, H=int(opts.get("H", 120)),
                            W=int(opts.get("W", 160)), fps=float(opts.get("fps", fps)),
                            noise=bool(opts.get("noise", True)), seed=int(opts.get("scene_seed", 0)))
    lo, hi = seq.scene.bounds()
    return BenchScene(
        name, seq, seq.gt_sdf, seq.gt_gradient, "exact", "exact analytic SDF (synthetic)", True,
        seq.scene.up_W, "true (synthetic building)", np.stack([lo - 0.2, hi + 0.2]),
        info={"building": name, "size": f"{seq.W}x{seq.H}", "fps": seq.fps, "noise": "KinectNoise" if seq.noise
              else "none", "scene_seed": seq.seed})


# ------------------------------------------------------------------ Replica office (rendered)


def replica_office(name: str, opts: dict, data: Path | None) -> BenchScene:
    from ..datasets import open_dataset
    from ..metrics import GridSDF, MeshSDF
    from ..synthetic import KinectNoise

    root = _need(data, "replica-office0-nvblox")
    s = float(opts.get("scale", 0.25))  # image scale of the 1200x680 camera
    H, W = int(round(680 * s)), int(round(1200 * s))
    K = intrinsics(600 * s, 600 * s, (W - 1) / 2, (H - 1) / 2)
    noise = KinectNoise(seed=int(opts.get("scene_seed", 0))) if opts.get("noise", True) else None
    ds = open_dataset("mesh", root, K=K, size=(H, W), stride=int(opts.get("stride", 1)),
                      max_frames=opts.get("max_frames"), noise=noise, fps=30.0)
    mesh = ds.gt_mesh()
    if opts.get("gt_grid", False):  # iSDF's 1 cm trilinear grid, built once and cached
        gt = GridSDF.from_mesh(mesh, voxel=0.01, sign="normal", cache_dir=opts.get("cache_dir"),
                               lazy=opts.get("cache_dir") is None)
        label = "Replica mesh, signed, 1 cm grid"
    else:
        gt = MeshSDF(mesh, sign="normal")
        label = "Replica mesh, signed, exact point-to-mesh"
    # Stamps follow the original 30 fps poses when strided: pose k at k / 30 s.
    return BenchScene(
        name, ds, gt, gt.gradient, "mesh", label, True, np.array([0.0, 0.0, 1.0]), "mesh z axis (Replica is z-up)",
        np.stack([mesh.bounds[0] - 0.1, mesh.bounds[1] + 0.1]),
        info={"size": f"{W}x{H}", "stride": int(opts.get("stride", 1)), "noise": "KinectNoise" if noise else "none",
              "mesh": str(ds.mesh_path)})


# ------------------------------------------------------------------ 7-Scenes RedKitchen (real)


def sevenscenes_redkitchen(name: str, opts: dict, data: Path | None) -> BenchScene:
    from ..datasets import open_dataset
    from ..metrics import GridSDF, MeshSDF
    from .reference import fused_reference_mesh

    root = _need(data, "7scenes-redkitchen")
    ds = open_dataset("7scenes", root / "data" if (root / "data").is_dir() else root)
    voxel = float(opts.get("reference_voxel", 0.01))
    mesh, ref_info = fused_reference_mesh(ds, voxel=voxel, cache_dir=opts.get("cache_dir"))
    if opts.get("gt_grid", False):
        gt = GridSDF.from_mesh(mesh, voxel=0.01, sign="unsigned", cache_dir=opts.get("cache_dir"),
                               lazy=opts.get("cache_dir") is None)
    else:
        gt = MeshSDF(mesh, sign="unsigned")
    up, up_src = camera_up(ds.poses()), "mean camera -y"
    grav = (root / "data" / "gravity-direction.txt", root / "gravity-direction.txt")
    for g in grav:
        if g.exists():  # gravity points down; its sign is checked against the cameras
            u = -_unit(np.loadtxt(g).ravel()[:3])
            up, up_src = (u if u @ up > 0 else -u), f"-{g.name} (sign checked against the cameras)"
            break
    label = (f"{REFERENCE_LABEL}: TSDF fusion of all {len(ds)} frames at {100 * voxel:g} cm, "
             "unsigned distance to its surface")
    b = np.asarray(mesh.bounds)
    opts_frames = opts.get("max_frames")
    frames = _Head(ds, int(opts_frames)) if opts_frames else ds
    return BenchScene(name, frames, gt, gt.gradient, "reference", label, False, up, up_src,
                      np.stack([b[0] - 0.2, b[1] + 0.2]), max_depth=5.0,
                      info={"size": f"{ds.W}x{ds.H}", "reference": ref_info, "path": str(ds.root)})


class _Head:
    """The first ``n`` frames of a dataset (the reference still uses all of them)."""

    def __init__(self, ds, n: int):
        self.ds, self.n = ds, min(n, len(ds))

    def __len__(self) -> int:
        return self.n

    def frame(self, i: int) -> dict:
        if not 0 <= i < self.n:
            raise IndexError(i)
        return self.ds.frame(i)

    def poses(self) -> np.ndarray:
        return self.ds.poses()[: self.n]


def _need(data: Path | None, sub: str) -> Path:
    from ..datasets import DataMissingError

    if data is None:
        raise DataMissingError(f"scene needs the shared data folder ({sub}); set AISDF_DATA or pass --data")
    p = Path(data) / sub
    if not p.is_dir() or not any(p.iterdir()):
        raise DataMissingError(f"{p} is missing or empty")
    return p


SCENES: dict[str, Callable[[str, dict, Path | None], BenchScene]] = {
    "manhattan": synthetic_scene,
    "atlanta": synthetic_scene,
    "stairs": synthetic_scene,
    "floor": synthetic_scene,
    "replica-office": replica_office,
    "7scenes-redkitchen": sevenscenes_redkitchen,
}


def make_scene(name: str, opts: dict | None = None, data: Path | None = None) -> BenchScene:
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    return SCENES[name](name, dict(opts or {}), data)
