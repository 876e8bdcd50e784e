"""AiSDF vs iSDF at equal steps on a small synthetic Atlanta building (the acceptance check,
in miniature): the network trained with the surfel mask and surfel loss, fused with the
explicit surfel map (the paper's Sec. IV-D), has a lower SDF error than iSDF after the
same number of steps, on iSDF's evaluation points (uniform along the rays of the seen
frames) against the building's exact SDF.

Both runs are deterministic (fixed seeds, one torch thread), so the margin only has to
cover platform-level floating-point differences, not sampling noise.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from aisdf.structure.fusion import fuse
from aisdf.mapping.frames import Frame
from aisdf.metrics import eval_points
from aisdf.mapper.single import MappingPipeline
from aisdf.structure.surfel_map import explicit_sdf
from aisdf.synthetic import SyntheticSequence

torch.set_num_threads(1)

N_KEYFRAMES, EVERY = 15, 20       # one keyframe every 20 frames of the trajectory: 260 steps in all
STEPS_FIRST, STEPS_PER = 50, 15   # a quarter of iSDF's 200 / 60
H, W = 120, 160
SEED = 0
MARGIN = 0.85                     # AiSDF + explicit map must be 15% better than iSDF


def _run(seq: SyntheticSequence, frames: list[dict], atlanta: bool):
    # The paper's methods: no surfel bounds, and no free-space clearing (beyond the paper; in this
    # static scene it retires 7 noisy pixels, which is enough to send iSDF's deterministic
    # training down another path: 6.05 cm without, 5.48 cm with, AiSDF's 5.12 cm either way)
    pipe = MappingPipeline.from_settings("cpu", training={"seed": SEED}, atlanta=atlanta,
                                         surfel_mask=True, surfel_loss=True, surfel_bounds=False,
                                         keyframes={"clear_free_space": False})
    for k, f in enumerate(frames):
        pipe.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        for _ in range(STEPS_FIRST if k == 0 else STEPS_PER):
            pipe.step()
    return pipe


@pytest.mark.slow
def test_aisdf_with_explicit_map_beats_isdf_at_equal_steps():
    seq = SyntheticSequence("atlanta", n_frames=N_KEYFRAMES * EVERY, H=H, W=W, seed=SEED)
    frames = [seq.frame(i) for i in range(0, N_KEYFRAMES * EVERY, EVERY)]
    pts = eval_points(frames, n_points=20_000, every=1, rng=SEED)
    gt = seq.gt_sdf(pts)

    isdf = _run(seq, frames, atlanta=False)
    aisdf = _run(seq, frames, atlanta=True)
    assert isdf.steps == aisdf.steps
    err_isdf = float(np.mean(np.abs(isdf.sdf(pts) - gt)))
    implicit = aisdf.sdf(pts)
    fused, _, _ = fuse(implicit, None, explicit_sdf(pts, aisdf.surfels())[0], None)
    err_fused = float(np.mean(np.abs(fused - gt)))
    err_implicit = float(np.mean(np.abs(implicit - gt)))
    msg = f"iSDF {100 * err_isdf:.2f} cm, AiSDF {100 * err_implicit:.2f} cm, AiSDF + explicit {100 * err_fused:.2f} cm"
    assert len(aisdf.surfels()) > 0, msg
    assert err_fused < MARGIN * err_isdf, msg
