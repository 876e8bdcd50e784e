"""The query service answering from submaps (protocol 1.3): blended
answers equal ``aisdf.submaps.field.blend`` over the submaps; values and gradients along
lines crossing a submap boundary have no jump; the bake re-evaluates only what changed
and equals a full bake; tiled meshes equal untiled ones and stay within a memory bound;
submap ordering, epochs and malformed snapshots; and, end to end over real Zenoh, a lost
submap sample recovered through ``map/index``, a late joiner, malformed messages.

The submap map: three submaps (3 m cells, 0.5 m overlap) of the synthetic Atlanta building
around six keyframes, each a small network fitted to the building's exact SDF over its own
extended box (different networks, each with its own error of a few cm, as neighbouring
submaps have)."""

import threading
import time
import tracemalloc

import numpy as np
import pytest
import torch

import stranger_client as sc
from aisdf import protocol
from aisdf.metrics import eval_points
from aisdf.network import NetworkConfig, SDFNetwork, build_model, load_numpy_state, model_spec, state_to_numpy
from aisdf.observed import ObservedGrid, ObservedSpace
from aisdf.stack import Stack, wait_for
from aisdf.submaps.field import blend
from aisdf.submaps.grid import SubmapGrid, cell_id
from aisdf.structure.surfel_types import Surfels
from aisdf.synthetic import SyntheticSequence
from aisdf.query.engine import QueryEngine
from aisdf.query.mapstate import MapState
from aisdf.query.meshing import tiled_marching_cubes

torch.set_num_threads(1)
NS = "aisdf/e2esub"
CELLS = [(1, 0, 0), (2, 0, 0), (1, -1, 0)]
EPOCH = 1_700_000_000_000


def fit_submap(seq, grid, cell, centres, seed, steps=200, pool=20_000, batch=512):
    """A small network fitted to the exact SDF near the observed space of the cell's extended box."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    pts = centres[grid.inside(cell, centres)]
    q = pts[rng.integers(0, len(pts), pool)] + rng.uniform(-0.05, 0.05, (pool, 3))
    q32 = torch.from_numpy(q.astype(np.float32))
    y = torch.from_numpy(seq.gt_sdf(q).astype(np.float32))
    net = SDFNetwork(NetworkConfig(width=32, offset=grid.centre_W(cell).tolist()))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(steps):
        j = torch.from_numpy(rng.integers(0, pool, batch))
        loss = (net(q32[j]).reshape(-1) - y[j]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net.eval()


def crop(obs: ObservedGrid, grid: SubmapGrid, cell) -> ObservedGrid:
    """The observed voxels inside the cell's extended box, on the same voxel lattice."""
    idx = np.argwhere(obs.occ)
    keep = grid.inside(cell, obs.origin + (idx + 0.5) * obs.voxel)
    idx = idx[keep]
    lo, hi = idx.min(0), idx.max(0) + 1
    occ = np.zeros(tuple(hi - lo), bool)
    occ[tuple((idx - lo).T)] = True
    return ObservedGrid(obs.origin + lo * obs.voxel, obs.voxel, occ)


def snapshot(net, grid, cell, version, observed, epoch=EPOCH, step=100, measured=None):
    spec = model_spec(net)
    lo, hi = observed.bounds
    spec["bounds"] = [lo.tolist(), hi.tolist()]
    snap = protocol.WeightSnapshot(version, step, time.time(), spec, state_to_numpy(net), epoch, observed.to_msg(),
                                   {"id": cell_id(cell), "grid": grid.to_msg()},
                                   None if measured is None else {"voxel": 0.1, "points": measured})
    return protocol.WeightSnapshot.from_msg(protocol.unpack(protocol.pack(snap.to_msg())))  # as received


def index(grid, versions: dict, version, epoch=EPOCH):
    return protocol.SubmapIndex(version, time.time(), grid.to_msg(),
                                {cell_id(c): {"version": v, "step": 100} for c, v in versions.items()}, epoch)


def surfel_map(surf: Surfels, version: int = 1) -> protocol.SurfelMap:
    """The SurfelMap message of ``surf``, as received (encoded and decoded)."""
    dtypes = {"direction": np.int32, "keyframe": np.int64}
    smap = protocol.SurfelMap(version, time.time(), np.array([0, 0, 1.0]), np.eye(3)[:1],
                              {f: getattr(surf, f).astype(dtypes.get(f, np.float32)) for f in (
                                  "center", "normal", "axis1", "axis2", "extent", "direction", "keyframe")}, EPOCH)
    return protocol.SurfelMap.from_msg(protocol.unpack(protocol.pack(smap.to_msg())))


def assert_same_bake(a, b, pts):
    """Two baked fields answer the same at ``pts``: coverage, values and gradients."""
    fa, ga, ca = a.query(pts)
    fb, gb, cb = b.query(pts)
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_allclose(fa, fb, atol=1e-6)
    np.testing.assert_allclose(ga, gb, atol=1e-5)


@pytest.fixture(scope="module")
def submap_map():
    seq = SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)
    frames = [seq.frame(i) for i in range(0, 120, 20)]
    space = ObservedSpace(voxel=0.1)
    for f in frames:
        space.add(f["depth"], f["K"], f["T_WC"])
    obs = space.grid()
    centres = obs.origin + (np.argwhere(obs.occ) + 0.5) * obs.voxel
    grid = SubmapGrid.around(frames[0]["T_WC"][:3, 3], cell_m=3.0, cell_height_m=6.0, overlap_m=0.5)
    nets = {c: fit_submap(seq, grid, c, centres, seed=n) for n, c in enumerate(CELLS)}
    observed = {c: crop(obs, grid, c) for c in CELLS}
    snaps = {c: snapshot(nets[c], grid, c, 1, observed[c]) for c in CELLS}
    return dict(seq=seq, frames=frames, grid=grid, nets=nets, observed=observed, snaps=snaps, centres=centres)


