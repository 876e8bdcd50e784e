"""The measured surface (``aisdf.structure.measured``): depth pixels pooled into voxels, and
the answer that moves the fused answer to the surfel distance where nothing was measured
nearer and caps it at the nearest measured point. Exact values on constructed cases."""

from __future__ import annotations

import numpy as np
import pytest

from aisdf.structure.measured import MeasuredPoints, MeasuredSurface, measured_fuse, measured_fuse_grad

K = np.array([[40.0, 0, 20.0], [0, 40.0, 15.0], [0, 0, 1]])


def _wall(z=2.0, H=30, W=40):
    return np.full((H, W), z, np.float32)


def test_pixels_pool_into_voxel_means_and_counts():
    m = MeasuredSurface(voxel=0.1, min_hits=3)
    depth = _wall()
    depth[0, :5] = 0.0  # no return
    depth[1, :5] = np.nan
    depth[2, :5] = 50.0  # beyond max_depth
    n = m.add(depth, K, np.eye(4))
    assert n == 40 * 30 - 15 and int(m.counts.sum()) == n
    pts = m.points()
    assert len(pts) == int((m.counts >= 3).sum()) < len(m)  # voxels with fewer than 3 pixels left out
    assert np.allclose(pts[:, 2], 2.0)  # every pixel on the wall: the means are on it too
    keys, counts, means = m.keys.copy(), m.counts.copy(), m.sums / m.counts[:, None]
    assert m.add(depth, K, np.eye(4)) == n  # the same view again: same voxels, twice the pixels, same means
    assert np.array_equal(m.keys, keys) and np.array_equal(m.counts, 2 * counts)
    assert np.allclose(m.sums / m.counts[:, None], means)
    assert len(m.points()) == int((counts >= 2).sum())  # now 2 pixels were enough for 3 hits


def test_moved_camera_and_distance_to_the_nearest_point():
    m = MeasuredSurface(voxel=0.1, min_hits=1)
    T = np.eye(4)
    T[:3, 3] = [5.0, -1.0, 0.5]  # the wall at z = 2 in the camera is at z = 2.5 in the world
    m.add(_wall(), K, T)
    pts = m.points()
    assert np.allclose(pts[:, 2], 2.5)
    q = pts[7] + np.array([0.0, 0.0, 1.25])  # straight out of the wall from one voxel's point
    assert m.distance(q[None])[0] == pytest.approx(1.25, abs=1e-9)
    assert np.isinf(MeasuredSurface().distance(q[None])[0])  # nothing measured: no bound


def test_state_round_trip_message_and_bad_state():
    """A checkpoint's pool (``state_dict``) comes back equal, adding more continues as if never
    saved; ``message`` is the protocol's map, rebuilt after a change; a state whose arrays do
    not fit together is refused."""
    m = MeasuredSurface(voxel=0.1, min_hits=2, max_depth=5.0)
    m.add(_wall(), K, np.eye(4))
    msg = m.message()
    assert msg["voxel"] == 0.1 and msg["points"].dtype == np.float32 and m.message() is msg  # cached
    np.testing.assert_array_equal(msg["points"], m.points().astype(np.float32))
    back = MeasuredSurface.from_state_dict(m.state_dict())
    assert (back.voxel, back.min_hits, back.max_depth) == (0.1, 2, 5.0)
    T = np.eye(4)
    T[:3, 3] = [0.03, 0.0, 0.1]
    for x in (m, back):
        x.add(_wall(), K, T)
    assert m.message() is not msg  # a change builds it again
    for a in ("keys", "sums", "counts"):
        np.testing.assert_array_equal(getattr(back, a), getattr(m, a))
    np.testing.assert_array_equal(back.message()["points"], m.message()["points"])
    bad = m.state_dict()
    bad["keys"] = bad["keys"][::-1]  # not sorted
    with pytest.raises(ValueError, match="sorted"):
        MeasuredSurface.from_state_dict(bad)
    bad = m.state_dict()
    bad["counts"] = bad["counts"][:-1]
    with pytest.raises(ValueError):
        MeasuredSurface.from_state_dict(bad)


def test_bad_input_is_refused_and_changes_nothing():
    m = MeasuredSurface()
    m.add(_wall(), K, np.eye(4))
    keys, sums = m.keys.copy(), m.sums.copy()
    with pytest.raises(ValueError):
        m.add(_wall(), np.eye(4), np.eye(4))  # K not 3x3
    with pytest.raises(ValueError):
        m.add(_wall(), K, np.full((4, 4), np.nan))
    with pytest.raises(ValueError):
        m.add(np.zeros(5), K, np.eye(4))
    with pytest.raises(ValueError):
        MeasuredSurface(voxel=0)
    assert np.array_equal(m.keys, keys) and np.array_equal(m.sums, sums)


