"""Camera geometry on exact cases."""

import numpy as np

from aisdf import geometry as g
from aisdf.collision import chomp_cost


def test_backproject_known_pixels():
    K = g.intrinsics(100.0, 100.0, 2.0, 1.0)
    d = np.zeros((3, 5))
    d[1, 2] = 2.0  # the principal point
    d[0, 4] = 1.0
    P = g.backproject(d, K)
    np.testing.assert_allclose(P[1, 2], [0, 0, 2])
    np.testing.assert_allclose(P[0, 4], [0.02, -0.01, 1.0])
    assert np.isnan(P[0, 0]).all()


def test_transform_and_invert():
    c, s = np.cos(0.7), np.sin(0.7)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [1, 2, 3]
    p = np.array([[0.5, -1.0, 2.0]])
    np.testing.assert_allclose(g.transform(g.invert(T), g.transform(T, p)), p)
    np.testing.assert_allclose(g.invert(T) @ T, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(g.rotate(T, np.array([1.0, 0, 0])), [c, s, 0])


def test_normals_of_a_tilted_plane_face_the_camera():
    H, W = 40, 60
    K = g.intrinsics(50.0, 50.0, 29.5, 19.5)
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    # Plane n . p = -2 (2 m in front): depth = -2 / (n . ray)
    rays = g.ray_dirs_C(K, H, W)
    depth = -2.0 / (rays @ n_true)
    N = g.normals_from_depth(depth, K)
    inner = N[1:-1, 1:-1].reshape(-1, 3)
    np.testing.assert_allclose(inner, np.tile(n_true, (len(inner), 1)), atol=1e-9)
    assert np.isnan(N[0]).all() and np.isnan(N[:, -1]).all()


def test_normals_are_nan_across_depth_jumps():
    K = g.intrinsics(50.0, 50.0, 9.5, 9.5)
    d = np.full((20, 20), 2.0)
    d[:, 10:] = 4.0
    N = g.normals_from_depth(d, K)
    assert np.isnan(N[5, 9]).all() and np.isnan(N[5, 10]).all()
    np.testing.assert_allclose(N[5, 5], [0, 0, -1])


def test_normals_at_sampled_pixels_are_the_normal_image_there():
    """Training computes normals only at the pixels it samples (``normals_at``); they are the
    normal image's (``normals_from_depth``) to the bit, NaN where it is NaN: the border,
    invalid pixels and their neighbours, depth jumps; float32 depth as keyframes hold it."""
    rng = np.random.default_rng(3)
    H, W = 30, 40
    K = g.intrinsics(40.0, 42.0, 19.3, 14.8)
    n_true = np.array([0.2, -0.4, -1.0])
    depth = (-2.0 / (g.ray_dirs_C(K, H, W) @ (n_true / np.linalg.norm(n_true)))).astype(np.float32)
    depth += rng.normal(0, 0.003, depth.shape).astype(np.float32)  # noise: normals differ pixel to pixel
    depth[5:8, 10:14] = 0.0  # invalid
    depth[:, 25:] += 1.0  # a jump
    full = g.normals_from_depth(depth, K)
    v, u = np.mgrid[0:H, 0:W]
    at = g.normals_at(depth, K, v.ravel(), u.ravel())
    assert np.array_equal(at, full.reshape(-1, 3), equal_nan=True)
    assert np.isnan(at).any(axis=1).sum() > 2 * (H + W)  # border, hole and jump: some NaN
    pick = rng.integers(0, H * W, 50)  # any order, repeats
    assert np.array_equal(g.normals_at(depth, K, pick // W, pick % W), full.reshape(-1, 3)[pick], equal_nan=True)
    assert g.normals_at(depth, K, np.array([0]), np.array([0])).shape == (1, 3)


def test_chomp_cost_values():
    e = 2.0
    np.testing.assert_allclose(chomp_cost(np.array([-1.0, 0.0, 0.5, 2.0, 3.0]), e),
                               [2.0, 1.0, (0.5 - 2) ** 2 / 4, 0.0, 0.0])


def test_kdtree_survives_flush_to_zero_on_lattice_points():
    """``geometry.kdtree`` in a process where ``aisdf.network`` turned flush-to-zero on (as
    every service does): lattice points (a floor and a box at 0.1 m, which crash scipy's
    default balanced build there) build and answer nearest-point queries exactly. In a
    child process: a crash must fail this test, not end the test run."""
    import subprocess
    import sys

    code = """
import numpy as np
import aisdf.network  # noqa: F401  (turns flush-to-zero on)
from aisdf.geometry import kdtree
floor = np.stack(np.meshgrid(np.arange(-1, 1, 0.1), np.arange(-1, 1, 0.1), [0.0], indexing="ij"), -1)
box = np.stack(np.meshgrid(np.arange(0.2, 0.6, 0.1), np.arange(0.2, 0.6, 0.1), [0.4], indexing="ij"), -1)
P = np.concatenate([floor.reshape(-1, 3), box.reshape(-1, 3)])
q = np.random.default_rng(0).uniform(-1, 1, (500, 3))
d, i = kdtree(P).query(q)
brute = np.linalg.norm(q[:, None] - P[None], axis=2).min(1)
assert np.allclose(d, brute), np.abs(d - brute).max()
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", (r.returncode, r.stderr[-2000:])
