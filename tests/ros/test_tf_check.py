"""The TF check refuses on evidence that the chain is wrong (consecutive depth images that the
poses do not explain), not on a fixed frame that is not z-up: that is a warning."""

import numpy as np
import pytest

from aisdf.ros.check import check_frames
from aisdf.synthetic import SyntheticSequence


@pytest.fixture(scope="module")
def frames():
    """The office's frames in a z-up fixed frame (the synthetic world turned so that the
    cameras' mean image 'down' axis is -z), as a right chain gives them."""
    seq = SyntheticSequence(building="office", n_frames=360, H=60, W=80, seed=0)
    fr = [seq.frame(i) for i in range(0, 360, 30)]
    d = np.mean([np.asarray(f["T_WC"])[:3, 1] for f in fr], axis=0)
    d /= np.linalg.norm(d)
    z = np.array([0.0, 0.0, -1.0])
    v, c = np.cross(d, z), float(d @ z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + vx + vx @ vx / (1 + c)  # the rotation taking d to -z
    return [dict(f, T_WC=T @ np.asarray(f["T_WC"])) for f in fr]


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    T[1:3, 1:3] = [[c, -s], [s, c]]
    return T


def test_a_fixed_frame_that_is_not_z_up_maps_with_a_warning(frames):
    right = check_frames(frames)
    assert right.ok and right.warning is None and right.figures["image_down_vs_gravity_deg"] < 45
    # The same chain in a fixed frame turned 120 degrees about x: every pose turned alike.
    turned = [dict(f, T_WC=_rot_x(120) @ np.asarray(f["T_WC"])) for f in frames]
    v = check_frames(turned)
    assert v.figures["image_down_vs_gravity_deg"] > 70  # the gravity test alone would refuse it
    assert v.ok, str(v)
    assert "not z-up" in v.warning and "agree with the poses" in v.warning and "Warning:" in str(v)
    assert v.figures["consistent_pairs"] == right.figures["consistent_pairs"] > 0


def test_the_optical_rotation_missing_is_still_refused_in_words(frames):
    # camera_link -> optical missing: the poses are those of a frame turned by REP-103's rotation
    link_from_optical = np.eye(4)
    link_from_optical[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    wrong = [dict(f, T_WC=np.asarray(f["T_WC"]) @ np.linalg.inv(link_from_optical)) for f in frames]
    v = check_frames(wrong)
    assert not v.ok and v.warning is None
    assert "consecutive depth images disagree" in v.message and "optical rotation" in v.message