def test_the_answer_rule_exactly():
    # Columns: a surfel 1 m away, the network (and so the fused answer) at 0.8 m ...
    fused = np.array([0.8, 0.8, 0.8, -0.1, 2.5, 0.7])
    sdf_i = np.array([0.8, 0.8, 0.8, -0.1, 2.5, 0.7])
    d_e = np.array([1.0, 1.0, 1.0, 1.0, 3.0, np.inf])
    # ... nothing measured nearer than the surfel; furniture measured at 0.5 m; a point half
    # way into the margin; inside (the network is negative); the surfel beyond 2 m; no surfel.
    d_m = np.array([1.0, 0.5, 0.975, 0.3, 2.8, np.inf])
    a = measured_fuse(fused, sdf_i, d_e, d_m, margin=0.05, slack=0.01, radius=2.0)
    assert a == pytest.approx([1.0, 0.51, 0.9, -0.1, 2.5, 0.7], abs=1e-12)
    # Signed surfel distances count as unsigned (behind a one-sided surfel is not inside).
    assert measured_fuse(fused, sdf_i, -d_e, d_m)[0] == pytest.approx(1.0)
    # Continuous in the measured distance: the weight goes linearly over the margin.
    dm = np.linspace(0.9, 1.1, 401)
    v = measured_fuse(np.full(401, 0.8), np.full(401, 0.8), np.ones(401), dm)
    assert np.max(np.abs(np.diff(v))) < 0.01


def _scene(x):
    """A floor surfel (z = 0), a network that is smooth and mostly below the floor distance,
    and a measured "box" standing on the floor (points nobody put in the surfel map)."""
    sdf_i = 0.8 * x[:, 2] + 0.05 * np.sin(3 * x[:, 0]) + 0.02
    g_i = np.stack([0.15 * np.cos(3 * x[:, 0]), np.zeros(len(x)), np.full(len(x), 0.8)], 1)
    d_e, g_e = x[:, 2].copy(), np.tile([0.0, 0.0, 1.0], (len(x), 1))  # signed, as explicit_sdf gives
    return sdf_i, g_i, d_e, g_e


def _answer(x, pts):
    from aisdf.structure.fusion import fuse

    sdf_i, g_i, d_e, g_e = _scene(x)
    f, g, _ = fuse(sdf_i, g_i, d_e, g_e, 2.0)
    d_m, g_m = pts.nearest(x)
    return measured_fuse_grad(f, g, sdf_i, d_e, g_e, d_m, g_m), (f, sdf_i, d_e, d_m)


def test_the_rule_s_gradient_is_the_derivative_of_its_value():
    rng = np.random.default_rng(0)
    floor = np.stack(np.meshgrid(np.arange(-1, 1, 0.1), np.arange(-1, 1, 0.1), [0.0], indexing="ij"), -1)
    box = np.stack(np.meshgrid(np.arange(0.2, 0.6, 0.1), np.arange(0.2, 0.6, 0.1), [0.4], indexing="ij"), -1)
    pts = MeasuredPoints(np.concatenate([floor.reshape(-1, 3), box.reshape(-1, 3)]))
    x = rng.uniform([-0.8, -0.8, -0.1], [0.8, 0.8, 1.0], (4000, 3))
    (f, g), (fused, sdf_i, d_e, d_m) = _answer(x, pts)
    assert np.allclose(f, measured_fuse(fused, sdf_i, d_e, d_m))  # the same values as the values-only rule
    h, smooth = 1e-5, np.ones(len(x), bool)
    fd = np.zeros_like(g)
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fp, fm = _answer(x + e, pts)[0][0], _answer(x - e, pts)[0][0]
        fd[:, a] = (fp - fm) / (2 * h)
        # Compare only where no switch of the rule (or of the nearest point) lies within h:
        # there the second difference is ~h^2, at a kink ~h.
        smooth &= np.abs(fp - 2 * f + fm) < 1e-8
    assert smooth.mean() > 0.8, smooth.mean()
    err = np.linalg.norm(fd - g, axis=1)
    assert err[smooth].max() < 1e-4, err[smooth].max()
    # The rule does what it says: the box's points pull answers above it down, the floor
    # surfel answers where nothing was measured nearer, inside keeps the network.
    above_box = np.array([[0.4, 0.4, 0.6]])
    (fb, gb), _ = _answer(above_box, pts)
    assert fb[0] == pytest.approx(0.2 + 0.01, abs=1e-9) and np.allclose(gb[0], [0, 0, 1])
    open_floor = np.array([[-0.5, -0.5, 0.3]])
    (fo, go), _ = _answer(open_floor, pts)
    assert fo[0] == pytest.approx(0.3, abs=1e-9) and np.allclose(go[0], [0, 0, 1])
    below = np.array([[-0.5, -0.5, -0.05]])
    (fi, _), (fu, si, _, _) = _answer(below, pts)
    assert si[0] < 0 and fi[0] == fu[0]
    assert np.isinf(MeasuredPoints(np.zeros((0, 3))).nearest(above_box)[0][0])
    with pytest.raises(ValueError):
        MeasuredPoints(np.array([[0.0, np.nan, 0.0]]))