def engine_of(m, **kw):
    e = QueryEngine(device="cpu", **kw)
    for c in CELLS:
        assert e.set_submap(m["snaps"][c])
    return e


def evaluators(m, snaps=None):
    """The submaps' networks rebuilt from their messages, as blend's evaluators."""
    out = {}
    for c, s in (snaps or m["snaps"]).items():
        net = build_model(s.model)
        load_numpy_state(net, s.state)
        net.eval()

        def ev(q, grad, net=net):
            x = torch.from_numpy(np.asarray(q, np.float32))
            if not grad:
                with torch.no_grad():
                    return net(x).reshape(-1).numpy(), None
            x.requires_grad_(True)
            f = net(x).reshape(-1)
            (g,) = torch.autograd.grad(f.sum(), x)
            return f.detach().numpy(), g.numpy()

        out[c] = ev
    return out


def band_points(m, n, rng):
    """Observed points in the overlap bands (where two submaps blend) and elsewhere."""
    c = m["centres"]
    w = np.stack([m["grid"].weight(cell, c) for cell in CELLS], 1)
    both, some = (w > 0).sum(1) >= 2, (w > 0).any(1)
    pick = np.concatenate([c[both][rng.integers(0, both.sum(), n // 2)], c[some][rng.integers(0, some.sum(), n - n // 2)]])
    return pick + rng.uniform(-0.05, 0.05, pick.shape)


# ----------------------------------------------------------------------------- in process


def test_blended_answers_equal_blend_over_the_submaps(submap_map):
    m = submap_map
    e = engine_of(m)
    st = e.state
    assert st.submaps is not None and len(st.submaps.submaps) == 3 and st.net is None
    assert (st.epoch, st.version) == (EPOCH, 1)
    rng = np.random.default_rng(0)
    pts = band_points(m, 4000, rng)
    pts = np.concatenate([pts, [[60.0, -40.0, 30.0]]])  # far from every submap: the nearest one answers
    f_ref, g_ref, covered = blend(m["grid"], evaluators(m), pts, True)
    assert covered[:-1].mean() > 0.95 and not covered[-1]
    for source, exact in (("implicit", False), ("fused", True)):
        rep = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, source=source, exact=exact, observed=True))
        assert not rep.baked and (rep.map_epoch, rep.map_version) == (EPOCH, 1)
        np.testing.assert_allclose(rep.sdf, f_ref, atol=2e-5)
        np.testing.assert_allclose(rep.gradient, g_ref, atol=2e-4)
    # Observed space: the union of the submaps' observed grids.
    want = np.zeros(len(pts), bool)
    for c in CELLS:
        want |= m["observed"][c].contains(pts)
    np.testing.assert_array_equal(rep.observed, want)
    assert want[:-1].mean() > 0.95
    # The index's version: once everything it lists is held, replies carry it.
    assert e.set_index(index(m["grid"], {c: 1 for c in CELLS}, 4)) == []
    assert e.state.version == 4
    # Baked: the blended field's bake answers within the bake's accuracy; radii as before.
    assert e.bake_now() is not None
    radii = rng.uniform(0, 0.2, len(pts))
    rep = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, radii=radii, collision_epsilon=0.3))
    assert rep.baked and rep.map_version == 4
    diff = np.abs(rep.sdf + radii - f_ref)
    assert diff.mean() < 0.005 and np.percentile(diff, 99) < 0.03, (diff.mean(), np.percentile(diff, 99))


def line_profile(e, grid, start_W, axis_W, half=0.8, h=0.001, exact=True):
    t = np.arange(-half, half + h / 2, h)
    p = start_W + t[:, None] * axis_W
    rep = e.answer_sdf(protocol.SdfRequest(p, gradient=True, exact=exact))
    return t, p, rep


def test_answers_are_continuous_across_a_submap_boundary(submap_map):
    """Along lines crossing the boundary between two submaps (value and gradient every mm):
    the blend has no jump; answering from the submap whose core holds the point would jump
    by the submaps' disagreement (the map's own error)."""
    m = submap_map
    grid, seq = m["grid"], m["seq"]
    e = engine_of(m)
    e.bake_now()
    ev = evaluators(m)
    a, b = (1, 0, 0), (2, 0, 0)  # neighbours along the grid's first axis
    x_W = grid.R_WG[:, 0]
    rng = np.random.default_rng(1)
    # Crossing points: observed space near the shared face, both submaps covering it.
    c = m["centres"]
    g = grid.to_grid(c)
    face = 2 * grid.cell_m
    near = (np.abs(g[:, 0] - face) < 0.1) & (grid.weight(a, c) > 0) & (grid.weight(b, c) > 0)
    assert near.sum() > 50
    starts = c[near][rng.choice(near.sum(), 12, replace=False)]
    jumps, seams, errs = [], [], []
    for s in starts:
        t, p, rep = line_profile(e, grid, s, x_W)
        fa, ga = ev[a](p, True)
        fb, gb = ev[b](p, True)
        f, gr = rep.sdf.astype(np.float64), rep.gradient.astype(np.float64)
        h = t[1] - t[0]
        gmax = np.linalg.norm(gr, axis=1).max()
        df = np.abs(np.diff(f))
        # Values: Lipschitz along the line (no step), far below the map's own error.
        assert df.max() <= 1.5 * h * max(gmax, 1.0) + 1e-5, (df.max(), gmax)
        # Gradients: change no faster than the submaps' own gradients do, plus the blend's
        # smooth ramp (|g_a - g_b| dw + |f_a - f_b| d(grad w): a few 1e-3 per mm).
        dg = np.linalg.norm(np.diff(gr, axis=0), axis=1).max()
        own = max(np.linalg.norm(np.diff(ga, axis=0), axis=1).max(), np.linalg.norm(np.diff(gb, axis=0), axis=1).max())
        assert dg <= own + 0.01, (dg, own)
        # A hard switch at the face (no blend) jumps by the submaps' disagreement there.
        i = np.argmin(np.abs(grid.to_grid(p)[:, 0] - face))
        seams.append((abs(fa[i] - fb[i]), np.linalg.norm(ga[i] - gb[i])))
        jumps.append((df.max(), dg, own))
        errs.append(np.abs(f - seq.gt_sdf(p)).mean())
        # The baked blended field along the same line (where the bake covers it): continuous too.
        fk, gk, ck = e.baked.field.query(p)
        both = ck[1:] & ck[:-1]
        assert both.sum() > 100
        dk = np.abs(np.diff(fk.astype(np.float64)))[both]
        assert dk.max() <= 1.5 * h * max(np.linalg.norm(gk[ck], axis=1).max(), 1.0) + 1e-5, dk.max()
    seams, jumps = np.array(seams), np.array(jumps)
    map_error = float(np.mean(errs))
    print(f"map error {map_error * 100:.2f} cm; hard switch at the face: value {seams[:, 0].mean() * 1000:.2f} mm, "
          f"gradient {seams[:, 1].mean():.3f} (means); blend's largest step per mm: value "
          f"{jumps[:, 0].max() * 1000:.3f} mm, gradient {jumps[:, 1].max():.4f} (submaps' own {jumps[:, 2].max():.4f})")
    # The test can fail: the submaps disagree at the face by about the map's error...
    assert seams[:, 0].mean() > 0.002 and seams[:, 1].mean() > 0.02, (seams.mean(0), map_error)
    # ...and the blended answer's largest step along every line is far below that.
    assert jumps[:, 0].max() < 0.1 * map_error, (jumps[:, 0].max(), map_error)


