"""The baked field (aisdf.baked) and observed space (aisdf.observed): exactness on linear
fields, C^1 continuity across block and level borders, accuracy against a known smooth
field, the coarse-to-fine budget, observed flags against the keyframes' frusta, and the
query engine's planner fields (radii, observed, exact) and bake swap."""

import numpy as np
import pytest
import torch

from aisdf import protocol, query_messages
from aisdf.baked import BakeConfig, bake
from aisdf.geometry import backproject, invert, transform
from aisdf.observed import ObservedGrid, ObservedSpace
from aisdf.synthetic import SyntheticSequence
from helpers.small_map import train_small_map

torch.set_num_threads(1)


def box_grid(lo=(-1.0, -2.0, 0.3), shape=(40, 30, 20), voxel=0.1, inner=((5, 35), (3, 27), (2, 18))):
    occ = np.zeros(shape, bool)
    occ[inner[0][0]:inner[0][1], inner[1][0]:inner[1][1], inner[2][0]:inner[2][1]] = True
    return ObservedGrid(np.array(lo), voxel, occ)


def inside_points(grid, n, rng):
    occ = np.argwhere(grid.occ)
    lo = grid.origin + occ.min(0) * grid.voxel
    hi = grid.origin + (occ.max(0) + 1) * grid.voxel
    return rng.uniform(lo, hi, (n, 3))


def plane_fn(n, c):
    n = np.asarray(n, float) / np.linalg.norm(n)
    return n, lambda p: ((p @ n - c).astype(np.float32), np.tile(n, (len(p), 1)).astype(np.float32))


def smooth_fn(p):
    """SDF of a sphere (radius 0.8 near (1, 0, 1)) plus a gentle wave: smooth, curved, with a
    surface through the box, value and gradient known exactly."""
    p = np.asarray(p, np.float64)
    c = np.array([1.013, 0.007, 1.021])  # off every lattice point
    d = p - c
    r = np.linalg.norm(d, axis=1)
    f = r - 0.8 + 0.02 * np.sin(3 * p[:, 0]) * np.cos(2 * p[:, 1])
    g = d / r[:, None]
    g[:, 0] += 0.06 * np.cos(3 * p[:, 0]) * np.cos(2 * p[:, 1])
    g[:, 1] += -0.04 * np.sin(3 * p[:, 0]) * np.sin(2 * p[:, 1])
    return f.astype(np.float32), g.astype(np.float32)


def test_exact_on_a_linear_field_and_a_planes_sdf():
    rng = np.random.default_rng(0)
    grid = box_grid()
    for normal, c in (([0.3, -0.5, 0.8], 0.2), ([0.0, 0.0, 1.0], 1.0), ([1.0, 2.0, -0.5], -0.7)):
        n, fn = plane_fn(normal, c)
        for cfg in (BakeConfig(), BakeConfig(near_surface=True, fine=4)):
            fld = bake(fn, grid, cfg)
            # A plane is linear: nothing to refine, unless asked to refine near surfaces.
            assert (fld.stats["fine_blocks"] > 0) == cfg.near_surface
            p = inside_points(grid, 50_000, rng)
            f, g, cov = fld.query(p)
            assert cov.all()
            np.testing.assert_allclose(f, p @ n - c, atol=3e-6)
            np.testing.assert_allclose(g, np.tile(n, (len(p), 1)), atol=3e-5)
            f2, g2, _ = fld.query(p, gradient=False)
            assert g2 is None
            np.testing.assert_array_equal(f2, f)


def test_a_linear_field_far_from_zero_is_exact_on_the_coarse_level():
    rng = np.random.default_rng(1)
    grid = box_grid()
    n, fn = plane_fn([0.2, 0.1, 1.0], -30.0)  # far above 0 everywhere: no fine level at all
    fld = bake(fn, grid)
    assert fld.stats["fine_blocks"] == 0
    # Corners (about one per block) and the centre check (one per block): nothing dense.
    assert fld.stats["evaluations"] < 2.5 * fld.stats["blocks"] + 200
    p = inside_points(grid, 20_000, rng)
    f, g, cov = fld.query(p)
    np.testing.assert_allclose(f, p @ n + 30.0, atol=3e-5)
    np.testing.assert_allclose(g, np.tile(n, (len(p), 1)), atol=3e-5)


