"""The mapper's algorithm in-process: keyframe validation, checkpoints, the map's messages,
and the query engine answering from them."""

import numpy as np
import pytest
import torch

from aisdf import protocol, query_messages
from aisdf.mapping.frames import Frame
from aisdf.mapper.single import MappingPipeline
from aisdf.structure.surfel_types import Surfels
from aisdf.synthetic import SyntheticSequence
from aisdf.query.engine import QueryEngine
from aisdf.query.mapstate import MapState

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def seq():
    return SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)


def frame(seq, i):
    f = seq.frame(i)
    return Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"])


def small(atlanta=True):
    return MappingPipeline.from_settings("cpu", {"network": {"width": 32}, "n_rays": 20}, atlanta=atlanta)


def test_bad_keyframes_leave_the_map_untouched(seq):
    p = small()
    p.add_keyframe(frame(seq, 0))
    p.step()
    before = p.trainer.state_numpy()
    empty = frame(seq, 30)
    empty.depth = np.zeros_like(empty.depth)
    with pytest.raises(ValueError, match="valid depth"):
        p.add_keyframe(empty)
    with pytest.raises(ValueError, match="already"):
        p.add_keyframe(frame(seq, 0))
    assert p.n_keyframes == 1 and p.steps == 1
    after = p.trainer.state_numpy()
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_checkpoint_restore_continues_identically(seq):
    p = small()
    for i in (0, 30, 60):
        p.add_keyframe(frame(seq, i))
    for _ in range(3):
        p.step()
    q = MappingPipeline.restore(p.checkpoint())
    assert (q.steps, q.n_keyframes) == (p.steps, p.n_keyframes)
    pts = np.random.default_rng(0).uniform(-1, 1, (100, 3)) + seq.poses[0][:3, 3]
    np.testing.assert_array_equal(p.sdf(pts), q.sdf(pts))
    assert len(q.surfels()) == len(p.surfels())
    p.step()
    q.step()
    np.testing.assert_allclose(p.sdf(pts), q.sdf(pts), atol=1e-6)


def test_messages_and_query_engine_agree(seq):
    p = small()
    for i in (0, 20, 40, 60, 80):
        p.add_keyframe(frame(seq, i))
    for _ in range(5):
        p.step()
    snap = protocol.WeightSnapshot.from_msg(protocol.unpack(protocol.pack(p.weight_snapshot(3).to_msg())))
    assert snap.version == 3 and snap.step == 5 and np.asarray(snap.model["bounds"]).shape == (2, 3)
    smap = p.surfel_map(3)
    assert smap is not None
    smap = protocol.SurfelMap.from_msg(protocol.unpack(protocol.pack(smap.to_msg())))
    v, _ = seq.scene.atlanta_truth()
    assert abs(abs(smap.vertical @ v) - 1) < 1e-3
    assert len(smap) > 0
    eng = QueryEngine(device="cpu")
    with pytest.raises(protocol.ProtocolError) as e:
        eng.answer_sdf(query_messages.SdfRequest(np.zeros((1, 3))))
    assert e.value.code == "no_map"
    assert eng.set_weights(snap) and not eng.set_weights(snap)  # same version: ignored
    pts = seq.poses[0][:3, 3] + np.random.default_rng(1).uniform(-1, 1, (300, 3))
    r = eng.answer_sdf(query_messages.SdfRequest(pts.astype(np.float32), source="implicit", gradient=True))
    np.testing.assert_allclose(r.sdf, p.sdf(pts.astype(np.float32)), atol=1e-5)
    with pytest.raises(protocol.ProtocolError) as e:
        eng.answer_sdf(query_messages.SdfRequest(pts, source="explicit"))
    assert e.value.code == "no_map"  # no surfels yet
    assert eng.set_surfels(smap)
    r_e = eng.answer_sdf(query_messages.SdfRequest(pts, source="explicit"))
    r_f = eng.answer_sdf(query_messages.SdfRequest(pts, gradient=True, collision_epsilon=1.0))
    e13 = QueryEngine(device="cpu", measured=False)  # 1.3's fused answer (1.5 adds the measured points)
    assert e13.set_weights(snap) and e13.set_surfels(smap)
    r13 = e13.answer_sdf(query_messages.SdfRequest(pts, gradient=True))
    assert np.all(r13.sdf <= r.sdf + 1e-6)  # 1.3's fused answer never exceeds the network alone
    assert np.isfinite(r_f.sdf).all() and np.isfinite(r_f.gradient).all()
    assert np.isfinite(r_e.sdf).all() and r_f.collision.shape == (300,)
    eng.max_points = 10
    with pytest.raises(protocol.ProtocolError) as e:
        eng.answer_sdf(query_messages.SdfRequest(pts))
    assert e.value.code == "too_large"