def test_bake_reevaluates_only_what_changed_and_equals_a_full_bake(submap_map):
    m = submap_map
    # A 0.5 m fuse radius: a changed surfel's surroundings (the radius + 5 cm) then stay a
    # small part of this small map; at the default 2 m they would cover most of it.
    e = engine_of(m, fuse_radius=0.5)
    first = e.bake_now().field
    full_evals = first.stats["evaluations"]
    assert first.stats["reused"] == 0 and full_evals > 1000
    # One submap changes (a new version: different weights).
    c = (1, -1, 0)
    net = m["nets"][c]
    net2 = SDFNetwork(net.cfg)
    net2.load_state_dict(net.state_dict())
    torch.manual_seed(7)
    with torch.no_grad():
        for prm in net2.parameters():
            prm.add_(1e-3 * torch.randn_like(prm))
    snap2 = snapshot(net2, m["grid"], c, 2, m["observed"][c])
    assert e.set_submap(snap2)
    second = e.bake_now().field
    assert 0 < second.stats["evaluations"] < 0.7 * full_evals and second.stats["reused"] > 0.3 * full_evals, (
        second.stats, full_evals)
    # Surfels change (one added on a wall): only their surroundings are re-evaluated.
    p0 = m["centres"][len(m["centres"]) // 2]
    surf = Surfels(center=[p0], normal=[[1.0, 0, 0]], axis1=[[0, 1.0, 0]], axis2=[[0, 0, 1.0]], extent=[[0.4, 0.4]],
                   direction=[0], keyframe=[0])
    smap = surfel_map(surf)
    assert e.set_surfels(smap)
    third = e.bake_now().field
    assert 0 < third.stats["evaluations"] < 0.5 * full_evals, third.stats
    # The incremental bake is the full bake of the same map.
    f2 = QueryEngine(device="cpu", fuse_radius=0.5)
    for cc in CELLS:
        f2.set_submap(snap2 if cc == c else m["snaps"][cc])
    f2.set_surfels(smap)
    ref = f2.bake_now().field
    assert ref.stats["reused"] == 0
    assert_same_bake(third, ref, band_points(m, 20_000, np.random.default_rng(3)))
    # Only the index's version moving on: no evaluation, the same bake answers for the new version.
    e.set_index(index(m["grid"], {cc: (2 if cc == c else 1) for cc in CELLS}, 9))
    bk = e.bake_now()
    assert bk.field is third and bk.state.version == 9


def test_answers_equal_the_submap_mappers_own_blend():
    """The mapper's SubmapPipeline and the query engine fed its messages answer the same."""
    from aisdf.mapping.frames import Frame
    from aisdf.submaps.pipeline import SubmapPipeline

    seq = SyntheticSequence(building="office", n_frames=300, H=60, W=80, seed=0)
    p = SubmapPipeline.from_settings("cpu", {"network": {"width": 32}, "n_rays": 20}, submaps={"cell_m": 3})
    frames = []
    for i in range(0, 300, 50):
        f = seq.frame(i)
        frames.append(f)
        p.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        p.step()
    assert len(p.submaps) >= 2
    e = QueryEngine(device="cpu")
    for key, data in p.map_messages(5, changed_only=False, epoch=3):
        msg = protocol.unpack(data)
        if key.startswith("map/submaps/"):
            assert e.set_submap(protocol.WeightSnapshot.from_msg(msg))
        elif key == "map/index":
            assert e.set_index(protocol.SubmapIndex.from_msg(msg)) == []
        elif key == "map/surfels":
            e.set_surfels(protocol.SurfelMap.from_msg(msg))
    pts = eval_points(frames, n_points=3000, every=1, rng=0)
    f_ref, g_ref = p.sdf_grad(pts)
    rep = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, source="implicit"))
    assert (rep.map_epoch, rep.map_version) == (3, 5)
    np.testing.assert_allclose(rep.sdf, f_ref, atol=1e-5)
    np.testing.assert_allclose(rep.gradient, g_ref, atol=1e-4)