def _plane_depth(n, c, T_WC, Kc, H, W, rng, sigma):
    """Depth of the plane n . x = c seen from T_WC, with Kinect-like noise ``sigma(d)``."""
    v, u = np.mgrid[0:H, 0:W]
    rays_c = np.stack([(u - Kc[0, 2]) / Kc[0, 0], (v - Kc[1, 2]) / Kc[1, 1], np.ones((H, W))], -1)
    rays_w = rays_c @ T_WC[:3, :3].T
    t = (c - T_WC[:3, 3] @ n) / (rays_w @ n)
    d = np.where(t > 0, t, 0.0)
    return (d + rng.normal(0, 1, d.shape) * sigma(d)).astype(np.float32)


def test_a_noisy_wall_s_points_lie_on_it_not_where_the_noise_tails_spill_into_the_voxels_around_it():
    from aisdf.mapper.clearing import depth_sigma
    rng = np.random.default_rng(0)
    Kc = np.array([[160.0, 0, 80], [0, 160.0, 60], [0, 0, 1]])
    n = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])  # a wall 17 degrees off the view, 4 m away
    m = MeasuredSurface()
    for i in range(10):
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.05 * i, 0.0]
        m.add(_plane_depth(n, 4.0, T, Kc, 120, 160, rng, depth_sigma), Kc, T)
    ok = m.counts >= m.min_hits
    off_own = np.abs((m.sums[ok] / m.counts[ok, None]) @ n - 4.0)
    off = np.abs(m.points() @ n - 4.0)
    # measured 2026-12-05: 35 % of the voxels' own means more than 3 cm off the wall, 0.9 % of the
    # points; on average 2.4 cm and 0.3 cm off
    assert np.mean(off_own > 0.03) > 0.1, np.mean(off_own > 0.03)
    assert np.mean(off > 0.03) <= 0.03 and np.mean(off) < 0.5 * np.mean(off_own), (np.mean(off > 0.03), np.mean(off))


def test_a_thin_post_and_a_box_s_edges_keep_their_own_means():
    # a post 4 cm wide before a wall, and a step: points off a plane's flat neighbourhood are not pulled
    m = MeasuredSurface(min_hits=1)
    d = _wall(3.0, H=120, W=160)
    d[:, 78:81] = 1.5  # the post: 3 pixels at 1.5 m (4 cm)
    Kc = np.array([[120.0, 0, 80], [0, 120.0, 60], [0, 0, 1]])
    m.add(d, Kc, np.eye(4))
    own = m.sums / m.counts[:, None]
    pts = m.voxel_points()
    post = own[:, 2] < 2.0
    assert post.sum() >= 5 and np.allclose(pts[post], own[post])  # the post is no plane: untouched
    assert np.allclose(pts[~post][:, 2], 3.0)  # the wall: on it


def test_the_points_kept_up_to_date_are_those_computed_afresh():
    from aisdf.structure.measured import surface_points
    rng = np.random.default_rng(1)
    Kc = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    m = MeasuredSurface(min_hits=1)
    for i in range(6):
        T = np.eye(4)
        T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
        d = (rng.uniform(1.5, 3.5) + rng.normal(0, 0.02, (60, 80))).astype(np.float32)
        d[rng.random((60, 80)) < 0.2] = 0.0
        m.add(d, Kc, T)
        m.points()  # computed now: later changes update it in place
        if i % 2:
            m.remove(rng.random(len(m)) < 0.1)
        assert np.allclose(m.voxel_points(), surface_points(m.keys, m.sums, m.counts, m.voxel))
    assert np.allclose(MeasuredSurface.from_state_dict(m.state_dict()).points(), m.points())
