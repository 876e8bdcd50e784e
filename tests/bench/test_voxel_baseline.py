"""The TSDF/ESDF voxel baseline (aisdf.bench.voxel) against exact distances."""

from __future__ import annotations

import numpy as np
import pytest

import open3d  # noqa: F401,E402 - the baseline needs it; installed by the dev extra

from aisdf.bench.voxel import VoxelEsdf  # noqa: E402
from aisdf.geometry import intrinsics, ray_dirs_C, transform  # noqa: E402
from aisdf.synthetic import SyntheticSequence  # noqa: E402

VOXEL = 0.055


def _tilted_pose() -> np.ndarray:
    a, b = np.radians(30.0), np.radians(-20.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz @ Rx, [0.7, -1.3, 0.4]
    return T


@pytest.mark.parametrize("T_WC", [np.eye(4), _tilted_pose()], ids=["identity", "tilted"])
def test_fronto_parallel_wall(T_WC):
    """A wall at z = 2 m filling the view: ESDF 0.5 and 1.0 m in front of it, negative behind."""
    H, W = 60, 80
    K = intrinsics(50.0, 50.0, (W - 1) / 2, (H - 1) / 2)
    m = VoxelEsdf(voxel_size=VOXEL)
    m.integrate(np.full((H, W), 2.0, np.float32), K, T_WC)
    m.finalize()
    pts_C = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 1.0], [0.2, -0.1, 1.0], [0.0, 0.0, 2.05]])
    pts_W = transform(T_WC, pts_C)
    np.testing.assert_allclose(m.sdf(pts_W)[:3], [0.5, 1.0, 1.0], atol=VOXEL)
    assert -VOXEL < m.sdf(pts_W)[3] < 0
    assert m.observed(pts_W).all()
    normal_W = T_WC[:3, :3] @ np.array([0.0, 0.0, -1.0])  # towards the camera: free space
    assert np.all(m.gradient(pts_W[:2]) @ normal_W > 0.95)
    V, F = m.mesh()
    assert len(F) > 0
    np.testing.assert_allclose(transform(np.linalg.inv(T_WC), V)[:, 2], 2.0, atol=0.01)


def _ray_points(frames, n_per_frame: int, rng) -> np.ndarray:
    """Points along seen rays: random valid pixels, z-depth uniform in [0.1, D + 0.1]."""
    out = []
    for f in frames:
        v, u = np.nonzero(f["depth"] > 0)
        s = rng.integers(0, len(v), n_per_frame)
        D = f["depth"][v[s], u[s]]
        z = rng.uniform(0.1, D + 0.1)
        dirs_C = ray_dirs_C(f["K"], *f["depth"].shape)[v[s], u[s]]
        out.append(transform(f["T_WC"], dirs_C * z[:, None]))
    return np.concatenate(out)


@pytest.fixture(scope="module")
def office():
    seq = SyntheticSequence(building="office", n_frames=300, H=120, W=160, seed=0, noise=None)
    frames = [seq.frame(i) for i in range(0, 300, 6)]  # 50 frames
    points = _ray_points(frames, 400, np.random.default_rng(0))
    return seq, frames, points, seq.gt_sdf(points)


def test_office_accuracy_and_voxel_size(office):
    seq, frames, points, gt = office
    fine = VoxelEsdf.from_frames(frames, voxel_size=VOXEL)
    coarse = VoxelEsdf.from_frames(frames, voxel_size=0.10)
    err_fine = np.abs(fine.sdf(points) - gt).mean()
    err_coarse = np.abs(coarse.sdf(points) - gt).mean()
    assert err_fine < 0.06  # measured 4.4 cm
    assert err_coarse > err_fine + 0.01  # measured 8.7 cm
    free = gt > 0.2
    assert np.mean(fine.sdf(points[free]) > 0) > 0.995
    assert fine.observed(points).mean() > 0.95
    # the mesh lies on the true surfaces, and every timing was recorded
    V, F = fine.mesh()
    assert len(F) > 1000 and np.abs(seq.gt_sdf(V)).mean() < VOXEL / 2
    t = fine.timing_summary()
    assert t["frames"] == 50 and len(fine.timings["integrate_ms"]) == 50 and t["finalize_ms"] > 0


def test_bounds_limit_the_grid(office):
    seq, frames, points, gt = office
    lo, hi = seq.scene.bounds()
    mid = (lo + hi) / 2
    bounds = np.stack([lo, np.r_[mid[0], hi[1:]]])
    m = VoxelEsdf.from_frames(frames, voxel_size=0.1, bounds=bounds)
    esdf, origin = m.grid()
    far_corner = origin + (np.array(esdf.shape) - 1) * 0.1
    assert np.all(origin >= bounds[0] - 0.2) and np.all(far_corner <= bounds[1] + 0.2)
    # surfaces outside the box are not mapped: only points near a surface inside it keep their accuracy
    near = np.all((points >= bounds[0] + 0.3) & (points <= bounds[1] - 0.3), axis=1) & (np.abs(gt) < 0.2)
    assert near.sum() > 500 and np.abs(m.sdf(points[near]) - gt[near]).mean() < 0.1  # one 10 cm voxel


def test_finalize_needs_frames():
    with pytest.raises(RuntimeError):
        VoxelEsdf().finalize()
    with pytest.raises(RuntimeError):
        VoxelEsdf().sdf(np.zeros((1, 3)))
