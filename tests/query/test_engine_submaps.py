"""The query engine answering from submaps (protocol 1.3), in process: blended answers equal
``aisdf.submaps.field.blend`` over the submaps; values and gradients along lines crossing a
submap boundary have no jump; the engine fed a submap mapper's messages answers as the mapper
does; submap ordering, epochs and malformed snapshots; ``aisdf bench query``'s republished map.

The submap map (the ``submap_map`` fixture, tests/helpers/submap_map.py): three submaps (3 m
cells, 0.5 m overlap) of the synthetic Atlanta building around six keyframes, each a small
network fitted to the building's exact SDF over its own extended box."""

import numpy as np
import pytest
import torch

from aisdf import protocol, query_messages
from aisdf.metrics import eval_points
from aisdf.submaps.field import blend
from aisdf.submaps.grid import SubmapGrid, cell_id
from aisdf.synthetic import SyntheticSequence
from aisdf.query.engine import QueryEngine
from helpers.submap_map import CELLS, EPOCH, band_points, engine_of, evaluators, index

torch.set_num_threads(1)


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
        rep = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, source=source, exact=exact, observed=True))
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
    rep = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, radii=radii, collision_epsilon=0.3))
    assert rep.baked and rep.map_version == 4
    diff = np.abs(rep.sdf + radii - f_ref)
    assert diff.mean() < 0.005 and np.percentile(diff, 99) < 0.03, (diff.mean(), np.percentile(diff, 99))


def line_profile(e, grid, start_W, axis_W, half=0.8, h=0.001, exact=True):
    t = np.arange(-half, half + h / 2, h)
    p = start_W + t[:, None] * axis_W
    rep = e.answer_sdf(query_messages.SdfRequest(p, gradient=True, exact=exact))
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
    rep = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, source="implicit"))
    assert (rep.map_epoch, rep.map_version) == (3, 5)
    np.testing.assert_allclose(rep.sdf, f_ref, atol=1e-5)
    np.testing.assert_allclose(rep.gradient, g_ref, atol=1e-4)


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
    rep = e.answer_sdf(query_messages.SdfRequest(np.zeros((2, 3))))
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