def test_values_and_gradients_continuous_across_block_and_level_borders():
    grid = box_grid()
    fld = bake(smooth_fn, grid, BakeConfig(block=0.2, fine=4, tol=0.002))
    assert 0 < fld.stats["fine_blocks"] < fld.stats["blocks"], "both levels must be present"
    rng = np.random.default_rng(2)
    B = fld.block
    # Points on block faces (x = a block border) in the baked region, approached from both sides.
    p = inside_points(grid, 20_000, rng)
    kinds = {"coarse|coarse": 0, "fine|fine": 0, "coarse|fine": 0}
    for axis in range(3):
        q = p.copy()
        q[:, axis] = fld.origin[axis] + np.round((q[:, axis] - fld.origin[axis]) / B) * B
        e = np.zeros(3)
        e[axis] = 1e-7
        a, b = q - e, q + e
        fa, ga, ca = fld.query(a)
        fb, gb, cb = fld.query(b)
        ok = ca & cb
        ia = np.floor((a[ok] - fld.origin) / B).astype(int)
        ib = np.floor((b[ok] - fld.origin) / B).astype(int)
        la = fld.state[tuple(ia.T)]
        lb = fld.state[tuple(ib.T)]
        kinds["coarse|coarse"] += int(np.sum((la == 1) & (lb == 1)))
        kinds["fine|fine"] += int(np.sum((la == 2) & (lb == 2)))
        kinds["coarse|fine"] += int(np.sum(la != lb))
        np.testing.assert_allclose(fa[ok], fb[ok], atol=1e-5)  # values: C0
        np.testing.assert_allclose(ga[ok], gb[ok], atol=2e-4)  # gradients: C1
    assert min(kinds.values()) > 100, kinds
    # Across fine cell faces inside blocks too.
    h = B / fld.nf
    q = p.copy()
    q[:, 2] = fld.origin[2] + (np.floor((q[:, 2] - fld.origin[2]) / h) + 0.0) * h
    fa, ga, ca = fld.query(q - [0, 0, 1e-7])
    fb, gb, cb = fld.query(q + [0, 0, 1e-7])
    ok = ca & cb
    np.testing.assert_allclose(fa[ok], fb[ok], atol=1e-5)
    np.testing.assert_allclose(ga[ok], gb[ok], atol=2e-4)


def test_accuracy_on_a_smooth_field_and_the_coarse_to_fine_budget():
    grid = box_grid()
    fld = bake(smooth_fn, grid, BakeConfig(block=0.2, fine=4))
    rng = np.random.default_rng(3)
    p = inside_points(grid, 100_000, rng)
    f, g, cov = fld.query(p)
    ft, gt = smooth_fn(p)
    near = np.abs(ft) < 0.1
    err = np.abs(f - ft)
    assert err[near].max() < 2e-3, err[near].max()  # the fine level near the surface: < 2 mm
    # Away from it the 20 cm coarse level (the cone at the centre of the sphere is the worst).
    assert err.mean() < 2.5e-3 and np.percentile(err, 99) < 1e-2, (err.mean(), np.percentile(err, 99))
    cos = 1 - np.sum(g * gt, 1) / np.linalg.norm(g, axis=1) / np.linalg.norm(gt, axis=1)
    assert cos.mean() < 2e-3
    # Coarse to fine: the fine level only near the surface, never in empty space.
    blocks = np.argwhere(fld.state > 0)
    centre_f = np.abs(smooth_fn(fld.origin + (blocks + 0.5) * fld.block)[0])
    is_fine = fld.state[tuple(blocks.T)] == 2
    assert is_fine.any() and (~is_fine).any()
    # core: a corner within diag/2 + band; centre to corner diag/2; dilation: a diagonal neighbour, diag.
    reach = 2 * fld.block * np.sqrt(3) + 0.05 + 0.03  # (+ the wave)
    assert centre_f[is_fine].max() < reach
    dense = fld.stats["blocks"] * fld.nf ** 3
    assert fld.stats["evaluations"] < dense, (fld.stats, dense)


def test_points_outside_the_bake_are_reported_not_covered():
    grid = box_grid()
    _, fn = plane_fn([0, 0, 1], 1.0)
    fld = bake(fn, grid)
    p = np.array([[100.0, 0, 0], [-1.05, -2.0, 0.3], grid.origin + 0.05])  # far away; unobserved corner
    _, _, cov = fld.query(p)
    assert not cov.any()


# ----------------------------------------------------------------------------- observed space


@pytest.fixture(scope="module")
def seq():
    return SyntheticSequence(building="office", n_frames=120, seed=0)


