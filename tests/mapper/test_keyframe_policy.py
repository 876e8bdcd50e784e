"""Keyframes that add nothing new are not stored (a parked robot does not grow the map), a walk
keeps all of its keyframes, and masked pixels (protocol 1.10) are no measurement."""

import numpy as np
import pytest
import torch

from aisdf import protocol
from aisdf.keyframes import KeyframeSelector, keyframe_message
from aisdf.mapper.factory import make_mapper, restore_mapper
from aisdf.synthetic import SyntheticSequence
from aisdf.observed import pack_keys
from aisdf.structure.measured import DEFAULT_VOXEL
from aisdf.synthetic.render import render_depth

torch.set_num_threads(1)
SMALL = {"network": {"width": 16}, "n_rays": 10}


@pytest.fixture(scope="module")
def seq():
    return SyntheticSequence(building="atlanta", n_frames=120, H=45, W=60, seed=1)


def parked(seq, n, i=10, first_id=0):
    """``n`` keyframes at frame ``i``'s pose, each with its own depth noise, 5 s apart."""
    f = seq.frame(i)
    for j in range(n):
        d = render_depth(seq.scene, f["T_WC"], seq.K, seq.H, seq.W, seq.noise, (seq.seed, 100_000 + j))
        yield protocol.Keyframe(first_id + j, 5.0 * j, d, f["K"], f["T_WC"])


@pytest.mark.parametrize("kind", ["submaps", "single"])
def test_a_parked_robot_adds_a_handful_of_keyframes(seq, kind):
    p = make_mapper(kind, "cpu", SMALL)
    stored = [p.add_keyframe(kf) for kf in parked(seq, 300)]
    assert 1 <= p.n_keyframes == sum(stored) <= 5, p.n_keyframes
    assert p.stats()["redundant"] == 300 - p.n_keyframes
    p.step()
    back = restore_mapper(p.checkpoint())  # the counter survives a checkpoint
    assert back.stats()["redundant"] == p.stats()["redundant"] and back.n_keyframes == p.n_keyframes
    # Off: every one of them is stored.
    off = make_mapper(kind, "cpu", SMALL, keyframes={"skip_redundant": False})
    assert all(off.add_keyframe(kf) for kf in parked(seq, 30))
    assert off.n_keyframes == min(30, off.cfg.max_keyframes) and off.stats()["redundant"] == 0


