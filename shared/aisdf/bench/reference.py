"""A reference surface for real scans with no ground-truth mesh (7-Scenes): every frame
fused at high resolution with Open3D's TSDF (``VoxelBlockGrid``), marching cubes, kept
as a mesh; the benchmark scores against the *unsigned* distance to it, as iSDF did for
ScanNet. It is a reference, not truth: it carries the sensor's noise and the poses'
1-2 cm error, and it has holes where no frame looked.

The mesh is cached (``cache_dir``) as a .ply keyed by the frames' files, poses and the
fusion options, so a benchmark builds it once.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from ..geometry import invert

TRUNC_VOXELS = 4.0
WEIGHT_THRESHOLD = 3.0  # voxels seen by fewer frames are left out of the surface


def _key(ds, voxel: float, max_depth: float) -> str:
    h = hashlib.sha1()
    h.update(f"{type(ds).__name__}|{getattr(ds, 'root', '')}|{len(ds)}|{voxel}|{max_depth}|{TRUNC_VOXELS}|"
             f"{WEIGHT_THRESHOLD}".encode())
    h.update(np.ascontiguousarray(ds.poses(), dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def fuse_frames(frames, voxel: float = 0.01, max_depth: float = 4.0):
    """TSDF-fuse an iterable of frame dicts (depth, K, T_WC); returns a trimesh.Trimesh."""
    import open3d as o3d
    import open3d.core as o3c
    import trimesh

    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)), voxel, 16,
                                        60_000, o3c.Device("CPU:0"))
    n = 0
    for f in frames:
        depth = np.where((f["depth"] > 0) & (f["depth"] <= max_depth), f["depth"], 0.0).astype(np.float32)
        img = o3d.t.geometry.Image(o3c.Tensor(depth))
        K = o3c.Tensor(np.asarray(f["K"], np.float64))
        T_CW = o3c.Tensor(invert(np.asarray(f["T_WC"], np.float64)))
        blocks = vbg.compute_unique_block_coordinates(img, K, T_CW, 1.0, max_depth, TRUNC_VOXELS)
        vbg.integrate(blocks, img, K, T_CW, 1.0, max_depth, TRUNC_VOXELS)
        n += 1
    if n == 0:
        raise ValueError("no frames to fuse")
    m = vbg.extract_triangle_mesh(weight_threshold=min(WEIGHT_THRESHOLD, float(n)))
    V = m.vertex.positions.numpy().astype(np.float64)
    F = m.triangle.indices.numpy().astype(np.int64)
    if not len(F):
        raise RuntimeError("the fused reference has no surface")
    return trimesh.Trimesh(V, F, process=False)


def fused_reference_mesh(ds, voxel: float = 0.01, max_depth: float = 4.0, cache_dir=None):
    """(trimesh, info) for all frames of dataset ``ds``; cached under ``cache_dir``."""
    import trimesh

    info = {"method": "open3d VoxelBlockGrid TSDF fusion of all frames, marching cubes", "frames": len(ds),
            "voxel_m": voxel, "trunc_voxels": TRUNC_VOXELS, "weight_threshold": WEIGHT_THRESHOLD,
            "max_depth_m": max_depth, "label": "reference, not truth"}
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"reference-{_key(ds, voxel, max_depth)}.ply"
        if path.exists():
            mesh = trimesh.load(path, force="mesh", process=False)
            info.update(cached=str(path), faces=len(mesh.faces))
            return mesh, info
    t = time.perf_counter()
    mesh = fuse_frames((ds.frame(i) for i in range(len(ds))), voxel, max_depth)
    info.update(build_s=round(time.perf_counter() - t, 1), faces=len(mesh.faces))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        mesh.export(path)
        path.with_suffix(".json").write_text(json.dumps(info, indent=2))
        info["cached"] = str(path)
    return mesh, info