def in_any_frustum(points, frames, slack_px=6.0, max_depth=12.0):
    inside = np.zeros(len(points), bool)
    for f in frames:
        pc = transform(invert(f["T_WC"]), points)
        z = pc[:, 2]
        K = f["K"]
        H, W = f["depth"].shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / z + K[0, 2]
            v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        inside |= (z > -0.3) & (z < max_depth + 0.5) & (u > -slack_px) & (u < W + slack_px) & (v > -slack_px) & (
            v < H + slack_px)
    return inside


def test_observed_true_on_seen_surfaces_and_false_outside_every_frustum(seq):
    frames = [seq.frame(i) for i in range(0, 120, 20)]
    obs = ObservedSpace(voxel=0.1)
    for f in frames:
        obs.add(f["depth"], f["K"], f["T_WC"])
    grid = ObservedGrid.from_msg(protocol.unpack(protocol.pack(obs.grid().to_msg())))
    # Seen surfaces: every valid depth pixel of every keyframe.
    surf = np.concatenate([transform(f["T_WC"], backproject(f["depth"], f["K"]).reshape(-1, 3)) for f in frames])
    surf = surf[np.isfinite(surf[:, 0])]
    assert grid.contains(surf).mean() > 0.995
    np.testing.assert_array_equal(grid.contains(surf[:5000]), obs.contains(surf[:5000]))
    # Outside every keyframe's frustum (with a pixel and voxel slack): never observed.
    rng = np.random.default_rng(0)
    b = grid.bounds
    p = rng.uniform(b[0] - 1, b[1] + 1, (200_000, 3))
    # A voxel's diagonal of slack: the point and its 26 neighbours 0.18 m away all outside.
    far_out = np.ones(len(p), bool)
    for off in np.stack(np.meshgrid(*([-0.18, 0.0, 0.18],) * 3, indexing="ij"), -1).reshape(-1, 3):
        far_out &= ~in_any_frustum(p + off, frames, slack_px=1.0)
    assert far_out.sum() > 10_000
    assert not grid.contains(p[far_out]).any()
    # And the free space in front of a seen surface is observed (halfway along the rays).
    f = frames[0]
    half = transform(f["T_WC"], 0.5 * backproject(f["depth"], f["K"]).reshape(-1, 3))
    half = half[np.isfinite(half[:, 0])]
    assert grid.contains(half).mean() > 0.99


def test_observed_space_holds_every_voxel_seen_once_sorted_and_counts_the_new_ones(seq):
    """Adding keyframes one by one gives exactly the sorted union of what each one saw (the
    incremental insertion against a plain union of all of them), and ``add`` returns how many
    voxels were new."""
    obs = ObservedSpace(voxel=0.1)
    seen = []
    for i in range(0, 120, 10):
        f = seq.frame(i)
        one = ObservedSpace(voxel=0.1)
        one.add(f["depth"], f["K"], f["T_WC"])
        seen.append(one.keys)
        before = obs.keys.copy()
        n_new = obs.add(f["depth"], f["K"], f["T_WC"])
        assert n_new == len(np.setdiff1d(one.keys, before))
        assert obs.add(f["depth"], f["K"], f["T_WC"]) == 0  # the same image again: nothing new
    np.testing.assert_array_equal(obs.keys, np.unique(np.concatenate(seen)))


def test_unknown_distance_exact_values_and_a_lower_bound_everywhere():
    """Protocol 1.6: the distance from a point to space no keyframe observed (unobserved
    voxels' cubes, and everything outside the grid): exact values on a block with a hole,
    and equal to brute force over every unobserved cube on random grids."""
    occ = np.ones((10, 10, 10), bool)
    occ[5, 5, 7] = False  # a hole: the cube [0.5, 0.6] x [0.5, 0.6] x [0.7, 0.8]
    g = ObservedGrid(np.zeros(3), 0.1, occ)
    pts = np.array([[0.5, 0.5, 0.5], [0.12, 0.5, 0.5], [0.55, 0.55, 0.45], [0.55, 0.55, 0.75], [0.3, 0.2, 0.95],
                    [2.0, 2.0, 2.0], [0.5, 0.5, -0.01]])
    np.testing.assert_allclose(g.unknown_distance(pts), [0.2, 0.12, 0.25, 0.0, 0.05, 0.0, 0.0], atol=1e-12)
    empty = ObservedGrid(np.zeros(3), 0.1, np.zeros((2, 2, 2), bool))
    assert not empty.unknown_distance(pts).any()
    rng = np.random.default_rng(0)
    for dense in (0.85, 0.97):
        occ = rng.random((12, 11, 9)) < dense
        g = ObservedGrid(np.array([1.0, -2.0, 0.3]), 0.1, occ)
        p = g.origin + rng.uniform(0.0, [1.2, 1.1, 0.9], (3000, 3))  # inside the grid: every unobserved cube is in it
        cen = g.origin + (np.argwhere(~np.pad(occ, 1)) - 0.5) * 0.1
        truth = np.array([np.linalg.norm(np.maximum(np.abs(q - cen) - 0.05, 0), axis=1).min() for q in p])
        u = g.unknown_distance(p)
        np.testing.assert_allclose(u, truth, atol=1e-12)
        assert np.all(u[~g.contains(p)] == 0)
        # Asked to stop at the first 2 cubes: where more may be nearer, a bound below the truth.
        u2 = g.unknown_distance(p, k=2, k_max=2)
        assert np.all(u2 <= truth + 1e-12) and np.all(truth - u2 <= 0.05 * np.sqrt(3)) and (u2 < truth - 1e-9).any()


