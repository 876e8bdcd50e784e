"""aisdf.mapping: losses, bounds, sampling, replay window, trainer, convergence on an analytic room."""

import math

import numpy as np
import pytest
import torch

from aisdf.mapping import PRESETS, Frame, KeyframeStore, Trainer, TrainingConfig, training_config
from aisdf.mapping.presets import submap_training_config
from aisdf.mapping.bounds import batch_bounds
from aisdf.mapping.frames import StoredFrame
from aisdf.mapping.losses import eikonal_term, grad_term, sdf_term, training_loss
from aisdf.mapping.sampling import FREE, SURFACE, SURFEL, ray_depths, sample_batch, sample_frame
from aisdf.structure.surfel_types import Surfels

torch.set_num_threads(1)  # 2 threads stall badly when another process holds a core

# ----------------------------------------------------------------------------- analytic scene
ROOM_C, ROOM_H = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.5, 1.25])  # 4 x 3 x 2.5 m room
BOX_C, BOX_H = np.array([0.8, 0.6, -0.85]), np.array([0.4, 0.35, 0.4])  # a 0.8 m box on the floor


def box_sdf(p, c, h):
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def scene_sdf(p):
    """Exact SDF in free space: the room's inside is free, the box is solid."""
    return np.minimum(-box_sdf(p, ROOM_C, ROOM_H), box_sdf(p, BOX_C, BOX_H))


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def render(T_WC, K, H, W):
    """z-depth by ray/slab intersection: exit of the room box, entry of the obstacle box."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T_WC[:3, :3].T
    o = T_WC[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_room = np.maximum((ROOM_C - ROOM_H - o) / d, (ROOM_C + ROOM_H - o) / d).min(-1)
        b1, b2 = (BOX_C - BOX_H - o) / d, (BOX_C + BOX_H - o) / d
        tn, tf = np.minimum(b1, b2).max(-1), np.maximum(b1, b2).min(-1)
    hit = (tn <= tf) & (tn > 0)
    return np.where(hit, np.minimum(tn, t_room), t_room).astype(np.float32)  # dirs have z = 1


K_SMALL = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])


def room_frames(n=6, H=60, W=80, K=K_SMALL):
    frames = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([0.9 * np.cos(a) - 0.3, 0.7 * np.sin(a), 0.2])
        T = look_at(eye, eye + np.array([np.cos(a + 2.2), np.sin(a + 2.2), -0.35]))
        frames.append(Frame(k, float(k), render(T, K, H, W), K, T))
    return frames


def eval_points(frames, n, rng):
    """iSDF's protocol: random valid pixels, one point per ray uniform in [0.1, D + 0.1]."""
    pts = []
    for f in frames:
        H, W = f.depth.shape
        idx = rng.integers(0, H * W, n)
        u, v, D = idx % W, idx // W, f.depth.reshape(-1)[idx]
        z = rng.uniform(0.1, D + 0.1)
        p_C = np.stack([(u - f.K[0, 2]) / f.K[0, 0], (v - f.K[1, 2]) / f.K[1, 1], np.ones(n)], -1) * z[:, None]
        pts.append(p_C @ f.T_WC[:3, :3].T + f.T_WC[:3, 3])
    return np.concatenate(pts)


def floor_surfels():
    """One surfel on the room's floor (z = -1.25), normal up, 1 x 2 m."""
    return Surfels(center=[[0.0, 0.0, -1.25]], normal=[[0, 0, 1.0]], axis1=[[1.0, 0, 0]], axis2=[[0, 1.0, 0]],
                   extent=[[1.0, 2.0]], direction=[-1], keyframe=[0])


# ----------------------------------------------------------------------------- losses
def test_sdf_term_hand_computed():
    f = torch.tensor([0.5, 1.5, -0.2, 0.1, 0.1, 0.0])
    b = torch.tensor([1.0, 1.0, 1.0, 0.2, -0.1, 0.2937])
    want = [
        0.0,  # free: max(relu(-0.5), exp(-2.5) - 1) = 0
        0.5,  # free: relu(0.5)
        math.e - 1.0,  # free: exp(1) - 1
        0.1 * 5.383,  # band
        0.2 * 5.383,  # band, behind the surface
        0.2937 * 5.383,  # b == t is the band
    ]
    torch.testing.assert_close(sdf_term(f, b), torch.tensor(want), rtol=1e-6, atol=1e-7)