def test_surfel_moves_below_the_tolerance_keep_samples_and_never_add_up():
    from aisdf.query.changes import surfel_diff

    def surfels(dx):
        return Surfels(center=[[dx, 0, 1.0], [2, 0, 1]], normal=[[1.0, 0, 0], [0, 1.0, 0]],
                       axis1=[[0, 1.0, 0], [1.0, 0, 0]], axis2=[[0, 0, 1.0]] * 2, extent=[[1.0, 1.0]] * 2,
                       direction=[0, 1], keyframe=[0, 1])

    s0 = surfels(0.0)
    changed, _, ref = surfel_diff(s0, surfels(0.0004), 0.001)
    assert len(changed) == 0 and ref.center[0, 0] == 0.0  # unchanged: the reference stays
    changed, _, ref = surfel_diff(ref, surfels(0.0008), 0.001)
    assert len(changed) == 0 and ref.center[0, 0] == 0.0
    changed, _, ref = surfel_diff(ref, surfels(0.0012), 0.001)  # 1.2 mm from what was baked
    assert len(changed) == 2 and sorted(ref.center[:, 0]) == [0.0012, 2.0]
    assert len(surfel_diff(s0, surfels(1e-6), 0.0)[0]) == 2  # no tolerance: any move
    flipped = surfels(0.0)
    flipped.normal[0] *= -1  # the other side of the wall: another surface
    assert len(surfel_diff(s0, flipped, 0.001)[0]) == 2
    assert len(surfel_diff(s0, surfels(0.0)[[1]], 0.001)[0]) == 1  # one gone


def test_a_changed_surfel_dirties_only_where_it_is_or_was_the_nearest():
    """surfel_dirty: wherever the nearest surfel within the fusion radius (distance, sign,
    direction) differs between the reference and the new surfels, the point is dirty; and a
    wall grown by 1 m dirties far less than its box grown by the radius (what a re-bake
    re-evaluates)."""
    from aisdf.structure.surfel_map import explicit_sdf
    from aisdf.query.changes import in_boxes, surfel_boxes, surfel_diff, surfel_dirty

    def room(wall_len, table_x):
        return Surfels(center=[[0, 2, 1.5], [0, -2, 1.5], [3, 0, 1.5], [-3, 0, 1.5], [0, 0, 0], [table_x, 0, 0.8]],
                        normal=[[0, -1, 0], [0, 1, 0], [-1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1]],
                        axis1=[[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0]],
                        axis2=[[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0]],
                        extent=[[wall_len, 3], [6, 3], [4, 3], [4, 3], [6, 4], [1, 0.6]],
                        direction=[1, 1, 0, 0, -1, -1], keyframe=[0] * 6)

    ref, new = room(5.0, 1.0), room(6.0, 1.3)  # a wall grown by 1 m, a table moved by 30 cm
    grow = 2.05
    dirty, out = surfel_dirty(ref, new, 0.001, grow)
    assert len(out) == 6
    pts = np.random.default_rng(5).uniform([-4, -3, -0.5], [4, 3, 3.5], (40_000, 3))
    d_old, g_old, _ = explicit_sdf(pts, ref)
    d_new, g_new, _ = explicit_sdf(pts, out)
    used = (np.abs(d_old) <= 2.0) | (np.abs(d_new) <= 2.0)  # the fused answer uses them (radius 2 m)
    differs = used & ((np.abs(d_old - d_new) > 1e-9) | (np.abs(g_old - g_new).max(axis=1) > 1e-9))
    d = dirty(pts)
    assert differs.any() and not (differs & ~d).any()  # every point whose surfel answer changed
    boxed = in_boxes(pts, surfel_boxes(surfel_diff(ref, new, 0.001)[0]), grow)  # the changed surfels' boxes, grown
    assert d.mean() < 0.6 * boxed.mean(), (d.mean(), boxed.mean())


def test_submap_ordering_epochs_and_bad_snapshots(submap_map):
    m = submap_map
    e = engine_of(m)
    s = m["snaps"][(1, 0, 0)]
    assert not e.set_submap(s)  # the same version again: nothing new
    older = protocol.WeightSnapshot(0, s.step, s.stamp, s.model, s.state, EPOCH, s.observed, s.submap)
    assert not e.set_submap(older)
    # The index lists a newer version of one submap: that one is wanted.
    assert e.set_index(index(m["grid"], {(1, 0, 0): 3, (2, 0, 0): 1, (1, -1, 0): 1}, 3)) == ["1_0_0"]
    assert e.state.version == 1  # not everything listed is held: the map keeps its version
    # A grid of another shape within the same incarnation: refused, the map unchanged.
    other = SubmapGrid(m["grid"].R_WG, m["grid"].origin + 0.3, 3.0, 6.0, 0.5)
    bad = protocol.WeightSnapshot(5, s.step, s.stamp, s.model, s.state, EPOCH, s.observed,
                                  {"id": "1_0_0", "grid": other.to_msg()})
    with pytest.raises(ValueError):
        e.set_submap(bad)
    broken = protocol.WeightSnapshot(5, s.step, s.stamp, s.model, dict(list(s.state.items())[1:]), EPOCH, s.observed,
                                     s.submap)
    with pytest.raises(ValueError):
        e.set_submap(broken)
    assert len(e.state.submaps.submaps) == 3 and e.state.version == 1
    # A new mapper incarnation replaces the whole set, whatever its version; older epochs never again.
    new = protocol.WeightSnapshot(1, s.step, s.stamp, s.model, s.state, EPOCH + 1, s.observed, s.submap)
    assert e.set_submap(new)
    assert len(e.state.submaps.submaps) == 1 and e.state.epoch == EPOCH + 1
    assert not e.set_submap(m["snaps"][(2, 0, 0)])
    assert e.set_index(index(m["grid"], {c: 1 for c in CELLS}, 1, epoch=EPOCH + 2)) is None  # newer: get all
    # A single-network mapper's weights replace submaps when newer, and the other way round.
    w = protocol.WeightSnapshot(7, 0, 0.0, s.model, s.state, EPOCH + 1)
    assert e.set_weights(w) and e.state.submaps is None and e.state.net is not None
    rep = e.answer_sdf(protocol.SdfRequest(np.zeros((2, 3))))
    assert rep.map_version == 7