def test_observed_space_rejects_malformed_grids():
    g = box_grid()
    m = g.to_msg()
    bad = dict(m, shape=[4, 4])
    with pytest.raises(protocol.ProtocolError):
        ObservedGrid.from_msg(bad)
    bad = dict(m, voxel=-1.0)
    with pytest.raises(protocol.ProtocolError):
        ObservedGrid.from_msg(bad)
    bad = dict(m, shape=[40, 30, 21])  # bits do not match the shape
    with pytest.raises(protocol.ProtocolError):
        ObservedGrid.from_msg(bad)


# ----------------------------------------------------------------------------- the query engine


@pytest.fixture(scope="module")
def trained():
    """A small map of the synthetic Atlanta building: the frames and its messages (as received).
    Without measured points: these tests hold the bake to the network and surfel answer of
    1.1-1.3 (the 1.5 answer over measured points: test_pipeline, test_e2e_query)."""
    s, frames, p = train_small_map(measured=False)
    snap = protocol.WeightSnapshot.from_msg(protocol.unpack(protocol.pack(p.weight_snapshot(3).to_msg())))
    smap = p.surfel_map(3)
    smap = None if smap is None else protocol.SurfelMap.from_msg(protocol.unpack(protocol.pack(smap.to_msg())))
    return s, frames, snap, smap


def engine_with(trained, **kw):
    from aisdf.query.engine import QueryEngine

    _, _, snap, smap = trained
    e = QueryEngine(device="cpu", **kw)
    assert e.set_weights(snap)
    if smap is not None:
        e.set_surfels(smap)
    return e


def test_engine_bakes_and_answers_like_the_network(trained):
    from aisdf.metrics import eval_points

    s, frames, snap, _ = trained
    e = engine_with(trained)
    pts = eval_points(frames, n_points=20_000, every=1, rng=0)
    req = query_messages.SdfRequest(pts, gradient=True)
    before = e.answer_sdf(req)
    assert not before.baked  # no bake yet: the network answers
    assert e.bake_now() is not None and e.baked.state.version == snap.version
    rep = e.answer_sdf(req)
    exact = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    assert rep.baked and not exact.baked and rep.map_version == exact.map_version == snap.version
    np.testing.assert_array_equal(exact.sdf, before.sdf)
    diff = np.abs(rep.sdf - exact.sdf)
    assert diff.mean() < 0.005 and np.percentile(diff, 99) < 0.03, (diff.mean(), np.percentile(diff, 99))
    cos = 1 - np.sum(rep.gradient * exact.gradient, 1) / (
        np.linalg.norm(rep.gradient, axis=1) * np.linalg.norm(exact.gradient, axis=1) + 1e-12)
    assert np.median(cos) < 0.01
    # Against the truth the bake is as good as the network (within 0.5 cm here).
    gt = s.gt_sdf(pts)
    assert abs(np.abs(rep.sdf - gt).mean() - np.abs(exact.sdf - gt).mean()) < 0.005
    # Other sources are the network's, as before.
    imp = e.answer_sdf(query_messages.SdfRequest(pts[:100], source="implicit"))
    assert not imp.baked


