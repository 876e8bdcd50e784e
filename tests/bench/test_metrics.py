"""The Table I metrics on analytic fields with known answers (isdf-reference.md)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from aisdf.datasets import open_dataset, require_data
from aisdf.datasets.raycast import MeshScene, open3d_available
from aisdf.geometry import intrinsics, invert, transform
from aisdf.metrics import (
    GridSDF,
    MeshSDF,
    collision_cost_error,
    eval_points,
    evaluate,
    gradient_cosine_distance,
    gt_gradient_central,
    sdf_error,
)

BACKENDS = ["numpy"] + (["open3d"] if open3d_available() else [])
RNG = np.random.default_rng(0)


def plane(n, offset=0.0):
    n = np.asarray(n, dtype=np.float64) / np.linalg.norm(n)
    return lambda p: p @ n - offset


def sphere_sdf(p, r=0.5):
    return np.linalg.norm(p, axis=1) - r


# --- the three metrics -------------------------------------------------------------------


def test_sdf_error_of_a_plane_shifted_by_3cm():
    pts = RNG.uniform(-1, 1, (1000, 3))
    gt, pred = plane([0, 0, 1]), plane([0, 0, 1], offset=0.03)
    assert sdf_error(pred(pts), gt(pts)) == pytest.approx(0.03, abs=1e-12)
    r = evaluate(pred, None, gt, None, pts)
    assert r["sdf_error_cm"] == pytest.approx(3.0, abs=1e-9)
    assert r["gradient_cosine_distance"] == pytest.approx(0.0, abs=1e-12)
    assert r["n_points"] == 1000 and r["n_gradient_points"] == int((pts[:, 2] >= 0).sum())


def test_collision_cost_error_by_hand():
    gt = np.array([-0.5, 0.5, 1.0, 3.0])
    pred = np.array([0.0, 1.0, 2.5, 1.0])
    # c(d) with e = 2: -d + 1 (d <= 0); (d - 2)^2 / 4 (0 < d <= 2); 0 beyond.
    c_gt = [1.5, 0.5625, 0.25, 0.0]
    c_pred = [1.0, 0.25, 0.0, 0.25]
    expect = np.mean(np.abs(np.subtract(c_pred, c_gt)))
    assert expect == 0.328125
    assert collision_cost_error(pred, gt, epsilon=2.0) == pytest.approx(expect, abs=1e-15)
    # Beyond epsilon both costs are 0, whatever the SDF error.
    assert collision_cost_error(np.array([2.5, 10.0]), np.array([5.0, 3.0])) == 0.0


@pytest.mark.parametrize("deg", [0.0, 10.0, 45.0, 90.0])
def test_gradient_distance_of_a_rotated_plane(deg):
    a = np.deg2rad(deg)
    gt, pred = plane([0, 0, 1]), plane([np.sin(a), 0, np.cos(a)])
    pts = RNG.uniform(0.1, 1, (500, 3))  # s >= 0 everywhere: all points count
    r = evaluate(pred, None, gt, None, pts)
    assert r["gradient_cosine_distance"] == pytest.approx(1 - np.cos(a), abs=1e-9)
    g = np.tile([np.sin(a), 0, np.cos(a)], (500, 1))
    assert gradient_cosine_distance(g, gt_gradient_central(gt, pts)) == pytest.approx(1 - np.cos(a), abs=1e-12)


def test_gradient_distance_respects_the_mask_and_ignores_scale():
    g1 = np.array([[1.0, 0, 0], [0, 2.0, 0], [1, 0, 0]])
    g2 = np.array([[3.0, 0, 0], [0, 0, 1.0], [-1, 0, 0]])
    assert gradient_cosine_distance(g1, g2) == pytest.approx((0 + 1 + 2) / 3)
    assert gradient_cosine_distance(g1, g2, valid=[True, True, False]) == pytest.approx(0.5)
    assert np.isnan(gradient_cosine_distance(g1, g2, valid=[False] * 3))


def test_central_differences_of_a_sphere():
    pts = RNG.normal(size=(200, 3))
    pts *= RNG.uniform(0.3, 2.0, (200, 1)) / np.linalg.norm(pts, axis=1, keepdims=True)
    g = gt_gradient_central(sphere_sdf, pts, h=0.01)
    np.testing.assert_allclose(g, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-3)


def test_evaluate_with_analytic_gradients_and_points_inside_walls():
    gt, pred = plane([0, 0, 1]), plane([0, 0, 1], offset=-0.05)
    pts = np.array([[0, 0, 1.0], [0, 0, 0.5], [0, 0, -0.05]])  # the last one is behind the wall
    r = evaluate(
        pred, lambda p: np.tile([0, 1.0, 0], (len(p), 1)), gt, lambda p: np.tile([0, 0, 1.0], (len(p), 1)), pts
    )
    assert r["sdf_error_m"] == pytest.approx(0.05)
    assert r["n_gradient_points"] == 2 and r["gradient_cosine_distance"] == pytest.approx(1.0)


# --- evaluation points -------------------------------------------------------------------


def _frames(n=11, H=20, W=30):
    K = intrinsics(20, 20, 14.5, 9.5)
    frames = []
    for i in range(n):
        depth = np.full((H, W), 2.0 + 0.1 * i, np.float32)
        depth[:, :5] = 0  # invalid columns
        T = np.eye(4)
        T[:3, 3] = [i, 0, 0]
        frames.append({"frame_id": i, "stamp": i / 30, "depth": depth, "K": K, "T_WC": T})
    return frames


@pytest.mark.parametrize("margin", [0.1, 0.0])
def test_eval_points_lie_on_seen_rays(margin):
    frames = _frames()
    pts = eval_points(frames, n_points=1000, every=5, rng=1, far_margin=margin)
    assert pts.shape == (1000, 3)
    # Frames 0, 5, 10 are used: 334 + 333 + 333 points, in that order.
    starts = {0: slice(0, 334), 5: slice(334, 667), 10: slice(667, 1000)}
    for i, sl in starts.items():
        f = frames[i]
        p = transform(invert(f["T_WC"]), pts[sl])
        D = f["depth"][0, -1]
        assert p[:, 2].min() >= 0.1 and p[:, 2].max() <= D + margin + 1e-9
        assert p[:, 2].max() > D + margin - 0.1  # uniform: reaches near the far end
        u = 20 * p[:, 0] / p[:, 2] + 14.5
        v = 20 * p[:, 1] / p[:, 2] + 9.5
        np.testing.assert_allclose(u, np.round(u), atol=1e-9)  # pixel centres
        np.testing.assert_allclose(v, np.round(v), atol=1e-9)
        assert np.round(u).min() >= 5  # only valid pixels
    assert np.mean(transform(invert(frames[0]["T_WC"]), pts[:334])[:, 2] > frames[0]["depth"][0, -1]) == pytest.approx(
        margin / (2.0 + margin - 0.1), abs=0.03 if margin else 0
    )


def test_eval_points_default_count_and_seed():
    frames = _frames(n=3)
    a = eval_points(frames, rng=7)
    assert a.shape == (200_000, 3)
    np.testing.assert_array_equal(a, eval_points(frames, rng=7))


# --- ground truth on a grid --------------------------------------------------------------


def test_grid_of_a_sphere_interpolates_closely():
    g = GridSDF.from_function(sphere_sdf, [[-0.8, -0.8, -0.8], [0.8, 0.8, 0.8]], voxel=0.01)
    assert g.values.shape == (161, 161, 161)
    p = RNG.uniform(-0.8, 0.8, (20000, 3))
    p = p[np.abs(np.linalg.norm(p, axis=1) - 0.5) < 0.3]  # away from the kink at the centre
    err = np.abs(g(p) - sphere_sdf(p))
    assert err.max() < 3e-4 and err.mean() < 5e-5  # trilinear error ~ h^2 / (8 r)
    near = (np.abs(sphere_sdf(p)) > 0.05) & g.inside_grid(p, pad=0.01)
    np.testing.assert_allclose(g.gradient(p[near]), p[near] / np.linalg.norm(p[near], axis=1, keepdims=True), atol=2e-3)
    # Exact at the nodes.
    nodes = np.array([[0.5, 0.0, 0.0], [0.0, -0.3, 0.2]])
    np.testing.assert_allclose(g(nodes), sphere_sdf(nodes), atol=1e-7)


def test_grid_masks_outside_and_inside_walls():
    g = GridSDF.from_function(plane([0, 0, 1]), [[0, 0, -0.5], [1, 1, 1]], voxel=0.05)
    pts = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, -0.2], [2.0, 0.5, 0.5], [0.5, 0.5, 0.995]])
    s = g(pts)
    assert s[0] == pytest.approx(0.5) and s[1] == pytest.approx(-0.2) and np.isnan(s[2])
    np.testing.assert_array_equal(g.gradient_mask(pts, h=0.01), [True, False, False, False])
    r = evaluate(plane([0, 0, 1], 0.02), None, g, None, pts)
    assert r["n_points"] == 3 and r["n_gradient_points"] == 1
    assert r["sdf_error_m"] == pytest.approx(0.02, abs=1e-6)
    unsigned = GridSDF(np.abs(g.values), g.origin, g.voxel, signed=False)
    assert unsigned.gradient_mask(pts[:2]).all()


def test_lazy_grid_computes_only_what_queries_touch():
    calls = []

    def fn(p):
        calls.append(len(p))
        return sphere_sdf(p)

    g = GridSDF.from_function(fn, [[-1, -1, -1], [1, 1, 1]], voxel=0.02, lazy=True)
    p = np.array([[0.1, 0.2, 0.3], [0.11, 0.2, 0.3]])
    np.testing.assert_allclose(g(p), sphere_sdf(p), atol=1e-3)
    assert sum(calls) <= 8 * 16**3 < g.values.size / 10
    full = GridSDF.from_function(sphere_sdf, [[-1, -1, -1], [1, 1, 1]], voxel=0.02)
    q = RNG.uniform(-1, 1, (5000, 3))
    np.testing.assert_array_equal(g(q), full(q))


@pytest.mark.parametrize("backend", BACKENDS)
def test_grid_from_a_closed_mesh_is_signed(backend, tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    g = GridSDF.from_mesh(mesh, voxel=0.02, margin=0.2, backend=backend, lazy=False)
    assert g.signed
    p = RNG.uniform(-0.65, 0.65, (5000, 3))
    # Facets of the icosphere lie up to ~2 mm inside the sphere; trilinear adds < 1 mm.
    assert np.abs(g(p) - sphere_sdf(p)).max() < 0.005
    assert np.all(np.sign(g(p))[np.abs(sphere_sdf(p)) > 0.01] == np.sign(sphere_sdf(p))[np.abs(sphere_sdf(p)) > 0.01])
    cached = GridSDF.from_mesh(mesh, voxel=0.05, backend=backend, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("gridsdf-*.npz"))) == 1
    again = GridSDF.from_mesh(mesh, voxel=0.05, backend=backend, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.values, cached.values)


def test_open_mesh_defaults_to_unsigned():
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    g = GridSDF.from_mesh(mesh, voxel=0.05, margin=0.3)
    assert not g.signed
    assert g(np.array([[0.2, 0.2, -0.1]]))[0] == pytest.approx(0.1, abs=1e-6)
    s = GridSDF.from_mesh(mesh, voxel=0.05, margin=0.3, sign="normal")
    assert s(np.array([[0.2, 0.2, -0.1]]))[0] == pytest.approx(-0.1, abs=1e-6)


def test_backends_agree_on_distances_with_sign_at_edges():
    assert len(BACKENDS) == 2, "open3d (a dev dependency) does not import: only the numpy backend"
    box = trimesh.creation.box(extents=[1, 2, 0.5])
    p = RNG.uniform(-1.5, 1.5, (3000, 3))
    a, b = (MeshScene.from_trimesh(box, backend=be).distance(p) for be in BACKENDS)
    np.testing.assert_allclose(a, b, atol=1e-6)
    # Exact box SDF (outside: distance to the box; inside: minus distance to the faces).
    q = np.abs(p) - [0.5, 1.0, 0.25]
    exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    np.testing.assert_allclose(a, exact, atol=1e-6)


def test_replica_office_ground_truth_along_real_rays():
    """The office scan is not watertight; its normals face the sensor, so sign="normal"
    gives free space positive. Real depth rays check it (isdf-reference: points in
    [0.1, D + 0.1])."""
    root = require_data("replica-office0-nvblox/replica")
    ds = open_dataset("replica", root / "office0")
    frames = [ds[0], ds[3]]
    pts = eval_points(frames, n_points=2000, every=1, rng=0, far_margin=0.0)
    g = GridSDF.from_mesh(ds.mesh_path, voxel=0.05, sign="normal")  # lazy: only blocks seen
    s = g(pts)
    assert np.isfinite(s).all()
    assert np.mean(s < -0.02) < 0.01  # in front of the measured depth: free space
    exact = MeshScene.from_file(ds.mesh_path).distance(pts, sign="normal")
    assert np.mean(exact < 0) < 0.005
    diff = np.abs(s - exact)
    assert np.median(diff) < 0.005 and np.quantile(diff, 0.95) < 0.03  # 5 cm grid, trilinear
    assert g._done.mean() < 0.5  # lazy: the blocks these two views touch


def test_mesh_sdf_matches_the_grid():
    mesh = trimesh.creation.box(extents=[1, 1, 1])
    exact = MeshSDF(mesh)
    grid = GridSDF.from_mesh(mesh, voxel=0.02, lazy=False)
    assert exact.signed and grid.signed
    p = RNG.uniform(-0.6, 0.6, (2000, 3))
    assert np.abs(exact(p) - grid(p)).max() < 0.01  # the grid's trilinear error at ridges
    np.testing.assert_array_equal(exact.gradient_mask(p), exact(p) >= 0)
    r = evaluate(exact, None, exact, None, p)
    assert r["sdf_error_m"] == 0 and r["n_gradient_points"] == int((exact(p) >= 0).sum())