def test_bench_query_republishes_a_submap_map_whole_at_a_new_version(submap_map):
    """``aisdf bench query``'s map messages: fed to an engine they give the whole submap map;
    republished at a new version (its lag run) every submap and the index move to it, so the
    engine takes all of them and the map's version is the new one."""
    from aisdf import keys
    from aisdf.bench.query_map import engine_of, versioned

    m = submap_map
    msgs = [(f"{keys.MAP_SUBMAPS}/{cell_id(c)}", m["snaps"][c].to_msg()) for c in CELLS]
    msgs.append((keys.MAP_INDEX, index(m["grid"], {c: 1 for c in CELLS}, 1).to_msg()))
    e = engine_of({"messages": msgs})
    assert e.state.version == 1 and set(e.state.submaps.submaps) == set(CELLS)
    again = versioned(msgs, 7)
    assert [k for k, _ in again] == [k for k, _ in msgs] and msgs[0][1]["version"] == 1  # the originals are kept
    idx = dict(again)[keys.MAP_INDEX]
    assert idx["version"] == 7 and {v["version"] for v in idx["submaps"].values()} == {7}
    for key, msg in again:
        if key == keys.MAP_INDEX:
            assert e.set_index(protocol.SubmapIndex.from_msg(msg)) == []  # everything listed is held
        else:
            assert e.set_submap(protocol.WeightSnapshot.from_msg(msg))  # newer: taken
    assert e.state.version == 7 and {sm.version for sm in e.state.submaps.submaps.values()} == {7}
    before = e.state
    assert not e.set_submap(protocol.WeightSnapshot.from_msg(again[0][1])) and e.state is before  # not newer
    with pytest.raises(ValueError, match="not a map key"):
        e.take("map/mesh", again[0][1])
    assert e.state is before


def test_measured_points_1_4_answers_bake_and_the_1_3_answer(submap_map):
    """Protocol 1.4: submaps carrying measured points. ``fused`` answers are the rule of
    ``structure.measured`` over the union of the submaps' points (value and gradient), closer
    to the truth than the 1.3 answer; snapshots without points (a 1.3 mapper), or the query
    service's ``measured`` off, give the 1.3 answer; the bake equals the exact answer within
    its accuracy, and a re-bake after one submap's points changed re-evaluates only near
    them and equals a full bake."""
    from aisdf.structure.measured import MeasuredPoints, MeasuredSurface, measured_fuse_grad

    m = submap_map
    grid = m["grid"]
    ms = MeasuredSurface()
    for f in m["frames"]:
        ms.add(f["depth"], f["K"], f["T_WC"])
    allp = ms.points().astype(np.float32)
    own = {c: allp[grid.inside(c, allp)] for c in CELLS}
    snaps = {c: snapshot(m["nets"][c], grid, c, 1, m["observed"][c], measured=own[c]) for c in CELLS}
    e = QueryEngine(device="cpu")
    off = QueryEngine(device="cpu", measured=False)
    for c in CELLS:
        assert e.set_submap(snaps[c]) and off.set_submap(snaps[c])
    old = engine_of(m)  # 1.3 snapshots
    # the union holds each point once: copies in overlaps (equal bit for bit) are kept once
    union = np.unique(np.concatenate(list(own.values())), axis=0)
    assert len(e.state.measured) == len(union) > 1000 and old.state.measured is None
    assert len(union) < sum(len(v) for v in own.values())  # (the cells overlap)
    pts = band_points(m, 4000, np.random.default_rng(5))
    f_ref, g_ref, _ = blend(grid, evaluators(m), pts, True)
    want_f, want_g = measured_fuse_grad(f_ref, g_ref, f_ref, np.full(len(pts), np.inf), None,
                                        *MeasuredPoints(np.concatenate(list(own.values()))).nearest(pts))
    rep = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, exact=True))
    np.testing.assert_allclose(rep.sdf, want_f, atol=2e-5)
    np.testing.assert_allclose(rep.gradient, want_g, atol=2e-4)
    for eng in (old, off):  # the 1.3 answer: no surfels here, so the blend itself
        r13 = eng.answer_sdf(protocol.SdfRequest(pts, gradient=True, exact=True))
        np.testing.assert_allclose(r13.sdf, f_ref, atol=2e-5)
        np.testing.assert_allclose(r13.gradient, g_ref, atol=2e-4)
    gt = m["seq"].gt_sdf(pts)
    err, err13 = np.abs(rep.sdf - gt).mean(), np.abs(r13.sdf - gt).mean()
    capped = rep.sdf < r13.sdf - 1e-4
    print(f"1.4 answer {100 * err:.2f} cm, 1.3 answer {100 * err13:.2f} cm; capped at {100 * capped.mean():.1f} % "
          f"of the points: {100 * np.abs(rep.sdf - gt)[capped].mean():.2f} against "
          f"{100 * np.abs(r13.sdf - gt)[capped].mean():.2f} cm there")
    assert capped.mean() > 0.01 and err < err13
    # Baked: within the bake's accuracy of the exact answer.
    first = e.bake_now().field
    bk = e.answer_sdf(protocol.SdfRequest(pts, gradient=True))
    assert bk.baked
    diff = np.abs(bk.sdf - want_f)
    assert diff.mean() < 0.005 and np.percentile(diff, 99) < 0.03, (diff.mean(), np.percentile(diff, 99))
    # One submap's points change (a new version, same weights): an object measured in the
    # open, in its overlap with a neighbour, where it lowers answers of the neighbour's space
    # too. Only what lies within the fusion radius of the moved points is re-evaluated.
    c = (1, -1, 0)
    cand = m["centres"][grid.inside(c, m["centres"], grow=0.3) & (grid.weight((1, 0, 0), m["centres"]) > 0)]
    far = cand[np.argmax(MeasuredPoints(allp).nearest(cand)[0])]
    box = (far + np.random.default_rng(2).uniform(-0.1, 0.1, (40, 3))).astype(np.float32)
    assert grid.inside(c, box).all()
    snap2 = snapshot(m["nets"][c], grid, c, 2, m["observed"][c], measured=np.concatenate([own[c], box]))
    assert e.set_submap(snap2)
    second = e.bake_now().field
    assert 0 < second.stats["evaluations"] < first.stats["evaluations"] and second.stats["reused"] > 0, second.stats
    ref = QueryEngine(device="cpu")
    for cc in CELLS:
        assert ref.set_submap(snap2 if cc == c else snaps[cc])
    full = ref.bake_now().field
    q = band_points(m, 20_000, np.random.default_rng(6))
    assert_same_bake(second, full, q)
    # With surfels that move less than bake_surfel_tol (as every refinement of the Atlanta
    # frame moves them all a little) while a submap changes: the re-bake keeps the surfels'
    # baked geometry (its reference) for its new samples too, so it is the full bake with
    # that reference, though the rule's ramp makes answers sensitive to such moves.
    def wall(dx, version):
        p0 = far + np.array([0.3 + dx, 0.0, 0.0])
        return surfel_map(Surfels(center=[p0], normal=[[-1.0, 0, 0]], axis1=[[0, 1.0, 0]], axis2=[[0, 0, 1.0]],
                                  extent=[[2.0, 2.0]], direction=[0], keyframe=[0]), version)

    assert e.set_surfels(wall(0.0, 1))
    e.bake_now()
    snap3 = snapshot(m["nets"][c], grid, c, 3, m["observed"][c], measured=np.concatenate([own[c], box[:20]]))
    assert e.set_surfels(wall(0.0004, 2)) and e.set_submap(snap3)
    third = e.bake_now()
    assert third.surfel_ref.center[0, 0] != e.state.surfels.center[0, 0]  # the reference kept the old geometry
    ref2 = QueryEngine(device="cpu")
    for cc in CELLS:
        assert ref2.set_submap(snap3 if cc == c else snaps[cc])
    ref2.set_surfels(wall(0.0, 1))
    assert_same_bake(third.field, ref2.bake_now().field, q)