def test_engine_radii_observed_and_points_outside_the_bake(trained):
    s, frames, snap, _ = trained
    e = engine_with(trained)
    e.bake_now()
    rng = np.random.default_rng(5)
    f = frames[0]
    surf = transform(f["T_WC"], backproject(f["depth"], f["K"]).reshape(-1, 3))
    surf = surf[np.isfinite(surf[:, 0])][:2000]
    far = rng.uniform(-1, 1, (500, 3)) + [60.0, -40.0, 30.0]  # nowhere near anything seen
    pts = np.concatenate([surf, far])
    radii = rng.uniform(0, 0.3, len(pts))
    base = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, collision_epsilon=0.2))
    sph = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, collision_epsilon=0.2, radii=radii, observed=True))
    np.testing.assert_allclose(sph.sdf, base.sdf - radii.astype(np.float32), atol=1e-6)
    np.testing.assert_array_equal(sph.gradient, base.gradient)
    from aisdf.collision import chomp_cost

    np.testing.assert_allclose(sph.collision, chomp_cost(sph.sdf, 0.2), atol=1e-6)
    assert sph.observed[:len(surf)].mean() > 0.99 and not sph.observed[len(surf):].any()
    # 1.6: distances to unobserved space, only when asked; of the spheres' surfaces with radii.
    assert base.unknown is None and sph.unknown is None
    unk = e.answer_sdf(query_messages.SdfRequest(pts, unknown=True))
    np.testing.assert_allclose(unk.unknown, e.baked.state.observed.unknown_distance(pts), atol=1e-6)
    assert np.all(unk.unknown[len(surf):] == 0) and np.mean(unk.unknown[:len(surf)] > 0) > 0.9
    sph_u = e.answer_sdf(query_messages.SdfRequest(pts, radii=radii, unknown=True))
    np.testing.assert_allclose(sph_u.unknown, unk.unknown - radii.astype(np.float32), atol=1e-6)
    assert e.baker.warm_unknown  # from now on each new map's index is built by the baker
    # Points outside the bake are answered by the network of the same map.
    net = e.answer_sdf(query_messages.SdfRequest(far, gradient=True, exact=True))
    np.testing.assert_allclose(base.sdf[len(surf):], net.sdf, atol=1e-6)
    assert base.map_version == net.map_version


def test_engine_orders_maps_by_epoch_then_version(trained):
    _, _, snap, _ = trained
    e = engine_with(trained)
    old = protocol.WeightSnapshot(snap.version + 5, snap.step, snap.stamp, snap.model, snap.state, epoch=0)
    assert e.set_weights(old)
    # A restarted mapper: a new epoch with a lower version wins; older epochs never again.
    new = protocol.WeightSnapshot(2, snap.step, snap.stamp, snap.model, snap.state, epoch=7)
    assert e.set_weights(new)
    assert (e.state.epoch, e.state.version) == (7, 2)
    assert not e.set_weights(old)
    rep = e.answer_sdf(query_messages.SdfRequest(np.zeros((3, 3))))
    assert (rep.map_epoch, rep.map_version) == (7, 2)


def test_while_the_bake_lags_a_baked_reply_names_the_older_map_and_exact_the_newest(trained):
    """A one-network map: a newer network changes every point, so until its bake is ready the
    bake answers with the map it baked, and says so (its ``map_version``, an age that keeps
    growing); ``exact`` answers from the newest map at once."""
    import dataclasses

    _, frames, snap, _ = trained
    e = engine_with(trained)  # no background baker: the bake changes only by bake_now()
    e.bake_now()
    pts = frames[0]["T_WC"][:3, 3] + np.random.default_rng(3).uniform(-1.0, 1.0, (3000, 3))
    before = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True))
    rng = np.random.default_rng(4)
    moved = {k: v + 0.05 * np.abs(v).mean() * rng.standard_normal(v.shape).astype(v.dtype) for k, v in snap.state.items()}
    assert e.set_weights(dataclasses.replace(snap, version=snap.version + 1, state=moved))
    assert e.baked.state.version == snap.version  # the bake lags
    baked = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True))
    exact = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    assert baked.baked and baked.map_version == snap.version and baked.map_age_s >= before.map_age_s
    np.testing.assert_array_equal(baked.sdf, before.sdf)  # the old map's values, bit for bit
    assert not exact.baked and exact.map_version == snap.version + 1 and exact.map_age_s <= baked.map_age_s
    assert np.abs(exact.sdf - baked.sdf).mean() > 0.005  # the new network answers differently
    lag = e.lag()
    assert lag["versions"] == lag["bake_versions"] == 1 and lag["behind_s"] >= 0
    e.bake_now()  # the bake catches up: now it answers for the newest map
    after = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True))
    assert after.baked and after.map_version == snap.version + 1
    diff = np.abs(after.sdf - exact.sdf)
    assert diff.mean() < 0.005, diff.mean()
    assert e.lag()["versions"] == 0
