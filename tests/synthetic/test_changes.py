"""aisdf.synthetic.changes: the cart is in pass 1's depth and not in pass 2's at the same
pose, the person only in its stretch, the drifted poses and their corrections, and the
ground truth of the scene with and without the cart."""

from __future__ import annotations

import numpy as np
import pytest

from aisdf.geometry import backproject, transform
from aisdf.synthetic import SyntheticSequence
from aisdf.synthetic.changes import (
    CART_SIZE, DRIFT_DEG, DRIFT_M, PERSON_SIZE, ChangingSequence, with_box,
)

N = 300  # frames a pass: the office's loop is 900


def _points_in(seq, frame, box, margin=0.02) -> int:
    """How many of the frame's measured points lie on or in ``box`` (canonical), the floor
    under it left out."""
    pts = transform(seq.true_poses[frame["frame_id"]], backproject(frame["depth"], frame["K"]).reshape(-1, 3))
    c = seq.scene.to_canon(pts[frame["depth"].ravel() > 0])
    return int(np.count_nonzero((box.sdf(c) < margin) & (c[:, 2] > 0.05)))


@pytest.fixture(scope="module")
def cart() -> ChangingSequence:
    return ChangingSequence("office", "cart", n_frames=N, pause_s=2.0, noise=False)


def test_cart_is_in_pass_one_and_gone_in_pass_two_at_the_same_pose(cart):
    assert len(cart) == 2 * N + 60 and cart.removed_at == N + 60
    assert np.allclose(cart.cart.size, CART_SIZE) and cart.cart.center[2] == pytest.approx(CART_SIZE[2] / 2)
    seen = [i for i in range(0, N, 10) if _points_in(cart, cart.frame(i), cart.cart) > 200]
    assert len(seen) >= 3, "the walk sees the cart well"
    for i in seen:
        j = i + cart.removed_at
        assert np.array_equal(cart.poses[i], cart.poses[j]) and cart.pass_of(i) == 1 and cart.pass_of(j) == 2
        d1, d2 = cart.frame(i)["depth"], cart.frame(j)["depth"]
        assert _points_in(cart, cart.frame(j), cart.cart) == 0
        assert np.count_nonzero(d1 < d2 - 0.05) > 200  # the cart stood in front of what pass 2 sees
    # The pause holds pass 1's last pose, the cart still there.
    assert cart.pass_of(N) == 0 and np.array_equal(cart.poses[N + 30], cart.poses[N - 1])
    assert cart.scene_at(cart.removed_at - 1) is not cart.scene and cart.scene_at(cart.removed_at) is cart.scene


def test_cart_stands_clear_of_the_walk_and_the_furniture(cart):
    box_sdf = cart.scene.boxes.sdf(cart.cart.grid(0.1)).min()
    assert box_sdf > 0.1, "no furniture in the cart's box"
    cam = cart.scene.to_canon(cart.poses[:, :3, 3])
    assert cart.cart.sdf(cam).min() > 0.4, "the camera never comes within 0.4 m of the cart"


def test_ground_truth_with_and_without_the_cart(cart):
    c = cart.cart
    # Points above the cart's top (canonical), and one in its middle.
    top = np.array([[c.center[0], c.center[1], CART_SIZE[2] + h] for h in (0.05, 0.2)])
    mid = c.center[None]
    pts = cart.scene.to_world(np.r_[top, mid])
    with_cart, without = cart.gt_sdf(pts, 0), cart.gt_sdf(pts)
    assert with_cart[:2] == pytest.approx([0.05, 0.2], abs=1e-9)
    assert with_cart[2] == pytest.approx(-min(CART_SIZE[:2]) / 2)  # inside: minus the distance to its nearest side
    assert without[2] > 0.3 and (without[:2] > with_cart[:2]).all()
    assert np.array_equal(cart.gt_sdf(pts, cart.removed_at - 1), with_cart)
    assert np.array_equal(without, cart.scene.sdf(pts))
    assert np.array_equal(with_box(cart.scene, c).sdf(pts), with_cart)


def test_person_appears_only_in_its_stretch():
    seq = ChangingSequence("office", "person", n_frames=N, pause_s=1.0, noise=False)
    w = seq.person
    assert 0 < w.first < w.last < N
    assert seq.scene_at(w.first - 1) is seq.scene and seq.scene_at(w.last + 1) is seq.scene
    assert seq.scene_at(N + 30 + w.first) is seq.scene  # not in pass 2
    boxes = [w.at(i) for i in range(w.first, w.last + 1)]
    assert np.allclose(boxes[0].size, PERSON_SIZE)
    moved = np.linalg.norm(boxes[-1].center - boxes[0].center)
    assert moved == pytest.approx(np.linalg.norm(w.end - w.start))
    # Every position lies inside the swept volume; the person is in the depth during its stretch.
    sw = w.swept
    for b in boxes[::10]:
        assert sw.sdf(b.grid(0.1)).max() < 1e-9
    seen = [i for i in range(w.first, w.last + 1, 5) if _points_in(seq, seq.frame(i), w.at(i)) > 50]
    assert len(seen) >= 3
    i = seen[len(seen) // 2]
    assert np.array_equal(seq.poses[i], seq.poses[i + seq.pass_frames + seq.pause_frames])
    later = seq.frame(i + seq.pass_frames + seq.pause_frames)
    assert _points_in(seq, later, w.at(i)) == 0
    # The truth after it is gone is the empty room's: positive over the swept volume.
    assert (seq.gt_sdf(seq.box_points(sw)) > 0).all()


def test_drifted_poses_and_their_corrections():
    seq = ChangingSequence("office", "drift", n_frames=N, noise=False)
    base = SyntheticSequence("office", n_frames=N, noise=False)
    assert len(seq) == N and np.array_equal(seq.true_poses, base.poses)
    sent = np.array([seq.frame(i)["T_WC"] for i in range(0, N, 7)])
    true = seq.true_poses[::7]
    err = np.linalg.norm(sent[:, :3, 3] - true[:, :3, 3], axis=1)
    assert err[0] == 0 and err.max() <= DRIFT_M + 1e-9 and np.all(np.diff(err) >= -1e-12)
    last = np.linalg.norm(seq.frame(N - 1)["T_WC"][:3, 3] - seq.true_poses[N - 1][:3, 3])
    assert last == pytest.approx(DRIFT_M)
    assert abs((sent[:, :3, 3] - true[:, :3, 3]) @ seq.scene.up_W).max() < 1e-9  # horizontal
    R = np.einsum("nji,njk->nik", true[:, :3, :3], sent[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert ang.max() <= DRIFT_DEG + 1e-6
    # The depth is rendered from the true pose; the corrections are the true poses.
    assert np.array_equal(seq.frame(100)["depth"], base.frame(100)["depth"])
    assert np.array_equal(seq.true_frame(100)["T_WC"], base.poses[100])
    corr = seq.corrections([0, 100, N - 1])
    assert sorted(corr) == [0, 100, N - 1] and all(np.array_equal(corr[i], base.poses[i]) for i in corr)


def test_unknown_change_is_refused():
    with pytest.raises(ValueError, match="unknown change"):
        ChangingSequence("office", "flood", n_frames=10)


def test_frontend_streams_a_changing_scene():
    from aisdf_frontend.config import FrontendConfig
    from aisdf_frontend.sources import open_source

    src = open_source(FrontendConfig(change="cart", n_frames=N, change_pause_s=1.0, noise=False))
    assert isinstance(src, ChangingSequence) and src.change == "cart" and len(src) == 2 * N + 30
    assert type(open_source(FrontendConfig(n_frames=10))) is SyntheticSequence
