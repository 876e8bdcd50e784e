"""Protocol 1.11's PoseCorrections and PosesApplied: round trips, and every malformed request
refused with a clear error (the mapper changes nothing for it: tests/mapper/test_repose.py,
tests/e2e/test_e2e_poses.py)."""

import numpy as np
import pytest

from aisdf import protocol
from aisdf.poses import corrections_message


def rot_z(deg, t=(0.0, 0.0, 0.0)):
    a = np.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def test_round_trip():
    c = {3: rot_z(10, (1, 2, 3)), 7: np.eye(4)}
    msg = protocol.unpack(protocol.pack(corrections_message("cam_a", c)))
    back = protocol.PoseCorrections.from_msg(msg)
    assert back.sensor == "cam_a" and back.frame_ids == [3, 7]
    np.testing.assert_array_equal(back.as_dict()[3], c[3])
    assert msg["T_WC"]["dtype"] == "<f8" and msg["T_WC"]["shape"] == [2, 4, 4]
    rep = protocol.PosesApplied("cam_a", 1, [7], 0, 2, 12, 5, 0.5)
    assert protocol.PosesApplied.from_msg(protocol.unpack(protocol.pack(rep.to_msg()))) == rep
    # the default sensor, and an empty batch (nothing to do) is valid
    empty = protocol.PoseCorrections.from_msg({"v": 1, "frame_ids": [], "T_WC": protocol.encode_array(
        np.zeros((0, 4, 4)), "<f8")})
    assert empty.sensor == "depth" and empty.frame_ids == []


def arr(T):
    return protocol.encode_array(np.asarray(T, np.float64), "<f8")


@pytest.mark.parametrize("msg, code, text", [
    ({"v": 1, "T_WC": arr(np.eye(4)[None])}, "bad_request", "missing field 'frame_ids'"),
    ({"v": 1, "frame_ids": [1], "T_WC": arr(np.eye(4))}, "bad_request", "'T_WC' must have shape Nx4x4"),
    ({"v": 1, "frame_ids": [1, 2], "T_WC": arr(np.eye(4)[None])}, "bad_request", "holds 1 poses for 2 frame ids"),
    ({"v": 1, "frame_ids": [1, 1], "T_WC": arr(np.stack([np.eye(4)] * 2))}, "bad_request", "distinct; repeated: [1]"),
    ({"v": 1, "frame_ids": [True], "T_WC": arr(np.eye(4)[None])}, "bad_request", "list of integers"),
    ({"v": 1, "frame_ids": "1", "T_WC": arr(np.eye(4)[None])}, "bad_request", "list of integers"),
    ({"v": 1, "frame_ids": [5], "T_WC": arr(np.diag([1.0, 1, 1.5, 1])[None])}, "bad_request",
     "T_WC of frame 5 is not a rigid"),
    ({"v": 1, "frame_ids": [5], "T_WC": arr(np.full((1, 4, 4), np.nan))}, "bad_request", "T_WC of frame 5"),
    ({"v": 1, "frame_ids": [5], "T_WC": protocol.encode_array(np.eye(4)[None], "<f4")}, "bad_request",
     "dtype '<f4' not accepted"),
    ({"v": 1, "sensor": 3, "frame_ids": [5], "T_WC": arr(np.eye(4)[None])}, "bad_request", "'sensor' must be"),
    ({"v": 1, "frame_ids": list(range(protocol.MAX_POSE_CORRECTIONS + 1)), "T_WC": arr(np.eye(4)[None])},
     "too_large", "at most"),
])
def test_malformed_requests_are_refused_in_words(msg, code, text):
    with pytest.raises(protocol.ProtocolError) as e:
        protocol.PoseCorrections.from_msg(msg)
    assert e.value.code == code and text in e.value.message


def test_the_client_checks_before_sending():
    with pytest.raises(protocol.ProtocolError, match="T_WC of frame 4 is not a rigid"):
        corrections_message("depth", {4: np.diag([2.0, 1, 1, 1])})
    with pytest.raises(ValueError):
        corrections_message("depth", {4: np.eye(3)})