# ----------------------------------------------------------------------------- meshes


class Balls(torch.nn.Module):
    """A few spheres (off the lattice), for meshes with known geometry."""

    def __init__(self, centres, r=0.4):
        super().__init__()
        self.c = torch.tensor(np.asarray(centres, np.float32))
        self.r = r
        self.calls = []

    def forward(self, x):
        self.calls.append(len(x))
        return (torch.cdist(x, self.c).min(dim=1).values - self.r).unsqueeze(-1)


def test_tiled_mesh_equals_the_untiled_mesh(submap_map):
    from scipy.spatial import cKDTree

    # A single network: marching cubes of the whole box at once vs tiles of 7, 17 samples.
    net = Balls([[0.013, 0.021, 0.007], [0.75, 0.61, 0.33]])
    st = MapState(3, 0, net, np.array([[-0.6, -0.6, -0.6], [1.3, 1.2, 0.9]]), None, -1)
    meshes = {}
    for tile in (7, 17, 1000):
        e = QueryEngine(device="cpu", mesh_tile=tile)
        e._state = st
        meshes[tile] = e.answer_mesh(protocol.MeshRequest(0.05))
    ref = meshes[1000]
    assert len(ref.faces) > 1000
    for tile in (7, 17):
        v = meshes[tile]
        assert len(v.vertices) == len(ref.vertices) and len(v.faces) == len(ref.faces)
        assert cKDTree(ref.vertices).query(v.vertices)[0].max() < 1e-5
        assert cKDTree(v.vertices).query(ref.vertices)[0].max() < 1e-5
        # Welded: every vertex is used, so no seam leaves a crack of duplicated vertices.
        assert len(np.unique(v.faces)) == len(v.vertices)
    # The submap map: the blended field, tiled vs not.
    m = submap_map
    e1, e2 = engine_of(m, mesh_tile=16), engine_of(m, mesh_tile=1000)
    a, b = e1.answer_mesh(protocol.MeshRequest(0.12)), e2.answer_mesh(protocol.MeshRequest(0.12))
    assert len(b.faces) > 1000 and len(a.faces) == len(b.faces)
    assert cKDTree(b.vertices).query(a.vertices)[0].max() < 1e-4
    assert cKDTree(a.vertices).query(b.vertices)[0].max() < 1e-4


def test_tiled_mesh_memory_stays_bounded_on_a_big_box():
    # A 14 x 12 x 3 m box at 5 cm: 3.6 M samples (the untiled volume, points and lattice
    # indices would take ~120 MB of numpy arrays); tiles of 32^3 samples.
    net = Balls([[1.01, 2.03, 1.02], [9.07, 7.01, 1.53]], r=0.6)
    e = QueryEngine(device="cpu", mesh_tile=32, mesh_max_cells=10 ** 7)
    e._state = MapState(1, 0, net, np.array([[0.0, 0.0, 0.0], [14.0, 12.0, 3.0]]), None, -1)
    tracemalloc.start()
    try:
        rep = e.answer_mesh(protocol.MeshRequest(0.05))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    r = np.min(np.linalg.norm(rep.vertices[:, None] - net.c.numpy()[None], axis=2), axis=1)
    assert len(rep.faces) > 5000 and np.abs(r - 0.6).max() < 0.01
    assert max(net.calls) <= 32 ** 3
    assert peak < 25e6, f"peak numpy/python memory {peak / 1e6:.1f} MB"