def test_bad_snapshot_keeps_the_old_map(seq):
    p = small(atlanta=False)
    p.add_keyframe(frame(seq, 0))
    p.step()
    assert p.surfel_map(1) is None
    eng = QueryEngine(device="cpu")
    eng.set_weights(p.weight_snapshot(1))
    bad = p.weight_snapshot(2)
    bad.state.pop(next(iter(bad.state)))
    with pytest.raises(ValueError):
        eng.set_weights(bad)
    assert eng.state.version == 1


class Sphere(torch.nn.Module):
    def forward(self, x):
        return (torch.linalg.norm(x, dim=-1) - 0.5).unsqueeze(-1)


def test_mesh_of_a_known_field():
    eng = QueryEngine(device="cpu", mesh_max_cells=10**6)
    eng._state = MapState(7, 0, Sphere(), np.array([[-1.0, -1, -1], [1, 1, 1]]), None, -1)
    m = eng.answer_mesh(query_messages.MeshRequest(0.05))
    r = np.linalg.norm(m.vertices, axis=1)
    assert m.map_version == 7 and len(m.faces) > 100
    assert np.abs(r - 0.5).max() < 0.01
    with pytest.raises(protocol.ProtocolError) as e:
        eng.answer_mesh(query_messages.MeshRequest(0.001))
    assert e.value.code == "too_large"


