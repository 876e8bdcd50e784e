"""aisdf.synthetic: exact SDF values, raycast vs sphere tracing, rendering, trajectory,
noise statistics and determinism."""

from __future__ import annotations

import numpy as np
import pytest

from aisdf.geometry import backproject, transform
from aisdf.synthetic import (
    BUILDINGS, Boxes, KinectNoise, Room, Scene, SyntheticSequence, make_building,
    make_trajectory, nguyen_sigma, render_depth, render_depth_and_cos,
)
from aisdf.synthetic.buildings import PLANS, random_world_frame
from aisdf.synthetic.scene import rot_z


def box_room(T=np.eye(4), yaw=0.0) -> Scene:
    """4 x 3 x 2.5 m room with a 1 m cube centred at (2, 1.5, 0.5)."""
    room = Room(np.array([[0, 0], [4, 0], [4, 3], [0, 3]], dtype=float), 2.5)
    boxes = Boxes([[2.0, 1.5, 0.5]], [rot_z(yaw)], [[0.5, 0.5, 0.5]])
    return Scene(room, boxes, T)


def l_room() -> Scene:
    room = Room(np.array([[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]], dtype=float), 2.5)
    return Scene(room, Boxes(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))))


@pytest.fixture(scope="module")
def office() -> Scene:
    return make_building("office", 0)


def test_box_room_sdf_exact_values():
    pts = np.array([
        [1.0, 1.0, 1.0],    # beside the cube: 0.5 to its -x face
        [2.0, 1.5, 1.5],    # above the cube's top
        [2.8, 2.2, 1.3],    # off the cube's corner: sqrt(0.3^2 + 0.2^2 + 0.3^2)
        [2.0, 1.5, 0.8],    # inside the cube, 0.2 below its top
        [3.7, 0.5, 2.0],    # nearest is the x = 4 wall
        [-0.3, 1.0, 1.0],   # inside the x = 0 wall
        [-0.3, -0.4, 1.0],  # outside a vertical room edge: hypot(0.3, 0.4)
        [-0.3, -0.4, -1.2],  # outside a room corner
        [2.0, 2.5, 2.9],    # above the ceiling
    ])
    want = [0.5, 0.5, np.sqrt(0.22), -0.2, 0.3, -0.3, -0.5, -np.sqrt(0.25 + 1.44), -0.4]
    np.testing.assert_allclose(box_room().sdf(pts), want, atol=1e-12)
    # Same numbers in a tilted world frame.
    T = random_world_frame(5)
    np.testing.assert_allclose(box_room(T).sdf(transform(T, pts)), want, atol=1e-12)


def test_rotated_box_and_nonconvex_room_exact_values():
    s = box_room(yaw=np.radians(30))
    ax = rot_z(np.radians(30))
    p = np.array([2.0, 1.5, 0.5]) + np.array([1.0 * ax[:, 0], 0.6 * ax[:, 1] + 0.7 * ax[:, 0]])
    np.testing.assert_allclose(s.sdf(p), [0.5, np.hypot(0.2, 0.1)], atol=1e-12)
    pts = np.array([[1.5, 1.5, 1.0], [3.0, 3.0, 1.0], [2.5, 2.5, 1.0], [1.0, 3.0, 2.3], [3.0, 1.0, 0.2]])
    np.testing.assert_allclose(l_room().sdf(pts), [np.sqrt(0.5), -1.0, -0.5, 0.2, 0.2], atol=1e-12)


def test_gradient_unit_and_matches_central_differences(office):
    rng = np.random.default_rng(0)
    lo, hi = office.bounds()
    p = rng.uniform(lo, hi, (4000, 3))
    d, g = office.sdf_and_gradient(p)
    free = d > 1e-3
    assert free.sum() > 500
    np.testing.assert_allclose(np.linalg.norm(g[free], axis=1), 1.0, atol=1e-9)
    h = 1e-4
    fd = np.stack([(office.sdf(p[free] + h * e) - office.sdf(p[free] - h * e)) / (2 * h) for e in np.eye(3)], 1)
    # Equal except on the medial axis (a kink), a tiny share of random points.
    assert np.mean(np.linalg.norm(fd - g[free], axis=1) < 1e-5) > 0.97


