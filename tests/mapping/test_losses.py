"""aisdf.mapping: the training losses (SDF, eikonal and gradient terms, totals) and the free-space
bounds of a batch, on hand-computed values."""

import math

import numpy as np
import pytest
import torch

from aisdf.mapping import TrainingConfig
from aisdf.mapping.bounds import batch_bounds
from aisdf.mapping.losses import eikonal_term, grad_term, sdf_term, training_loss
from aisdf.mapping.sampling import FREE, SURFACE, SURFEL

torch.set_num_threads(1)  # 2 threads stall badly when another process holds a core


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

