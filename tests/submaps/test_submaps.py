"""Submaps: the grid and its C¹ blend, the submap pipeline (assignment, training
only what is in view, publishing only what changed, checkpoints, several sensors), maps
far from the origin, and no seams across submap boundaries on a trained map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aisdf import keys, protocol
from aisdf.mapping.frames import Frame
from aisdf.metrics import eval_points
from aisdf.submaps.field import blend
from aisdf.submaps.grid import SubmapGrid, cell_id, parse_cell_id
from aisdf.mapper.factory import restore_mapper
from aisdf.submaps.pipeline import SubmapPipeline
from aisdf.synthetic import SyntheticSequence

R = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix()


def tilted_grid() -> SubmapGrid:
    return SubmapGrid.around(np.array([1.0, 2.0, 3.0]), vertical=R[:, 2], reference=R[:, 0], cell_m=4.0,
                             cell_height_m=6.0, overlap_m=0.5)


def test_cell_ids_round_trip_and_reject_garbage():
    assert cell_id((3, -1, 0)) == "3_-1_0"
    assert parse_cell_id("3_-1_0") == (3, -1, 0)
    for bad in ("3_1", "a_b_c", "1_2_3_4", ""):
        with pytest.raises(ValueError):
            parse_cell_id(bad)


def test_grid_is_aligned_with_the_atlanta_frame_and_centres_the_first_camera():
    g = tilted_grid()
    assert np.allclose(g.R_WG[:, 2], R[:, 2]) and np.allclose(g.R_WG[:, 0], R[:, 0])
    assert tuple(g.cell_of(np.array([[1.0, 2.0, 3.0]]))[0]) == (0, 0, 0)
    assert np.allclose(g.centre_W((0, 0, 0)), [1.0, 2.0, 3.0])


def test_blend_weights_are_a_partition_of_unity_and_c1():
    g = tilted_grid()
    rng = np.random.default_rng(0)
    cells = [(i, j, k) for i in range(-1, 2) for j in range(-1, 2) for k in range(-1, 2)]
    # points well inside the 3x3x3 block of cells: weights of all cells sum to one
    p = g.origin + (rng.uniform([-3, -3, -4], [7, 7, 10], (4000, 3))) @ g.R_WG.T
    total = sum(g.weight(c, p) for c in cells)
    assert np.allclose(total, 1.0, atol=1e-12)
    # weight gradients match finite differences
    for c in [(0, 0, 0), (1, 0, -1)]:
        w, dw = g.weight(c, p, grad=True)
        h = 1e-6
        fd = np.stack([(g.weight(c, p + h * e) - g.weight(c, p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        assert np.abs(fd - dw).max() < 1e-5
    # zero outside the extended box, one deep inside the core
    assert g.weight((0, 0, 0), g.centre_W((0, 0, 0))[None])[0] == 1.0
    assert g.weight((0, 0, 0), g.centre_W((2, 0, 0))[None])[0] == 0.0


def _biased(c):
    bias = 0.05 * (hash(c) % 5)

    def fn(q, grad):
        q = q.astype(np.float64)
        f = np.sin(q[:, 0]) + 0.1 * q[:, 1] * q[:, 2] + bias
        g = np.stack([np.cos(q[:, 0]), 0.1 * q[:, 2], 0.1 * q[:, 1]], axis=1)
        return f, g

    return fn


def test_blend_of_disagreeing_submaps_is_continuous_with_the_exact_gradient():
    """Submaps that disagree by a constant: the blend has no jump, and its gradient is the
    derivative of its values along a line that crosses several boundaries."""
    g = tilted_grid()
    ev = {(i, j, 0): _biased((i, j, 0)) for i in (-1, 0, 1) for j in (-1, 0, 1)}
    d = g.R_WG[:, 0] * 0.8 + g.R_WG[:, 1] * 0.6
    t = np.linspace(-5, 5, 20001)
    pts = g.centre_W((0, 0, 0)) + np.outer(t, d)
    f, grad, covered = blend(g, ev, pts)
    assert covered.all()
    step = t[1] - t[0]
    assert np.abs(np.diff(f.astype(np.float64))).max() < 3 * step  # |f'| <= ~1.3 here: no jumps
    fd = np.diff(f.astype(np.float64)) / step
    an = 0.5 * (grad[:-1] + grad[1:]).astype(np.float64) @ d
    assert np.abs(fd - an).max() < 5e-3
    # inside a core, away from the faces, the answer is that submap's alone
    c = g.centre_W((1, 1, 0))[None]
    assert np.isclose(blend(g, ev, c, grad=False)[0][0], ev[(1, 1, 0)](c.astype(np.float32), False)[0][0], atol=1e-6)
    # points no submap covers get the nearest submap's answer, flagged
    far = g.centre_W((5, 0, 0))[None]
    f2, _, cov2 = blend(g, ev, far)
    assert not cov2[0] and np.isfinite(f2[0])


# ----------------------------------------------------------------------------- pipeline


def office_frames(step: int = 30, n: int = 900, offset=(0.0, 0.0, 0.0)):
    seq = SyntheticSequence(building="office", n_frames=n, H=60, W=80, fps=30, noise=True, seed=0)
    off = np.asarray(offset, float)
    frames = []
    for i in range(0, len(seq), step):
        f = seq.frame(i)
        T = np.array(f["T_WC"], float)
        T[:3, 3] += off
        frames.append(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], T))
    return seq, frames


def small_pipeline(keyframes: dict | None = None, **sub) -> SubmapPipeline:
    cfg = {"cell_m": 3.0, "cell_height_m": 6.0, "overlap_m": 0.4, **sub}
    return SubmapPipeline.from_settings("cpu", training={"seed": 0}, submaps=cfg, **({"keyframes": keyframes} if keyframes else {}))


def test_keyframes_create_submaps_and_steps_train_only_what_is_in_view():
    _, frames = office_frames()
    p = small_pipeline(refine_every=0)
    for f in frames[:3]:
        p.add_keyframe(f)
    assert p.grid is not None and len(p.submaps) >= 1
    # the grid's vertical is the Atlanta vertical the structure module found
    assert abs(p.grid.R_WG[:, 2] @ p.structure.atlanta_frame().vertical) > 0.999
    for _ in range(10):
        p.step()
    before = {c: (sm.trainer.steps, {k: v.copy() for k, v in sm.trainer.state_numpy().items()})
              for c, sm in p.submaps.items()}
    for f in frames[3:]:
        p.add_keyframe(f)
    active = set(p._recent[0]) | set(p._recent[1] if len(p._recent) > 1 else {})
    for _ in range(12):
        info = p.step()
        assert tuple(parse_cell_id(info["submap"])) in active
    for c, (steps, state) in before.items():
        if c not in active:  # out of view: not a single weight moved
            assert p.submaps[c].trainer.steps == steps
            assert all(np.array_equal(state[k], v) for k, v in p.submaps[c].trainer.state_numpy().items())
    assert len(p.submaps) > len(before)  # the walk reached new space
    # every keyframe is stored once, its submaps hold views of the same arrays
    assert p.n_keyframes == len(frames)
    views = [v for sm in p.submaps.values() for v in sm.trainer.store.keyframes]
    assert len(views) >= len(frames)
    assert all(v.depth is p.frames[v.frame.key].depth for v in views)


def test_a_new_submap_starts_from_its_most_trained_neighbour():
    _, frames = office_frames()
    p = small_pipeline(refine_every=0)
    p.add_keyframe(frames[0])
    for _ in range(5):
        p.step()
    first = set(p.submaps)
    trained = {c: sm.trainer.steps for c, sm in p.submaps.items()}
    for f in frames[1:]:
        p.add_keyframe(f)
        new = set(p.submaps) - first
        if new:
            break
    c = sorted(new)[0]
    sm = p.submaps[c]
    donors = [d for d in first if max(abs(d[i] - c[i]) for i in range(3)) == 1 and trained[d] > 0]
    assert donors, "the walk moves into a cell next to a trained one"
    if donors:  # warm: the same network (weights and encoding centre) as the most trained neighbour
        d = max(donors, key=lambda x: (trained[x], cell_id(x)))
        a, b = sm.trainer.state_numpy(), p.submaps[d].trainer.state_numpy()
        assert all(np.array_equal(a[k], b[k]) for k in a)
        assert sm.trainer.cfg.network.offset == p.submaps[d].trainer.cfg.network.offset
    cold = small_pipeline(refine_every=0, warm_start=False)
    cold.add_keyframe(frames[0])
    for _ in range(5):
        cold.step()
    for f in frames[1:]:
        cold.add_keyframe(f)
    for cc, s2 in cold.submaps.items():  # fresh networks are centred on their own cells
        assert np.allclose(s2.trainer.cfg.network.offset, cold.grid.centre_W(cc))


def test_only_changed_submaps_are_published_and_messages_decode():
    _, frames = office_frames()
    # free-space clearing off: it retires the odd voxel of a static walk (a depth edge's noise),
    # which a later keyframe pools again from its own pixels only (tests/mapper/test_clearing.py)
    p = small_pipeline(refine_every=0, keyframes={"clear_free_space": False})
    for f in frames:
        p.add_keyframe(f)
    for _ in range(5):
        p.step()
    msgs = dict(p.map_messages(1, changed_only=False, epoch=7))
    sub = {k: v for k, v in msgs.items() if k.startswith(keys.MAP_SUBMAPS + "/")}
    assert len(sub) == len(p.submaps) and keys.MAP_INDEX in msgs and keys.MAP_SURFELS in msgs
    # 1.4: each submap carries the measured points of its extended box: those of every
    # keyframe's pixels pooled in 10 cm voxels (3 pixels at least), computed here afresh.
    from aisdf.structure.measured import MeasuredSurface

    ref = MeasuredSurface(max_depth=p.cfg.max_depth)
    for f in frames:
        ref.add(f.depth, f.K, f.T_WC)
    ref_pts = ref.points()
    for k, v in sub.items():
        snap = protocol.WeightSnapshot.from_msg(protocol.unpack(v))
        assert snap.submap["id"] == k.rsplit("/", 1)[1] and snap.epoch == 7 and snap.version == 1
        assert snap.observed is not None
        cell = parse_cell_id(snap.submap["id"])
        want = ref_pts[p.grid.inside(cell, ref_pts, grow=p.grid.overlap_m)]
        got = snap.measured["points"]
        assert snap.measured["voxel"] == 0.1 and len(got) == len(want) > 100
        np.testing.assert_allclose(got[np.lexsort(got.T)], want[np.lexsort(want.T)].astype(np.float32), atol=1e-6)
    off = small_pipeline(refine_every=0, measured=False)  # pooling off: 1.3 messages
    off.add_keyframe(frames[0])
    off.step()
    assert all(protocol.WeightSnapshot.from_msg(protocol.unpack(v)).measured is None
               for k, v in off.map_messages(1) if k.startswith(keys.MAP_SUBMAPS + "/"))
    idx = protocol.SubmapIndex.from_msg(protocol.unpack(msgs[keys.MAP_INDEX]))
    assert set(idx.submaps) == {sm.id for sm in p.submaps.values()}
    # nothing trained: only the index and surfels go out
    again = dict(p.map_messages(2))
    assert not any(k.startswith(keys.MAP_SUBMAPS) for k in again)
    info = p.step()
    third = dict(p.map_messages(3))
    assert [k for k in third if k.startswith(keys.MAP_SUBMAPS)] == [f"{keys.MAP_SUBMAPS}/{info['submap']}"]
    idx3 = protocol.SubmapIndex.from_msg(protocol.unpack(third[keys.MAP_INDEX]))
    assert idx3.submaps[info["submap"]]["version"] == 3
    assert all(v["version"] == 1 for k, v in idx3.submaps.items() if k != info["submap"])


def test_background_refinement_is_published_in_batches_and_in_view_submaps_at_once():
    _, frames = office_frames()
    p = small_pipeline(refine_every=0, idle_steps=1, background_publish_steps=3, background_publish_periods=4)
    for f in frames[:6]:
        p.add_keyframe(f)
    for _ in range(4):
        p.step()
    p.map_messages(1)  # everything is published once
    in_view = set().union(*p._recent)
    out_of_view = [sm for c, sm in p.submaps.items() if c not in in_view]
    assert out_of_view, "the test needs a submap the newest keyframes do not see"

    def sent(msgs):
        return {k.rsplit("/", 1)[1] for k, _ in msgs if k.startswith(keys.MAP_SUBMAPS + "/")}

    # idle: every step refines the least trained submap; one step on a submap out of view waits
    target = out_of_view[0]
    target.trainer.step()
    assert target.id not in sent(p.map_messages(2))
    # ... what republishing everything would cost (mark=False) records nothing
    assert target.id in sent(p.map_messages(2, changed_only=False, mark=False))
    assert target.id not in sent(p.map_messages(3))
    # the index lists what was put, not the unpublished steps
    idx = protocol.SubmapIndex.from_msg(protocol.unpack(dict(p.map_messages(4))[keys.MAP_INDEX]))
    assert idx.submaps[target.id]["step"] == target.published_step < target.trainer.steps
    assert target.id not in sent(p.map_messages(5))
    # ... until it has waited background_publish_periods (4) publications since the first that held it back
    assert target.id in sent(p.map_messages(6))
    # or until it has background_publish_steps (3) unpublished steps
    for n in range(3):
        target.trainer.step()
        assert (target.id in sent(p.map_messages(7 + n))) == (n == 2)
    # a submap in view goes out after a single step
    sm = p.submaps[next(iter(p._recent[0]))]
    sm.trainer.step()
    assert sm.id in sent(p.map_messages(10))
    # a resumed pipeline keeps what waits
    target.trainer.step()
    p.map_messages(11)
    q = restore_mapper(p.checkpoint())
    assert q.submaps[target.cell].dirty_since == target.dirty_since == 11 and q.publisher.publications == 11


def test_checkpoint_restores_every_submap_and_continues_identically():
    _, frames = office_frames()
    p = small_pipeline()
    for f in frames[:12]:
        p.add_keyframe(f)
    for _ in range(15):
        p.step()
    ck = p.checkpoint()
    q = restore_mapper(ck)
    assert isinstance(q, SubmapPipeline) and set(q.submaps) == set(p.submaps) and q.n_keyframes == p.n_keyframes
    assert np.array_equal(q.measured.keys, p.measured.keys) and np.array_equal(q.measured.counts, p.measured.counts)
    pts = np.random.default_rng(1).uniform(-3, 3, (500, 3)) + frames[5].T_WC[:3, 3]
    assert np.array_equal(p.sdf(pts), q.sdf(pts))
    for f in frames[12:14]:
        p.add_keyframe(f)
        q.add_keyframe(f)
    for _ in range(5):
        a, b = p.step(), q.step()
        assert a["submap"] == b["submap"] and a["window"] == b["window"]
    assert np.allclose(p.sdf(pts), q.sdf(pts), atol=1e-5)


def test_two_sensors_with_the_same_frame_ids_build_one_map():
    _, frames = office_frames()
    p = small_pipeline()
    a, b = frames[:6], frames[6:12]
    for f in a:
        p.add_keyframe(Frame(f.frame_id, f.stamp, f.depth, f.K, f.T_WC, sensor="robot1"))
    for f, g in zip(b, a):  # robot2 numbers its frames like robot1 does
        p.add_keyframe(Frame(g.frame_id, f.stamp, f.depth, f.K, f.T_WC, sensor="robot2"))
    assert p.n_keyframes == 12
    with pytest.raises(ValueError, match="already in the map"):
        p.add_keyframe(Frame(a[0].frame_id, a[0].stamp, a[0].depth, a[0].K, a[0].T_WC, sensor="robot1"))
    assert p.n_keyframes == 12


def test_bad_keyframe_changes_nothing():
    _, frames = office_frames()
    p = small_pipeline()
    for f in frames[:3]:
        p.add_keyframe(f)
    n, subs, pooled = p.n_keyframes, set(p.submaps), p.measured.counts.copy()
    empty = Frame(999, 0.0, np.zeros_like(frames[3].depth), frames[3].K, frames[3].T_WC)
    with pytest.raises(ValueError, match="valid depth"):
        p.add_keyframe(empty)
    with pytest.raises(ValueError, match="already in the map"):
        p.add_keyframe(frames[1])
    assert p.n_keyframes == n and set(p.submaps) == subs and np.array_equal(p.measured.counts, pooled)


def _map_error(offset, steps: int = 300, settle: int = 0, seed: int = 0) -> float:
    """The office room walked with ``steps`` steps, then ``settle`` more without new keyframes."""
    seq, frames = office_frames(step=45, offset=offset)
    p = SubmapPipeline.from_settings("cpu", training={"seed": seed})
    per = max(1, steps // len(frames))
    for f in frames:
        p.add_keyframe(f)
        for _ in range(per):
            p.step()
    for _ in range(settle):
        p.step()
    raw = [seq.frame(i) for i in range(0, len(seq), 45)]
    pts = eval_points(raw, n_points=4000, every=1, rng=np.random.default_rng(0), far_margin=0.1)
    gt = seq.gt_sdf(pts)
    return float(np.abs(p.sdf(pts + np.asarray(offset)) - gt).mean())


@pytest.mark.slow
def test_a_room_200m_from_the_origin_maps_as_well_as_at_the_origin():
    """Submaps centre their encodings on themselves: 200 m away is no different.

    One training run is chaotic: the room shifted by 1 mm mapped 6.48 cm against 6.05 cm
    unshifted (seed 0, 300 steps), and single seeds at 200 m ranged 0.94-1.20x the origin's.
    So the test compares settled maps (200 steps after the walk), averaged over two seeds:
    measured 1.029 and 1.038x for seeds 0 and 1."""
    near = np.mean([_map_error((0.0, 0.0, 0.0), settle=200, seed=s) for s in (0, 1)])
    far = np.mean([_map_error((200.0, -150.0, 10.0), settle=200, seed=s) for s in (0, 1)])
    print(f"office error at the origin {100 * near:.2f} cm, 250 m away {100 * far:.2f} cm")
    assert far <= 1.1 * near


def test_answers_across_a_submap_boundary_have_no_seam():
    """A trained map: along lines crossing submap faces, value steps stay far below the map's
    own error and the gradient is the derivative of the values (no kinks)."""
    seq, frames = office_frames(step=60)
    p = small_pipeline()
    for f in frames:
        p.add_keyframe(f)
        for _ in range(6):
            p.step()
    assert len(p.submaps) >= 2
    g = p.grid
    # a line through the first camera's cell along the grid's x axis, crossing two faces
    c0 = g.centre_W(g.cell_of(frames[0].T_WC[:3, 3][None])[0])
    t = np.linspace(-g.cell_m, g.cell_m, 4001)
    pts = c0 + np.outer(t, g.R_WG[:, 0]) - 0.5 * g.R_WG[:, 2]
    f, grad = p.sdf_grad(pts)
    f = f.astype(np.float64)
    step = t[1] - t[0]
    jumps = np.abs(np.diff(f))
    err = float(np.abs(p.sdf(pts) - seq.gt_sdf(pts)).mean())
    assert jumps.max() < max(0.1 * err, 3 * step), (jumps.max(), err)
    fd = np.diff(f) / step
    an = 0.5 * (grad[:-1] + grad[1:]).astype(np.float64) @ g.R_WG[:, 0]
    assert np.median(np.abs(fd - an)) < 0.05 and np.quantile(np.abs(fd - an), 0.99) < 0.5