def test_tiled_marching_cubes_welds_seams_on_a_generic_field():
    def fn(p):
        p = np.asarray(p, np.float64)
        return (np.linalg.norm(p - [0.1013, 0.2071, 0.3033], axis=1) - 0.7).astype(np.float32)

    from skimage.measure import marching_cubes

    lo, res, n = np.array([-1.0, -1.0, -1.0]), 0.06, np.array([37, 35, 30])
    axes = [lo[a] + res * np.arange(n[a]) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    v, f, _, _ = marching_cubes(fn(pts).reshape(tuple(n)), 0.0, spacing=(res,) * 3)
    for tile in (3, 8, 16):
        V, F = tiled_marching_cubes(fn, lo, res, n, tile)
        assert len(V) == len(v) and len(F) == len(f)
        key = lambda VV, FF: np.sort(np.sort(np.round(VV[FF], 4).reshape(len(FF), 3, 3), axis=1).reshape(len(FF), -1),
                                     axis=0)
        np.testing.assert_allclose(key(V, F), key(v + lo, f), atol=2e-4)


# ----------------------------------------------------------------------------- end to end


def info(s):
    status, msg = sc.request(s, f"{NS}/info/query", {"v": 1}, 2.0)
    return msg if status == "ok" else {}


def test_e2e_lost_submap_sample_late_joiner_and_malformed_messages(submap_map):
    """A real aisdf-query over real Zenoh. The test process plays the submap mapper: it
    publishes two of the three submaps, loses the third, and its index lists all three;
    the service gets the third through its key. Then malformed messages, then a restarted
    (late-joining) service gets everything with gets."""
    m = submap_map
    snaps = {c: protocol.pack(m["snaps"][c].to_msg()) for c in CELLS}
    lost = (1, -1, 0)
    asked = []
    served = {"on": False}

    def on_get(q):  # the mapper's queryable on map/submaps/**
        asked.append(str(q.key_expr))
        if not served["on"]:
            return
        for c in CELLS:
            k = f"{NS}/map/submaps/{cell_id(c)}"
            if sc.zenoh.KeyExpr(str(q.key_expr)).intersects(sc.zenoh.KeyExpr(k)):
                q.reply(k, snaps[c], encoding=sc.ENC)

    idx_msg = protocol.pack(index(m["grid"], {c: 1 for c in CELLS}, 2).to_msg())
    with Stack(services=("query",), namespace=NS) as st:
        s = sc.open_session(st.endpoints)
        try:
            qa = s.declare_queryable(f"{NS}/map/submaps/**", on_get)
            qi = s.declare_queryable(f"{NS}/map/index", lambda q: q.reply(f"{NS}/map/index", idx_msg, encoding=sc.ENC)
                                     if served["on"] else None)
            wait_for(lambda: info(s), 60, what="the query service")

            def two_loaded():
                for c in CELLS:
                    if c != lost:
                        s.put(f"{NS}/map/submaps/{cell_id(c)}", snaps[c], encoding=sc.ENC)
                return info(s).get("submaps") == 2

            wait_for(two_loaded, 60, period=1.0, what="two submaps")
            assert info(s)["version"] == 1
            # The index lists the third (lost) submap: the service gets it by its key.
            served["on"] = True
            asked.clear()

            def recovered():
                s.put(f"{NS}/map/index", idx_msg, encoding=sc.ENC)
                i = info(s)
                return i.get("submaps") == 3 and i.get("version") == 2 and i.get("baked_version") == 2

            wait_for(recovered, 90, period=1.0, what="the lost submap fetched and the map baked")
            assert f"{NS}/map/submaps/{cell_id(lost)}" in asked, asked
            assert info(s)["fetched"] >= 1
            # Answers: the same as the in-process engine's, from the baked blended field.
            e = engine_of(m)
            e.set_index(index(m["grid"], {c: 1 for c in CELLS}, 2))
            e.bake_now()
            pts = band_points(m, 2000, np.random.default_rng(4))
            req = {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True, "observed": True}
            status, msg = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok", msg
            want = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, observed=True))
            assert msg["baked"] is True and msg["map_version"] == 2 and msg["map_epoch"] == EPOCH
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(msg["gradient"]), want.gradient, atol=1e-4)
            np.testing.assert_array_equal(sc.unarr(msg["observed"]).astype(bool), want.observed)
            # Malformed submap and index messages: logged and skipped, the map unchanged.
            good = m["snaps"][(1, 0, 0)].to_msg()
            for key, payload in [
                ("map/submaps/1_0_0", b"\xc1not msgpack"),
                ("map/submaps/1_0_0", protocol.pack({"v": 1, "version": "x"})),
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "submap": {"id": "1_0", "grid": {}}})),
                ("map/submaps/2_0_0", protocol.pack({**good, "version": 50})),  # id and key disagree
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "state": {}})),
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "submap": None})),
                ("map/index", protocol.pack({"v": 1, "version": 60, "stamp": 0.0, "grid": {"R_WG": [1]},
                                             "submaps": {}})),
                ("map/index", protocol.pack({"v": 1, "version": 60, "stamp": 0.0, "grid": m["grid"].to_msg(),
                                             "submaps": {"a_b": {"version": 1}}})),
                ("map/index", protocol.pack({"v": 9})),
            ]:
                s.put(f"{NS}/{key}", payload, encoding=sc.ENC)
            time.sleep(2.0)
            assert st.alive("query")
            i = info(s)
            assert i["submaps"] == 3 and i["version"] == 2, i
            status, msg2 = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok" and msg2["map_version"] == 2
            np.testing.assert_array_equal(sc.unarr(msg2["sdf"]), sc.unarr(msg["sdf"]))
            # A late joiner: the service restarted gets every submap and the index with gets.
            st.stop_one("query")
            st.start(only=["query"])
            wait_for(lambda: info(s).get("submaps") == 3 and info(s).get("baked_version") == 2, 90, period=1.0,
                     what="the restarted service to get the whole map")
            status, msg3 = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok" and msg3["map_version"] == 2 and msg3["baked"] is True
            np.testing.assert_allclose(sc.unarr(msg3["sdf"]), want.sdf, atol=1e-5)
            qa.undeclare()
            qi.undeclare()
        finally:
            s.close()


