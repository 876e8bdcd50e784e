"""aisdf.mapping: the presets, the trainer (smoke training, exact checkpoint resume, the settling
learning rate) and convergence on the analytic room."""

import numpy as np
import pytest
import torch

from aisdf.mapping import PRESETS, Trainer, TrainingConfig, training_config
from aisdf.mapping.presets import submap_training_config
from helpers.analytic_room import eval_points, floor_surfels, room_frames, scene_sdf

torch.set_num_threads(1)  # 2 threads stall badly when another process holds a core


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


def test_the_surfel_prior_caps_free_samples_bounds_in_training():
    """``surfel_bounds``: each step asks the trainer's prior about its free samples, and a prior
    that knows a surface nearer than the batch does changes the training; one that knows none
    (or the switch off) leaves the step exactly as iSDF's."""
    calls = []

    def near(points):  # known surface 1 cm from every sample
        calls.append(len(points))
        return np.full(len(points), 0.01), np.tile([0.0, 0.0, 1.0], (len(points), 1))

    def nothing(points):
        return np.full(len(points), np.inf), np.zeros((len(points), 3))

    losses = {}
    for name, prior, on in (("near", near, True), ("nothing", nothing, True), ("off", near, False)):
        trainer = Trainer(_tiny_cfg(surfel_bounds=on))
        trainer.bound_prior = prior
        for f in room_frames(3):
            trainer.add_keyframe(f)
        losses[name] = trainer.step()["loss"]
    assert len(calls) == 1 and calls[0] > 0  # asked once (the switch off: never), about the free samples
    assert losses["nothing"] == losses["off"]
    assert losses["near"] != losses["nothing"], losses


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