def test_raycast_hand_values():
    s = box_room()
    o = np.array([[1.0, 1.5, 0.5], [1.0, 1.5, 0.5], [-1.0, 1.0, 1.0], [1.0, 1.0, 3.5], [2.0, 1.5, 0.5]])
    d = np.array([[1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    t, n = s.raycast(o, d, return_normals=True)
    # cube face; ceiling; wall from outside; ceiling from above; from inside the cube
    np.testing.assert_allclose(t, [0.5, 2.0, 1.0, 1.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(n, [[-1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, 0, 1], [0, 0, -1]], atol=1e-12)


def test_raycast_agrees_with_sphere_tracing(office):
    rng = np.random.default_rng(1)
    lo, hi = office.bounds()
    p = rng.uniform(lo, hi, (20000, 3))
    o = p[office.sdf(p) > 0.05][:400]
    d = rng.normal(size=o.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_rc = office.raycast(o, d)
    t = np.zeros(len(o))
    active = np.ones(len(o), bool)
    for _ in range(400):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        s = office.sdf(o[idx] + t[idx, None] * d[idx])
        t[idx] += np.maximum(s, 0.0)
        active[idx[s < 1e-9]] = False
    done = ~active
    assert done.mean() > 0.95
    assert np.all(np.isfinite(t_rc))
    np.testing.assert_allclose(t[done], t_rc[done], atol=1e-6)


def test_noiseless_depth_lies_on_surfaces():
    seq = SyntheticSequence("office", n_frames=120, H=120, W=160, noise=None, seed=0)
    for i in (0, 60, 119):
        f = seq.frame(i)
        assert f["depth"].dtype == np.float32 and f["depth"].shape == (120, 160)
        assert np.all(f["depth"] > 0)
        P = transform(f["T_WC"], backproject(f["depth"], f["K"]).reshape(-1, 3))
        assert np.abs(seq.gt_sdf(P)).max() < 1e-3


def test_world_up_not_axis_aligned_and_atlanta_truth():
    s = make_building("atlanta", 0)
    assert np.abs(s.up_W).max() < 0.95
    vert, hor = s.atlanta_truth()
    np.testing.assert_allclose(vert, s.up_W)
    np.testing.assert_allclose(np.linalg.norm(hor, axis=1), 1.0)
    np.testing.assert_allclose(hor @ vert, 0.0, atol=1e-12)
    ang = np.degrees(np.arccos(np.clip(np.abs(hor @ hor.T), 0, 1)))[np.triu_indices(len(hor), 1)]
    assert len(hor) >= 3 and ang.min() >= 29.9  # distinct (opposite normals merged)
    assert np.any(np.abs(ang - 90) > 20)  # non-orthogonal walls
    walls = s.atlanta_truth(include_solids=False)[1]
    assert len(walls) == 3  # hexagon: three wall directions, 60 degrees apart
    np.testing.assert_allclose(np.sort(np.degrees(np.arccos(np.abs(walls @ walls.T)))[0]), [0, 60, 60], atol=1e-6)
    assert np.allclose(make_building("atlanta", 0, "identity").up_W, [0, 0, 1])


@pytest.mark.parametrize("name", sorted(BUILDINGS))
def test_planes_and_mesh_lie_on_surfaces(name):
    s = make_building(name, 1)
    pl = s.planes_truth()
    assert np.abs(s.sdf(pl.center)).max() < 1e-9
    assert np.all(s.sdf(pl.center + 0.005 * pl.normal) > 0)  # normals point to free space
    assert np.all((pl.direction >= -2) & (pl.direction < len(s.atlanta_truth()[1])))
    assert np.sum(pl.direction == -1) >= 2 and np.all(pl.direction > -2)  # floor/ceiling; all Atlanta
    m = s.mesh()
    assert np.abs(s.sdf(m.vertices)).max() < 1e-9
    lo, hi = s.bounds()
    assert np.all(m.vertices >= lo - 1e-9) and np.all(m.vertices <= hi + 1e-9)
    assert np.all(hi - lo <= (30.0 if name in PLANS else 9.0))  # a floor is bigger than a room


@pytest.mark.parametrize("name,seed", [(n, 0) for n in sorted(BUILDINGS) if n not in PLANS] + [("office", 1), ("stairs", 2)])
def test_trajectory_clearance_height_and_smoothness(name, seed):
    s = make_building(name, seed)
    fps, speed = 30.0, 0.4
    T = make_trajectory(s, 450, seed, fps=fps, speed=speed)
    c = T[:, :3, 3]
    assert np.all(s.sdf(c) >= 0.4)
    h = (c - s.to_world(np.zeros((1, 3)))) @ s.up_W
    assert h.min() >= 1.2 and h.max() <= 1.5
    v = np.linalg.norm(np.diff(c, axis=0), axis=1) * fps
    assert np.all(np.abs(v - speed) < 0.05)
    R = T[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nij,nik->njk", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))) * fps
    assert ang.max() <= 30.0
    assert np.all(R[:, :, 1] @ -s.up_W > 0.85)  # camera y (down) ~ -up
    assert np.all(R[:, :, 2] @ -s.up_W > 0)  # looking slightly down


def test_noise_statistics_and_holes():
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1.0]])
    z = np.full((240, 320), 2.0)
    quiet = KinectNoise(blobs_per_frame=0, pixel_dropout=0, edge_px=0)
    n = quiet.apply(z, K, np.ones_like(z), key=(0,))
    assert np.all(n > 0)
    err = n - 2.0
    assert abs(err.std() / nguyen_sigma(2.0) - 1) < 0.1 and abs(err.mean()) < 1e-3
    # Disparity quantised to 1/8 px (f = 580 px, b = 7.5 cm): 1.15 cm steps at 2 m.
    disp8 = 8 * 580.0 * 0.075 / n.astype(np.float64)
    assert np.abs(disp8 - np.round(disp8)).max() < 1e-3
    assert quiet.depth_resolution(2.0) == pytest.approx(4 / (8 * 580 * 0.075))
    # Holes and range limits.
    ramp = np.tile(np.linspace(0.1, 8.0, 320), (240, 1))
    out = KinectNoise().apply(ramp, K, np.ones_like(ramp), key=(3,))
    valid = out > 0
    assert out.max() <= 5.0 and out[valid].min() >= 0.3
    inner = (ramp > 0.5) & (ramp < 4.5)
    assert 0.001 < np.mean(~valid[inner]) < 0.2
    graze = np.where(np.arange(320) < 160, 1.0, np.cos(np.radians(80)))[None].repeat(240, 0)
    g = KinectNoise().apply(z, K, graze, key=(4,))
    assert np.all(g[:, 160:] == 0) and np.mean(g[:, :160] > 0) > 0.8


def test_rendered_noise_holes_and_determinism():
    a = SyntheticSequence("office", n_frames=60, seed=3)
    b = SyntheticSequence("office", n_frames=60, seed=3)
    c = SyntheticSequence("office", n_frames=60, seed=4)
    np.testing.assert_array_equal(a.poses, b.poses)
    fa, fb = a.frame(10), b.frame(10)
    np.testing.assert_array_equal(fa["depth"], fb["depth"])
    np.testing.assert_array_equal(a.frame(10)["depth"], fa["depth"])  # order does not matter
    assert not np.array_equal(c.frame(10)["depth"], fa["depth"]) and not np.allclose(c.poses, a.poses)
    assert fa["stamp"] == pytest.approx(10 / 30) and fa["frame_id"] == 10
    assert SyntheticSequence(n_frames=2, noise=False).noise is None  # config flags
    assert SyntheticSequence(n_frames=2, noise=True).noise == KinectNoise()
    d = fa["depth"]
    assert d.max() <= 5.0 and 0 < np.mean(d == 0) < 0.3
    clean, cos = render_depth_and_cos(a.scene, fa["T_WC"], a.K, a.H, a.W)
    ok = d > 0
    assert np.all(cos[ok] >= np.cos(np.radians(78)) - 1e-9)
    rel = np.abs(d[ok] - clean[ok]) / nguyen_sigma(clean[ok])
    assert np.median(rel) < 1.5 and np.percentile(rel, 99.9) < 6


def test_render_matches_general_raycast(office):
    T = make_trajectory(office, 5, 0)[2]
    K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1.0]])
    depth = render_depth(office, T, K, 60, 80)
    from aisdf.geometry import ray_dirs_C
    d_C = ray_dirs_C(K, 60, 80).reshape(-1, 3)
    d_W = (d_C / np.linalg.norm(d_C, axis=1, keepdims=True)) @ T[:3, :3].T
    t = office.raycast(np.broadcast_to(T[:3, 3], d_W.shape), d_W)
    np.testing.assert_allclose(depth.ravel(), t / np.linalg.norm(d_C, axis=1), rtol=1e-6)