def test_e2e_real_submap_mapper_answers_planners(tmp_path):
    """The real mapper with ``--submaps`` (protocol 1.3) and the real frontend and query
    service: the query service holds every submap the index lists, answers planners from
    the baked blend of them, and its answers equal an in-process engine fed the same
    messages (heard by this test on the same keys)."""
    ns = NS + "/real"
    mapper = ["--preset", "cpu", "--mapper", "submaps", "--set", "training.network.width=32", "--set", "submap.cell_m=3"]
    frontend = ["--set", "n_frames=200", "--set", "width=80", "--set", "height=60", "--set", "linger=true", "--fast"]
    heard: dict = {"submaps": {}, "index": None, "surfels": None}
    lock = threading.Lock()

    def on_surfels(sample):
        smap = protocol.SurfelMap.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            old = heard["surfels"]
            if old is None or (smap.epoch, smap.version) > (old.epoch, old.version):
                heard["surfels"] = smap

    def on_submap(sample):
        snap = protocol.WeightSnapshot.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            old = heard["submaps"].get(snap.submap["id"])
            if old is None or (snap.epoch, snap.version) > (old.epoch, old.version):
                heard["submaps"][snap.submap["id"]] = snap

    def on_index(sample):
        idx = protocol.SubmapIndex.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            if heard["index"] is None or (idx.epoch, idx.version) > (heard["index"].epoch, heard["index"].version):
                heard["index"] = idx

    def qinfo(s):
        status, msg = sc.request(s, f"{ns}/info/query", {"v": 1}, 2.0)
        return msg if status == "ok" else {}

    with Stack(services=("query", "mapper", "frontend"), namespace=ns,
               args={"mapper": mapper, "frontend": frontend}) as st:
        s = sc.open_session(st.endpoints)
        try:
            subs = [s.declare_subscriber(f"{ns}/map/submaps/*", on_submap),
                    s.declare_subscriber(f"{ns}/map/index", on_index),
                    s.declare_subscriber(f"{ns}/map/surfels", on_surfels)]

            def fe_done():
                status, msg = sc.request(s, f"{ns}/info/frontend", {"v": 1}, 2.0)
                return status == "ok" and msg.get("done") and msg.get("pending") == 0

            wait_for(fe_done, 240, period=2.0, what="every keyframe acknowledged")
            time.sleep(3.0)
            # This test joined late too: what it missed, it gets (the subscription keeps the newest).
            for r in s.get(f"{ns}/map/submaps/**", timeout=5.0):
                if r.ok is not None:
                    on_submap(r.ok)
            assert st.stop_one("mapper") == 0  # the map stops changing: its last messages stand
            time.sleep(2.0)
            with lock:
                idx, snaps, surfels = heard["index"], dict(heard["submaps"]), heard["surfels"]
            assert idx is not None and len(idx.submaps) >= 2, idx
            assert surfels is not None
            assert set(snaps) == set(idx.submaps)
            wait_for(lambda: (lambda i: i.get("submaps") == len(idx.submaps) and i.get("version") == idx.version
                              and i.get("baked_version") == idx.version)(qinfo(s)), 120, period=1.0,
                     what="the query service to hold and bake the final map")
            assert qinfo(s)["measured_points"] == sum(len(sn.measured["points"]) for sn in snaps.values()) > 0
            e = QueryEngine(device="cpu")
            for snap in snaps.values():
                assert e.set_submap(snap)
            assert e.set_index(idx) == [] and e.state.version == idx.version
            e.set_surfels(surfels)
            seq = SyntheticSequence(building="office", n_frames=200, H=60, W=80, seed=0)
            pts = eval_points([seq.frame(i) for i in range(0, 200, 20)], n_points=3000, every=1, rng=0)
            req = {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True, "source": "implicit"}
            status, msg = sc.request(s, f"{ns}/query/sdf", req, 60.0)
            assert status == "ok", msg
            want = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, source="implicit"))
            assert msg["map_version"] == idx.version and msg["map_epoch"] == idx.epoch
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(msg["gradient"]), want.gradient, atol=1e-4)
            err = np.abs(sc.unarr(msg["sdf"]) - seq.gt_sdf(pts)).mean()
            status, fused = sc.request(s, f"{ns}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8")}, 60.0)
            assert status == "ok" and fused["baked"] is True
            err_f = np.abs(sc.unarr(fused["sdf"]) - seq.gt_sdf(pts)).mean()
            # 1.4: every submap carries its measured points; the service's exact fused answer is
            # the in-process engine's (the measured-surface rule), the 1.3 answer (measured off)
            # another.
            assert all(sn.measured is not None and len(sn.measured["points"]) > 0 for sn in snaps.values())
            status, ex = sc.request(s, f"{ns}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8"), "exact": True,
                                                           "gradient": True}, 60.0)
            assert status == "ok" and ex["baked"] is False
            want = e.answer_sdf(protocol.SdfRequest(pts, gradient=True, exact=True))
            np.testing.assert_allclose(sc.unarr(ex["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(ex["gradient"]), want.gradient, atol=1e-4)
            e13 = QueryEngine(device="cpu", measured=False)
            for snap in snaps.values():
                assert e13.set_submap(snap)
            e13.set_surfels(surfels)
            err_x = np.abs(want.sdf - seq.gt_sdf(pts)).mean()
            err_13 = np.abs(e13.answer_sdf(protocol.SdfRequest(pts, exact=True)).sdf - seq.gt_sdf(pts)).mean()
            # (Figures only: a walk of seconds trains each submap a few dozen steps.)
            print(f"{len(idx.submaps)} submaps, map version {idx.version}: SDF error {100 * err:.1f} cm (blend), "
                  f"{100 * err_f:.1f} cm (fused, baked), {100 * err_x:.1f} cm (fused, exact; 1.3's answer "
                  f"{100 * err_13:.1f} cm)")
            # A whole-map mesh, tiled.
            status, mesh = sc.request(s, f"{ns}/query/mesh", {"v": 1, "resolution": 0.1}, 120.0)
            assert status == "ok" and sc.unarr(mesh["faces"]).shape[0] > 1000
            for d in subs:
                d.undeclare()
        finally:
            s.close()