@pytest.mark.parametrize("mapper", ["single", "submaps"])
def test_a_keyframe_holds_its_depth_once(seq, mapper):
    """The stored frame holds the cleaned depth the training samples (one array, not a raw
    copy beside it) and its surfel mask as packed bits, the caller's frame is left as it was,
    the memory count does not count the depth twice, and a checkpoint brings back the same
    keyframes."""
    from aisdf.mapper.factory import restore_mapper
    from aisdf.submaps.pipeline import SubmapPipeline

    p = small() if mapper == "single" else SubmapPipeline.from_settings(
        "cpu", {"network": {"width": 32}, "n_rays": 20})
    given, masks_given = [], []
    for i in range(0, 40, 8):
        f = frame(seq, i)
        f.depth = f.depth.astype(np.float32)
        f.depth[:3, :3] = np.nan  # invalid pixels: 0 once stored
        raw = f.depth.copy()
        p.add_keyframe(f)
        assert np.array_equal(f.depth, raw, equal_nan=True)  # the caller's frame: untouched
        given.append(raw)
        masks_given.append(f.surfel_mask)  # (the Atlanta module fills the caller's frame)
    stored = p.trainer.store.keyframes if mapper == "single" else list(p.frames.values())
    assert len(stored) == len(given)
    H, W = given[0].shape
    assert sum(m is not None and m.any() for m in masks_given) >= 3  # surfels were found
    for kf, raw, mask in zip(stored, given, masks_given):
        assert kf.frame.depth is kf.depth and kf.depth.dtype == np.float32
        ok = np.isfinite(raw) & (raw > 0)
        assert np.array_equal(kf.depth, np.where(ok, raw, 0))
        # the surfel mask: one bit a pixel in the keyframe, none in the stored frame
        assert kf.frame.surfel_mask is None and (kf.surfel_mask is None) == (mask is None)
        if mask is not None:
            assert np.array_equal(kf.surfel_mask, mask) and kf.surfel_bits.nbytes == -(-H * W // 8)
        # depth 4 B per pixel, the surfel mask 1 bit, the surfels a few hundred bytes (normals
        # are computed where sampled)
        assert kf.nbytes() <= H * W * 4 + H * W // 8 + 4096
    masks = 0 if mapper == "single" else sum(  # submaps: a pixel mask per keyframe and submap it joined
        v.pixel_bits.nbytes for sm in p.submaps.values() for v in sm.trainer.store.keyframes)
    assert p.memory()["keyframes"] == sum(k.nbytes() for k in stored) + masks
    if mapper == "submaps":  # each view's mask, one bit a pixel, is the mask it was given
        for c, sm in p.submaps.items():
            for v in sm.trainer.store.keyframes:
                assert v.pixel_bits.nbytes == -(-H * W // 8) and v.depth is p.frames[v.frame.key].depth
                assert v.surfel_bits is p.frames[v.frame.key].surfel_bits  # shared, not copied
                assert np.array_equal(v.pixel_mask, p._pixel_mask(v, c)) and v.pixel_mask.any()
    p.step()
    back = restore_mapper(p.checkpoint())
    again = back.trainer.store.keyframes if mapper == "single" else list(back.frames.values())
    assert [k.frame.key for k in again] == [k.frame.key for k in stored]
    for a, b in zip(again, stored):
        assert np.array_equal(a.depth, b.depth) and a.frame.depth is a.depth
        assert np.array_equal(a.surfel_bits, b.surfel_bits) if b.surfel_bits is not None else a.surfel_bits is None


def test_one_network_sends_its_measured_points_1_5(seq):
    """Protocol 1.5: the one-network mapper pools every keyframe's depth pixels (as the submap
    mapper does since 1.4) and sends them with each snapshot on ``map/weights``; the query
    service's ``fused`` answer is then the measured-surface rule over them, exactly, and
    nearer the truth than 1.3's. Old parts: a snapshot without points (a 1.4 mapper) and a
    query service with ``measured`` off (as a 1.4 service, which ignored them on
    ``map/weights``) answer 1.3's fused answer. Checkpoints keep the pool; one from before
    1.5 rebuilds it from its keyframes."""
    from aisdf.query.answer import far_floor, surfel_support
    from aisdf.structure.measured import MeasuredPoints, MeasuredSurface, measured_fuse_grad
    from aisdf.structure.surfel_map import explicit_sdf
    from aisdf.metrics import eval_points

    p = small()
    frames = [seq.frame(i) for i in (0, 20, 40, 60, 80)]
    own = MeasuredSurface(max_depth=p.cfg.max_depth)
    for f in frames:
        p.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        own.add(f["depth"], f["K"], f["T_WC"])
    for _ in range(5):
        p.step()
    with pytest.raises(ValueError):  # a bad keyframe leaves the pool as it was
        p.add_keyframe(Frame(99, 0.0, np.zeros_like(frames[0]["depth"]), frames[0]["K"], frames[0]["T_WC"]))
    assert p.memory()["measured"] == p.measured.nbytes() > 0
    msgs = dict(p.map_messages(4))
    snap = protocol.WeightSnapshot.from_msg(protocol.unpack(msgs["map/weights"]))
    smap = protocol.SurfelMap.from_msg(protocol.unpack(msgs["map/surfels"]))
    pts_m = snap.measured["points"]
    assert snap.measured["voxel"] == 0.1 and pts_m.dtype == np.float32
    np.testing.assert_array_equal(pts_m, own.points().astype(np.float32))  # every keyframe's pixels, pooled
    assert len(pts_m) > 1000
    np.testing.assert_array_equal(p.measured_points(), pts_m)

    e, e13 = QueryEngine(device="cpu"), QueryEngine(device="cpu", measured=False)
    old = protocol.WeightSnapshot.from_msg(protocol.unpack(msgs["map/weights"]))
    old.measured = None  # what a 1.4 mapper sent
    e_old = QueryEngine(device="cpu")
    for eng, s in ((e, snap), (e13, snap), (e_old, old)):
        eng.baker.layout_prior = False  # the rule of 1.5 alone (1.13's cap on top: tests/query/test_layout_answer.py)
        assert eng.set_weights(s) and eng.set_surfels(smap)
    assert len(e.state.measured) == len(pts_m) and e13.state.measured is None and e_old.state.measured is None
    pts = eval_points(frames, n_points=3000, every=1, rng=0).astype(np.float32)
    rep = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    r13 = e13.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    r_old = e_old.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    np.testing.assert_array_equal(r_old.sdf, r13.sdf)
    np.testing.assert_array_equal(r_old.gradient, r13.gradient)
    imp = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, source="implicit"))
    d_e, g_e, _ = explicit_sdf(pts.astype(np.float64), Surfels.from_protocol_dict(smap.surfels))
    d_m, g_m = MeasuredPoints(pts_m).nearest(pts, within=2.0)
    want, want_g = measured_fuse_grad(r13.sdf, r13.gradient, imp.sdf, d_e.astype(np.float32),
                                      g_e.astype(np.float32), d_m, g_m, radius=2.0)
    within = np.abs(d_e) <= 2.0  # 1.15's floor, with the surfels its measured points support
    ok = surfel_support(pts, d_e, g_e, d_m, MeasuredPoints(pts_m)) & within
    want, want_g = far_floor(want, want_g, d_m, g_m, np.where(ok, d_e, np.inf), g_e, behind=(d_e < 0) & within)
    np.testing.assert_allclose(rep.sdf, want, atol=1e-6)
    np.testing.assert_allclose(rep.gradient, want_g, atol=1e-5)
    gt = seq.gt_sdf(pts)
    err, err13 = np.abs(rep.sdf - gt).mean(), np.abs(r13.sdf - gt).mean()
    print(f"1.5 answer {100 * err:.2f} cm, 1.3 answer {100 * err13:.2f} cm")
    assert err < err13
    # The bake answers the rule too: this 5-step toy network is far from the truth (tens of
    # centimetres) and the rule bends its field between the bake's samples, so the bake is held
    # to the truth here, not to the exact answer (the query bench measures its fidelity).
    e.bake_now()
    bk = e.answer_sdf(query_messages.SdfRequest(pts))
    err_b = np.abs(bk.sdf - gt).mean()
    print(f"baked 1.5 answer {100 * err_b:.2f} cm")
    assert bk.baked and err_b < err13 and err_b < err + 0.01

    # Checkpoints: the pool as it was; from before 1.5 (no "measured"): rebuilt from the keyframes.
    ck = p.checkpoint()
    q = MappingPipeline.restore(ck)
    np.testing.assert_array_equal(q.measured_points(), pts_m)
    ck.pop("measured")
    np.testing.assert_array_equal(MappingPipeline.restore(ck).measured_points(), pts_m)
    off = MappingPipeline.from_settings("cpu", {"network": {"width": 32}, "n_rays": 20}, measured=False)
    off.add_keyframe(frame(seq, 0))
    assert off.weight_snapshot(1).measured is None and off.memory()["measured"] == 0
    assert MappingPipeline.restore(off.checkpoint()).measured is None


