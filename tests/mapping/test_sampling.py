"""aisdf.mapping: ray depths and samples of a frame, surfel sampling and its mask, and the
keyframe store's replay window (composition, loss weighting, uniform replay, dropping)."""

import numpy as np
import pytest
import torch

from aisdf.mapping import KeyframeStore, TrainingConfig
from aisdf.mapping.frames import StoredFrame
from aisdf.mapping.sampling import SURFACE, SURFEL, ray_depths, sample_frame
from helpers.analytic_room import floor_surfels, room_frames

torch.set_num_threads(1)  # 2 threads stall badly when another process holds a core


def test_ray_depths_ranges():
    rng = np.random.default_rng(0)
    D = np.array([0.05, 1.0, 3.0, 11.9])
    z = ray_depths(D, rng, n_gaussian=7, std=0.1, n_stratified=19, min_depth=0.07, margin=0.1)
    assert z.shape == (4, 27)
    np.testing.assert_array_equal(z[:, 0], D)
    assert np.all(z[:, 1:] >= 0.07 - 1e-12) and np.all(z[:, 1:] <= (D + 0.1)[:, None] + 1e-12)
    edges = 0.07 + (D + 0.1 - 0.07)[:, None] * np.arange(20) / 19  # one stratified sample per bin
    strat = z[:, 8:]
    assert np.all(strat >= edges[:, :-1] - 1e-12) and np.all(strat <= edges[:, 1:] + 1e-12)


def test_sample_frame_counts_and_geometry():
    cfg = TrainingConfig()
    assert cfg.samples_per_ray == 27
    frame = room_frames(1)[0]
    depth = frame.depth.copy()
    depth[:, :40] = 13.0  # beyond 12 m: invalid
    depth[0, 50] = np.nan
    frame.depth = depth
    kf = StoredFrame.make(frame, cfg.max_depth)
    batch = sample_frame(kf, 3, cfg, np.random.default_rng(0))
    assert len(batch) == 200 * 27 and np.all(batch.slot == 3)
    assert (batch.kind == SURFACE).sum() == 200 and np.all(batch.kind.reshape(200, 27)[:, 0] == SURFACE)
    # Every sample lies on its pixel's ray at depth z; rays come from valid pixels only.
    p_C = (batch.points_W - frame.T_WC[:3, 3]) @ frame.T_WC[:3, :3]
    np.testing.assert_allclose(p_C[:, 2], batch.z, rtol=1e-5)
    uv = p_C[:, :2] / p_C[:, 2:] * [frame.K[0, 0], frame.K[1, 1]] + frame.K[:2, 2]
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-3)
    assert u.min() >= 40 and np.all(depth[v, u] > 0) and np.all(depth[v, u] <= 12)
    np.testing.assert_allclose(batch.ray_depth, depth[v, u], rtol=1e-6)
    surf = batch.kind == SURFACE
    np.testing.assert_allclose(np.linalg.norm(batch.target[surf], axis=1)[np.isfinite(batch.target[surf, 0])], 1,
                               atol=1e-2)
    assert np.all(np.isnan(batch.target[~surf]))


def test_surfel_sampling_and_mask():
    frame = room_frames(1)[0]
    mask = np.zeros(frame.depth.shape, bool)
    mask[30:, :] = True
    frame.surfels, frame.surfel_mask = floor_surfels(), mask
    kf = StoredFrame.make(frame, 12.0)
    rng = np.random.default_rng(0)
    # iSDF (both switches off): surfels are ignored.
    b0 = sample_frame(kf, 0, TrainingConfig(), rng)
    assert len(b0) == 200 * 27 and not np.any(b0.kind == SURFEL)
    b = sample_frame(kf, 0, TrainingConfig(surfel_mask=True), rng)
    assert (b.kind == SURFACE).sum() == 200  # default: surfel points come on top of the rays
    b = sample_frame(kf, 0, TrainingConfig(surfel_mask=True, surfels_replace_rays=True), rng)
    assert (b.kind == SURFACE).sum() == 199  # one surfel replaces one ray
    sp = b.points_W[b.kind == SURFEL]
    assert len(sp) == 27
    s = floor_surfels()
    rel = sp - s.center
    assert np.all(np.abs(rel @ s.axis1[0]) <= 0.5 + 1e-6) and np.all(np.abs(rel @ s.axis2[0]) <= 1.0 + 1e-6)
    np.testing.assert_allclose(rel @ s.normal[0], 0, atol=1e-6)
    np.testing.assert_allclose(b.target[b.kind == SURFEL], np.tile([[0, 0, 1.0]], (27, 1)))
    p_C = (b.points_W[b.kind == SURFACE] - frame.T_WC[:3, 3]) @ frame.T_WC[:3, :3]
    v = np.round(p_C[:, 1] / p_C[:, 2] * frame.K[1, 1] + frame.K[1, 2]).astype(int)
    assert v.max() < 30  # rays only from non-surfel pixels
    # Surfel loss alone: surfel points, but rays from every valid pixel, 200 of them.
    b2 = sample_frame(kf, 0, TrainingConfig(surfel_loss=True), rng)
    assert (b2.kind == SURFACE).sum() == 200 and (b2.kind == SURFEL).sum() == 27


