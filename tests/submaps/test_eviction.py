"""The submap mapper's whole-map bound on keyframes (``keyframes.max_keyframes_total``): the
best covered keyframe goes from every submap and from ``frames``; the map still answers, its
measured points stay, and checkpoints (new and old) restore it."""

import numpy as np
import pytest
import torch

from aisdf.keyframes import keyframe_message
from aisdf.mapper.factory import make_mapper, restore_mapper
from aisdf.synthetic import SyntheticSequence

torch.set_num_threads(1)
SMALL = {"network": {"width": 16}, "n_rays": 10}


@pytest.fixture(scope="module")
def seq():
    return SyntheticSequence(building="atlanta", n_frames=200, H=45, W=60, seed=1)


def build(seq, limit, frames=range(0, 200, 8)):
    p = make_mapper("submaps", "cpu", SMALL, keyframes={"max_keyframes_total": limit, "skip_redundant": False})
    sizes = []
    for i in frames:
        p.add_keyframe(keyframe_message(seq.frame(i)))
        sizes.append(p.n_keyframes)
        p.step()
    return p, sizes


def test_eviction_keeps_the_bound_and_the_map(seq):
    p, sizes = build(seq, 6)
    full, _ = build(seq, 2000)
    assert max(sizes) == 6 and p.n_keyframes == 6 and p.stats()["evicted"] == 25 - 6
    assert full.n_keyframes == 25 and full.stats()["evicted"] == 0
    kept = set(p.frames)
    assert set(p.intake.coverage.views) == kept
    for sm in p.submaps.values():  # evicted from every submap's training store too
        assert {k.frame.key for k in sm.trainer.store.keyframes} <= kept and set(sm.seen_by) <= kept
        assert len(sm.trainer.store) >= 1
    assert ("depth", 192) in kept and ("depth", 184) in kept  # the newest two stay
    # What the map learnt stays: the measured points are those of every keyframe it was sent.
    np.testing.assert_array_equal(p.measured.points(), full.measured.points())
    pts = seq.poses[100][:3, 3] + np.random.default_rng(0).uniform(-1, 1, (200, 3))
    assert np.all(np.isfinite(p.sdf(pts)))
    for _ in range(5):
        p.step()


def test_checkpoint_round_trip_with_evictions(seq):
    p, _ = build(seq, 6)
    back = restore_mapper(p.checkpoint())
    assert list(back.frames) == list(p.frames) and back.stats()["evicted"] == p.stats()["evicted"]
    assert back.kf_policy.max_keyframes_total == 6
    np.testing.assert_array_equal(back.measured.points(), p.measured.points())  # not rebuilt from 6 keyframes
    for c, sm in p.submaps.items():
        assert [k.frame.key for k in back.submaps[c].trainer.store.keyframes] == \
               [k.frame.key for k in sm.trainer.store.keyframes]
    pts = seq.poses[100][:3, 3] + np.random.default_rng(1).uniform(-1, 1, (200, 3))
    np.testing.assert_array_equal(back.sdf(pts), p.sdf(pts))
    back.add_keyframe(keyframe_message(seq.frame(199)))  # resumed: the bound still holds
    assert back.n_keyframes == 6 and back.stats()["evicted"] == p.stats()["evicted"] + 1
    back.step()
    # A checkpoint from before the bound (no policy, counters or pool): defaults, the pool rebuilt.
    old = {k: v for k, v in p.checkpoint().items() if k not in ("keyframes", "redundant", "evicted", "measured")}
    again = restore_mapper(old)
    assert again.kf_policy.max_keyframes_total == 2000 and again.stats()["evicted"] == 0
    assert list(again.frames) == list(p.frames) and 0 < len(again.measured.points()) <= len(p.measured.points())
    np.testing.assert_array_equal(again.sdf(pts), p.sdf(pts))