@pytest.mark.parametrize("mapper", ["single", "submaps"])
def test_a_u2_keyframe_is_held_raw_with_the_same_training(seq, mapper):
    """A keyframe sent as ``<u2`` (as the frontend sends it) is held as its raw values, 2 bytes
    a pixel instead of 4, 0 where the cleaned depth is invalid; decoded it is the float depth
    to the bit, so a map fed the same keyframes as ``<f4`` metres trains to the same bits.
    Checkpoints keep the raw values; a frame whose raw depth does not decode to its depth is
    held as floats."""
    from aisdf.mapping.frames import StoredFrame, clean_depth
    from aisdf.geometry import decode_depth, normals_at
    from aisdf.mapper.factory import restore_mapper
    from aisdf.submaps.pipeline import SubmapPipeline

    def make():
        torch.manual_seed(0)
        return small() if mapper == "single" else SubmapPipeline.from_settings(
            "cpu", {"network": {"width": 32}, "n_rays": 20})

    p_u2, p_f = make(), make()
    sent = []
    for i in range(0, 40, 8):
        f = seq.frame(i)
        raw = np.clip(np.round(np.nan_to_num(f["depth"]) * 1000.0), 0, 65535).astype(np.uint16)
        raw[:2, :6] = 0  # no return
        raw[2, :6] = 65000  # 65 m: beyond max_depth, invalid once stored
        kf = protocol.Keyframe(f["frame_id"], f["stamp"], raw, f["K"], f["T_WC"], depth_scale=1000.0)
        sent.append(kf)
        p_u2.add_keyframe(kf)
        p_f.add_keyframe(protocol.Keyframe(f["frame_id"], f["stamp"], kf.depth_m(), f["K"], f["T_WC"]))
    for _ in range(6):
        p_u2.step()
        p_f.step()
    pts = seq.poses[0][:3, 3] + np.random.default_rng(3).uniform(-1.5, 1.5, (500, 3))
    np.testing.assert_array_equal(p_u2.sdf(pts), p_f.sdf(pts))  # the same training, bit for bit

    def stored(p):
        return p.trainer.store.keyframes if mapper == "single" else list(p.frames.values())

    H, W = sent[0].depth.shape
    rng = np.random.default_rng(0)
    for kf, kf_f, k in zip(stored(p_u2), stored(p_f), sent):
        assert kf.scale == 1000.0 and kf.raw.dtype == np.uint16 and kf_f.scale is None
        assert kf.frame.depth is None and kf.frame.depth_raw is kf.raw
        want = clean_depth(k.depth_m(), p_u2.cfg.max_depth)
        np.testing.assert_array_equal(kf.depth, want)
        np.testing.assert_array_equal(kf.depth, kf_f.depth)
        assert not kf.raw[2, :6].any() and np.array_equal(kf.valid(), want > 0)
        pix = rng.integers(0, H * W, 300)
        np.testing.assert_array_equal(kf.depth_at(pix), want.reshape(-1)[pix])
        v, u = pix // W, pix % W
        np.testing.assert_array_equal(normals_at(kf.raw, k.K, v, u, scale=kf.scale), normals_at(want, k.K, v, u))
        assert kf.nbytes() <= H * W * 2 + H * W // 8 + 4096 < kf_f.nbytes()
    ck = p_u2.checkpoint()
    # Version 2 (raw depth): a build that knows only version 1 refuses it with a clear error;
    # a version-1 checkpoint (float depth, the same keyframes) loads into the same map.
    assert (ck["trainer"] if mapper == "single" else ck)["version"] == 2
    v1 = p_f.checkpoint()
    (v1["trainer"] if mapper == "single" else v1)["version"] = 1
    np.testing.assert_array_equal(restore_mapper(v1).sdf(pts), p_f.sdf(pts))
    back = restore_mapper(ck)
    for a, b in zip(stored(back), stored(p_u2)):
        assert a.scale == 1000.0 and np.array_equal(a.raw, b.raw) and a.frame.depth is None
    p_u2.step()
    back.step()
    np.testing.assert_array_equal(back.sdf(pts), p_u2.sdf(pts))  # resumed where it stopped
    f = frame(seq, 0)  # raw depth that does not decode to the frame's depth: held as floats
    f.depth_raw, f.depth_scale = np.zeros(f.depth.shape, np.uint16), 1000.0
    kf = StoredFrame.make(f, 12.0)
    assert kf.scale is None and kf.raw.dtype == np.float32 and np.array_equal(
        kf.depth, clean_depth(f.depth, 12.0)) and not np.array_equal(kf.depth, decode_depth(f.depth_raw, 1000.0))