def _store(n, **kw):
    store = KeyframeStore(**kw)
    for f in room_frames(n, H=8, W=10, K=np.array([[8.0, 0, 4.5], [0, 8.0, 3.5], [0, 0, 1]])):
        store.add(f)
    return store


def test_window_composition_and_loss_weighting():
    rng = np.random.default_rng(0)
    assert _store(1).window(rng) == [0]
    assert _store(3).window(rng) == [2, 1, 0]
    store = _store(12)
    assert store.losses().tolist() == [1.0] * 12  # untrained: mean of others, 1.0 when none
    store.update_losses(list(range(12)), np.array([100.0] + [1.0] * 9 + [5.0, 5.0]))
    seen = np.zeros(12)
    for _ in range(300):
        w = store.window(rng)
        assert w[:2] == [11, 10] and len(w) == 5 and len(set(w)) == 5 and max(w[2:]) < 10
        seen[w[2:]] += 1
    assert seen[0] == 300  # the high-loss keyframe is (nearly surely) always replayed
    assert 50 < seen[1:10].mean() < 80  # others share the 2 remaining slots: 600 / 9 = 67
    # window_size 3 = 1 replay: P(keyframe 0) = 100 / 109
    store.window_size = 3
    hits = sum(store.window(rng)[2] == 0 for _ in range(2000))
    assert abs(hits / 2000 - 100 / 109) < 0.03


def test_uniform_replay_reaches_keyframes_whose_loss_estimate_is_low():
    rng = np.random.default_rng(1)
    store = _store(12)
    store.update_losses(list(range(12)), np.array([1e-9] * 5 + [100.0] * 5 + [1.0, 1.0]))
    # By loss alone the five low-loss keyframes (a stale estimate: a room learnt earlier) are never replayed.
    assert all(max(store.window(rng)[2:]) >= 5 and min(store.window(rng)[2:]) >= 5 for _ in range(200))
    seen = np.zeros(12)
    for _ in range(2000):
        w = store.window(rng, uniform=1)
        assert w[:2] == [11, 10] and len(w) == 5 and len(set(w)) == 5 and max(w[2:]) < 10
        seen[w[2]] += 1  # the uniform draw
        assert min(w[3:]) >= 5  # the other two: by loss
    assert np.all(np.abs(seen[:10] / 2000 - 0.1) < 0.025)  # uniform over the 10 older keyframes
    all_uniform = [store.window(rng, uniform=3)[2:] for _ in range(2000)]
    assert np.mean([min(w) < 5 for w in all_uniform]) == pytest.approx(1 - (10 - 5) * 4 * 3 / (10 * 9 * 8), abs=0.03)
    assert store.window(rng, uniform=9)[:2] == [11, 10] and len(store.window(rng, uniform=9)) == 5


def test_max_keyframes_drops_lowest_loss_not_newest():
    store = _store(3, max_keyframes=3)
    store.update_losses([0, 1, 2], np.array([2.0, 1.0, 0.1]))
    extra = room_frames(4, H=8, W=10, K=np.array([[8.0, 0, 4.5], [0, 8.0, 3.5], [0, 0, 1]]))[3]
    assert store.add(extra) == [1]  # 2 has a lower loss but is among the newest two
    assert [k.frame.frame_id for k in store.keyframes] == [0, 2, 3] and store.dropped == 1