def test_eikonal_and_grad_terms_hand_computed():
    grad = torch.tensor([[3.0, 0, 0], [3.0, 0, 0], [0, 0.5, 0], [1.0, 0, 0]])
    b = torch.tensor([0.05, 0.1, 2.0, 0.5])
    torch.testing.assert_close(eikonal_term(grad, b), torch.tensor([0.0, 2.0, 0.5, 0.0]))
    torch.testing.assert_close(eikonal_term(grad), torch.tensor([2.0, 2.0, 0.5, 0.0]))
    target = torch.tensor([[0, 1.0, 0], [-2.0, 0, 0], [float("nan")] * 3, [1.0, 1.0, 0]])
    torch.testing.assert_close(grad_term(grad, target), torch.tensor([1.0, 2.0, 0.0, 1 - 1 / math.sqrt(2)]))


def test_training_loss_totals_and_surfel_switch():
    f = torch.tensor([0.1, 1.5, 0.2, -0.1])
    grad = torch.tensor([[0, 0, 2.0], [1.0, 0, 0], [0, 0, 1.0], [0, 0, 1.0]])
    b = torch.tensor([0.0, 1.0, 0.0, 0.0])
    g = torch.tensor([[0, 0, 1.0], [0, 1.0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    kind = torch.tensor([SURFACE, FREE, SURFEL, SURFEL])
    slot = torch.tensor([0, 0, 1, 1])
    # iSDF per point: sdf + 0.268 eik (b >= 0.1 only) + 0.018 (1 - cos)
    p0 = 0.1 * 5.383
    p1 = 0.5 + 0.268 * 0.0 + 0.018 * 1.0
    p2 = 0.2 * 5.383 + 0.018 * 2.0  # surfel point through iSDF's loss: b = 0, g = v
    p3 = 0.1 * 5.383
    loss, terms, per_frame = training_loss(f, grad, b, g, kind, slot, 2, TrainingConfig(surfel_mask=True))
    assert float(loss) == pytest.approx((p0 + p1 + p2 + p3) / 4, rel=1e-6)
    assert terms["sdf"] + terms["eikonal"] + terms["grad"] + terms["surfel"] == pytest.approx(terms["loss"], rel=1e-6)
    np.testing.assert_allclose(per_frame, [(p0 + p1) / 2, (p2 + p3) / 2], rtol=1e-6)
    # Surfel loss on: |f| + 0.4 (1 - cos) + 0.2 |‖∇f‖ - 1| on surfel points, iSDF's on the others.
    s2 = 0.2 + 0.4 * 2.0 + 0.2 * 0.0
    s3 = 0.1 + 0.0 + 0.0
    # Default ("joint"): one mean over all points, each with the loss of its kind.
    loss, terms, per_frame = training_loss(f, grad, b, g, kind, slot, 3, TrainingConfig(surfel_loss=True))
    assert float(loss) == pytest.approx((p0 + p1 + s2 + s3) / 4, rel=1e-6)
    assert terms["surfel"] == pytest.approx((s2 + s3) / 4, rel=1e-6)
    assert terms["sdf"] + terms["eikonal"] + terms["grad"] + terms["surfel"] == pytest.approx(terms["loss"], rel=1e-6)
    np.testing.assert_allclose(per_frame[:2], [(p0 + p1) / 2, (s2 + s3) / 2], rtol=1e-6)
    # "separate": mean over the non-surfel points + mean over the surfel points.
    cfg = TrainingConfig(surfel_loss=True, surfel_loss_mean="separate")
    loss, terms, per_frame = training_loss(f, grad, b, g, kind, slot, 3, cfg)
    assert float(loss) == pytest.approx((p0 + p1) / 2 + (s2 + s3) / 2, rel=1e-6)
    assert terms["surfel"] == pytest.approx((s2 + s3) / 2, rel=1e-6)
    assert np.isnan(per_frame[2])
    np.testing.assert_allclose(per_frame[:2], [(p0 + p1) / 2, (s2 + s3) / 2], rtol=1e-6)


# ----------------------------------------------------------------------------- bounds
@pytest.mark.parametrize("method", ["kdtree", "cdist"])
def test_batch_bounds_hand_made(method):
    nan = float("nan")
    pts = torch.tensor([
        [0, 0, 2.0], [1.0, 0, 2.0],  # SURFACE samples (D = 2)
        [0, 0, 1.0],  # FREE in front: nearest (0,0,2) at 1
        [1.0, 0, 2.05],  # FREE behind: nearest (1,0,2) at 0.05, negative
        [0.9, 0, 1.5],  # FREE: nearest (1,0,2)
        [3.0, 0, 1.2],  # SURFEL point, normal (0,0,-1)
        [3.0, 0, 1.0],  # FREE: nearest is the surfel point (Eq. 1)
    ])
    z = torch.tensor([2.0, 2.0, 1.0, 2.05, 1.5, nan, 1.0])
    D = torch.tensor([2.0, 2.0, 2.0, 2.0, 2.0, nan, 2.0])
    kind = torch.tensor([SURFACE, SURFACE, FREE, FREE, FREE, SURFEL, FREE])
    target = torch.full((7, 3), nan)
    target[0] = torch.tensor([0, 0, -1.0])
    target[1] = torch.tensor([0.6, 0, -0.8])
    target[5] = torch.tensor([0, 0, -1.0])
    b, g = batch_bounds(pts, z, D, kind, target, method)
    d4 = math.sqrt(0.1**2 + 0.5**2)
    torch.testing.assert_close(b, torch.tensor([0, 0, 1.0, -0.05, d4, 0, 0.2]), rtol=1e-5, atol=1e-6)
    want_g = torch.tensor([[0, 0, -1.0], [0.6, 0, -0.8], [0, 0, -1.0], [0, 0, -1.0],
                           [-0.1 / d4, 0, -0.5 / d4], [0, 0, -1.0], [0, 0, -1.0]])
    torch.testing.assert_close(g, want_g, rtol=1e-5, atol=1e-5)
    # Without the surfel point the last sample's nearest point is (1,0,2) (plain iSDF).
    keep = kind != SURFEL
    b2, _ = batch_bounds(pts[keep], z[keep], D[keep], kind[keep], target[keep], method)
    assert float(b2[-1]) == pytest.approx(math.sqrt(5.0), rel=1e-6)


# ----------------------------------------------------------------------------- sampling
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


# ----------------------------------------------------------------------------- window
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


# ----------------------------------------------------------------------------- presets and trainer
def test_presets():
    paper = training_config("paper")
    assert paper.model_dump(exclude={"preset"}) == TrainingConfig().model_dump(exclude={"preset"})
    assert (paper.n_rays, paper.window_size, paper.lr, paper.weight_decay) == (200, 5, 1.3e-3, 1.2e-2)
    cpu = training_config("cpu", seed=3, network={"octaves": 4})
    assert cpu.preset == "cpu" and cpu.seed == 3 and cpu.network.octaves == 4
    assert cpu.network.width == PRESETS["cpu"]["network"]["width"]
    assert training_config("auto").preset == ("paper" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="unknown training preset"):
        training_config("fast")
    # submaps on the cpu preset: narrower networks whose rate settles; the caller's overrides win
    sub = submap_training_config("cpu", seed=3)
    assert (sub.network.width, sub.lr_settle, sub.n_rays, sub.seed) == (64, 2e-4, cpu.n_rays, 3)
    assert (sub.lr_halflife_steps, sub.lr_settle_after, sub.replay_uniform, cpu.replay_uniform) == (10, 5, 1, 0)
    assert cpu.lr_settle is None and submap_training_config("cpu", network={"width": 32}).network.width == 32
    assert submap_training_config("paper") == paper


def _tiny_cfg(**kw):
    return training_config("cpu", device="cpu", network={"width": 32}, n_rays=20, **kw)


@pytest.mark.parametrize("switches", [{}, {"surfel_mask": True}, {"surfel_mask": True, "surfel_loss": True}])
def test_two_step_smoke_training(switches):
    trainer = Trainer(_tiny_cfg(surfels_replace_rays=True, **switches))
    frames = room_frames(3)
    frames[1].surfels = floor_surfels()
    for f in frames:
        trainer.add_keyframe(f)
    infos = [trainer.step() for _ in range(2)]
    assert trainer.steps == 2 and trainer.n_keyframes == 3 and trainer.dropped_keyframes == 0
    info = infos[-1]
    spr = trainer.cfg.samples_per_ray
    assert np.isfinite(info["loss"]) and info["n_points"] == 3 * 20 * spr  # a surfel replaces a ray
    assert info["n_surfel_points"] == (spr if switches else 0)  # all 3 frames are in the window
    assert set(info["timings_ms"]) >= {"sampling", "bound", "forward", "backward", "total"}
    d, g = trainer.sdf_grad(np.zeros((5, 3)))
    assert d.shape == (5,) and g.shape == (5, 3) and np.allclose(trainer.sdf(np.zeros((5, 3))), d)


def test_checkpoint_resume_is_exact():
    trainer = Trainer(_tiny_cfg(max_keyframes=3))
    for f in room_frames(4):
        trainer.add_keyframe(f)
    for _ in range(3):
        trainer.step()
    ck = trainer.checkpoint()
    resumed = Trainer.from_checkpoint(ck)
    assert (resumed.steps, resumed.n_keyframes, resumed.dropped_keyframes) == (3, 3, 1)
    a, b = trainer.step(), resumed.step()
    assert a["loss"] == b["loss"] and a["window"] == b["window"]
    for k, v in trainer.state_numpy().items():
        np.testing.assert_array_equal(v, resumed.state_numpy()[k])


def test_learning_rate_settles_while_no_keyframe_arrives_and_restarts_with_one():
    frames = room_frames(3)
    paper = Trainer(_tiny_cfg())
    paper.add_keyframe(frames[0])
    paper.step()
    assert paper.learning_rate() == paper.optimizer.param_groups[0]["lr"] == 1.3e-3  # iSDF's constant rate
    tr = Trainer(_tiny_cfg(lr_settle=2e-4, lr_halflife_steps=2))
    tr.add_keyframe(frames[0])
    rates = []
    for _ in range(5):
        tr.step()
        rates.append(tr.optimizer.param_groups[0]["lr"])
    # steps 0..4 since the keyframe: the excess over 2e-4 (1.1e-3) halves every 2 steps
    assert rates == pytest.approx([2e-4 + 1.1e-3 * 0.5 ** (k / 2) for k in range(5)], rel=1e-12)
    tr.add_keyframe(frames[1])  # a new view: back to the full rate, then settling again
    tr.step()
    assert tr.optimizer.param_groups[0]["lr"] == pytest.approx(1.3e-3)
    resumed = Trainer.from_checkpoint(tr.checkpoint())
    assert resumed.learning_rate() == tr.learning_rate() == pytest.approx(2e-4 + 1.1e-3 * 0.5 ** 0.5)
    start = Trainer(_tiny_cfg(lr_settle=2e-4, lr_halflife_steps=2, lr_decay_from="start"))
    start.add_keyframe(frames[0])
    for _ in range(4):
        start.step()
    start.add_keyframe(frames[1])
    assert start.learning_rate() == pytest.approx(2e-4 + 1.1e-3 * 0.25)  # a keyframe does not restart it
    # a network short of steps for its keyframes (here 3 per keyframe) keeps the full rate
    short = Trainer(_tiny_cfg(lr_settle=2e-4, lr_halflife_steps=2, lr_settle_after=3))
    short.add_keyframe(frames[0])
    short.add_keyframe(frames[1])
    rates = []
    for _ in range(8):
        short.step()
        rates.append(short.optimizer.param_groups[0]["lr"])
    assert rates == pytest.approx([1.3e-3] * 6 + [2e-4 + 1.1e-3 * 0.5 ** (k / 2) for k in (6, 7)], rel=1e-12)


N_CONVERGENCE_STEPS = 120


def test_convergence_on_analytic_room():
    """The cpu preset learns the room: iSDF's evaluation points (uniform in [0.1, D + 0.1] along
    seen rays) against the exact SDF."""
    frames = room_frames(6)
    trainer = Trainer(training_config("cpu", device="cpu"))
    for f in frames:
        trainer.add_keyframe(f)
    pts = eval_points(frames, 500, np.random.default_rng(1))
    gt = scene_sdf(pts)
    err0 = np.abs(trainer.sdf(pts) - gt).mean()
    for _ in range(N_CONVERGENCE_STEPS):
        trainer.step()
    err = np.abs(trainer.sdf(pts) - gt).mean()
    print(f"mean |sdf error|: untrained {err0:.3f} m, after {trainer.steps} steps {err:.3f} m")
    assert err0 > 0.3
    assert err < 0.10