def test_a_walk_keeps_every_keyframe(seq):
    """The redundancy test drops nothing a frontend selects on a walk through new space."""
    walk = SyntheticSequence(building="office", n_frames=900, H=45, W=60, seed=1)
    sel = KeyframeSelector()
    kfs = [keyframe_message(f) for f in walk if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"])]
    counts = {}
    for on in (True, False):
        p = make_mapper("submaps", "cpu", SMALL, keyframes={"skip_redundant": on})
        for kf in kfs:
            p.add_keyframe(kf)
        counts[on] = p.n_keyframes
    assert counts[True] == counts[False] == len(kfs) > 20, counts


def test_revisiting_a_pose_later_is_redundant_but_new_space_is_not(seq):
    p = make_mapper("submaps", "cpu", SMALL)
    first = seq.frame(10)
    p.add_keyframe(keyframe_message(first))
    for kf in list(parked(seq, 4, first_id=1000)):  # the noise's voxels fill in
        p.add_keyframe(kf)
    n = p.n_keyframes
    assert not p.add_keyframe(next(parked(seq, 1, first_id=2000))) and p.n_keyframes == n
    assert p.add_keyframe(keyframe_message(seq.frame(60)))  # far away: new space


def masked_keyframe(seq, i, box, u2=False):
    f = seq.frame(i)
    d = f["depth"]
    mask = np.zeros(d.shape, np.uint8)
    mask[box] = 1
    if u2:
        raw = np.clip(np.round(np.nan_to_num(d) * 1000), 0, 65535).astype(np.uint16)
        return protocol.Keyframe(f["frame_id"], f["stamp"], raw, f["K"], f["T_WC"], 1000.0, mask=mask)
    return protocol.Keyframe(f["frame_id"], f["stamp"], d, f["K"], f["T_WC"], mask=mask)


def box_points(kf, box):
    """World points of the depth pixels inside ``box`` (those a mask hides)."""
    d = kf.depth.astype(np.float64) / (kf.depth_scale or 1.0)
    v, u = np.mgrid[0:d.shape[0], 0:d.shape[1]]
    v, u, D = v[box].ravel(), u[box].ravel(), d[box].ravel()
    ok = D > 0
    K = kf.K
    P = np.stack([(u[ok] - K[0, 2]) / K[0, 0] * D[ok], (v[ok] - K[1, 2]) / K[1, 1] * D[ok], D[ok]], -1)
    return P @ kf.T_WC[:3, :3].T + kf.T_WC[:3, 3]


@pytest.mark.parametrize("u2", [False, True])
def test_masked_pixels_are_no_measurement(seq, u2):
    """A box of masked pixels (a person a detector found): the wire round trip keeps the mask,
    no measured point is there, the stored keyframe holds no depth there (nothing trains on it)."""
    box = (slice(10, 30), slice(20, 40))
    kf = protocol.Keyframe.from_msg(protocol.unpack(protocol.pack(masked_keyframe(seq, 10, box, u2).to_msg())))
    assert kf.mask is not None and kf.mask[box].all() and kf.mask.sum() == 20 * 20
    assert not kf.depth_m()[box].any()
    inner = (slice(14, 26), slice(24, 36))  # pixels 4 from the mask's edge: voxels only they reach
    hidden = pack_keys(np.floor(box_points(kf, inner) / DEFAULT_VOXEL).astype(np.int64))
    assert len(hidden) > 100
    p = make_mapper("submaps", "cpu", SMALL)
    assert p.add_keyframe(kf)
    stored = p.frames[(kf.sensor, kf.frame_id)]
    assert not stored.depth[box].any() and stored.depth[20, 5] > 0  # masked: 0 = invalid; the rest kept
    assert not stored.valid()[box].any()  # rays are drawn from valid pixels only: none trains there
    assert (stored.scale == 1000.0) == u2  # <u2 depth is still held raw (masked pixels 0 in it)
    assert not np.isin(hidden, p.measured.keys).any()  # none of the masked surface is measured
    unmasked = make_mapper("submaps", "cpu", SMALL)
    unmasked.add_keyframe(keyframe_message(seq.frame(10)))
    assert np.isin(hidden, unmasked.measured.keys).all()  # the same keyframe unmasked measures it
    for _ in range(3):
        p.step()  # trains on the rest


def test_a_bad_mask_is_rejected_and_changes_nothing(seq):
    good = masked_keyframe(seq, 10, (slice(0, 5), slice(0, 5)))
    msg = good.to_msg()
    for bad, why in [
        (protocol.encode_array(np.zeros((4, 4), np.uint8)), "shape"),
        (protocol.encode_array(np.zeros(good.depth.shape, np.float32)), "dtype"),
        (protocol.encode_array(np.full(good.depth.shape, 255, np.uint8)), "0 \\(keep\\) or 1"),
        ("nope", "array map"),
    ]:
        with pytest.raises(protocol.ProtocolError, match=why):
            protocol.Keyframe.from_msg({**msg, "mask": bad})
    no_mask = {k: v for k, v in msg.items() if k != "mask"}  # an old frontend: nothing masked
    assert protocol.Keyframe.from_msg(no_mask).mask is None
    p = make_mapper("submaps", "cpu", SMALL)
    p.add_keyframe(keyframe_message(seq.frame(0)))
    before = (p.n_keyframes, len(p.measured), p.stats()["redundant"], p.observed.nbytes())
    wrong = masked_keyframe(seq, 30, (slice(0, 5), slice(0, 5)))
    wrong.mask = np.zeros((3, 3), np.uint8)  # in-process: the same refusal, as ValueError
    with pytest.raises(ValueError, match="mask shape"):
        p.add_keyframe(wrong)
    assert (p.n_keyframes, len(p.measured), p.stats()["redundant"], p.observed.nbytes()) == before


def test_a_source_frame_with_a_mask_goes_out_with_it(seq):
    f = dict(seq.frame(5))
    f["mask"] = np.zeros(f["depth"].shape, bool)
    f["mask"][:4, :4] = True
    for enc in ("f4", "u2"):
        kf = keyframe_message(f, depth_encoding=enc)
        back = protocol.Keyframe.from_msg(protocol.unpack(protocol.pack(kf.to_msg())))
        assert back.mask.dtype == np.uint8 and back.mask.sum() == 16 and not back.depth_m()[:4, :4].any()
    assert keyframe_message(seq.frame(5)).to_msg().get("mask") is None  # no mask: the key is absent
