"""Protocol v1 codec: a round trip per message, messages built by hand as a stranger's
client would (straight from protocol.md), and every kind of malformed payload."""

import math

import msgpack
import numpy as np
import pytest

from aisdf import protocol as P
from aisdf import query_messages as Q


def arr(a, dtype):
    """An array map built by hand, as protocol.md describes it."""
    a = np.ascontiguousarray(np.asarray(a, dtype=np.dtype(dtype)))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def pose(yaw=0.3, t=(1.0, 2.0, 0.5)):
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])


def keyframe_msg(**over):
    depth = np.full((120, 160), 2000, dtype="<u2")
    m = {"v": 1, "frame_id": 7, "stamp": 1.25, "depth": arr(depth, "<u2"), "depth_scale": 1000.0,
         "K": arr(K, "<f8"), "T_WC": arr(pose(), "<f8"), "sensor": "kinect"}
    m.update(over)
    return m


# ----------------------------------------------------------------------------- round trips


def roundtrip(msg):
    return P.unpack(P.pack(msg))


def test_array_roundtrip_all_dtypes():
    for dt in P.ALLOWED_DTYPES:
        a = (np.arange(24).reshape(2, 3, 4) % 200).astype(np.dtype(dt))
        b = P.decode_array(roundtrip({"v": 1, "a": P.encode_array(a)})["a"], "a")
        assert b.dtype == np.dtype(dt) and b.shape == (2, 3, 4)
        np.testing.assert_array_equal(a, b)


def test_encode_array_makes_little_endian():
    a = np.arange(5, dtype=">f4")
    m = P.encode_array(a)
    assert m["dtype"] == "<f4"
    np.testing.assert_array_equal(P.decode_array(m, "a"), a)


def test_keyframe_roundtrip_u2_and_f4():
    depth = np.random.default_rng(0).integers(0, 5000, (120, 160)).astype(np.uint16)
    kf = P.Keyframe(3, 0.5, depth, K, pose(), depth_scale=1000.0, sensor="cam0")
    back = P.Keyframe.from_msg(roundtrip(kf.to_msg()))
    assert back.frame_id == 3 and back.stamp == 0.5 and back.sensor == "cam0" and back.depth_scale == 1000.0
    np.testing.assert_array_equal(back.depth, depth)
    np.testing.assert_allclose(back.depth_m(), depth / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(back.T_WC, pose())
    d = np.full((120, 160), 1.5, np.float32)
    d[0, 0] = np.nan
    back = P.Keyframe.from_msg(roundtrip(P.Keyframe(4, 1.0, d, K, pose()).to_msg()))
    assert back.depth_scale is None and back.depth_m()[0, 0] == 0.0 and back.depth_m()[1, 1] == 1.5


def test_weight_snapshot_roundtrip():
    st = {"layers.0.weight": np.ones((4, 3), np.float32), "layers.0.bias": np.zeros(4, np.float32)}
    s = P.WeightSnapshot(5, 1200, 3.5, {"arch": "isdf", "width": 4}, st)
    b = P.WeightSnapshot.from_msg(roundtrip(s.to_msg()))
    assert (b.version, b.step, b.stamp, b.model) == (5, 1200, 3.5, {"arch": "isdf", "width": 4})
    np.testing.assert_array_equal(b.state["layers.0.weight"], st["layers.0.weight"])


def test_weight_snapshot_measured_points_1_4():
    """1.4: a snapshot may carry the measured points of its space; a 1.3 snapshot (without
    them) decodes as before, and a message built by hand from the README decodes."""
    st = {"w": np.ones(2, np.float32)}
    pts = np.array([[0.0, 1.0, 2.0], [3.5, -1.0, 0.25]], np.float32)
    s = P.WeightSnapshot(5, 10, 1.0, {"arch": "isdf"}, st, measured={"voxel": 0.1, "points": pts})
    b = P.WeightSnapshot.from_msg(roundtrip(s.to_msg()))
    assert b.measured["voxel"] == 0.1 and b.measured["points"].dtype == np.float32
    np.testing.assert_array_equal(b.measured["points"], pts)
    assert P.WeightSnapshot.from_msg(roundtrip(P.WeightSnapshot(5, 10, 1.0, {}, st).to_msg())).measured is None
    hand = {"v": 1, "version": 1, "step": 0, "stamp": 0.0, "model": {}, "state": {},
            "measured": {"voxel": 0.1, "points": arr(pts, "<f4")}}
    np.testing.assert_array_equal(P.WeightSnapshot.from_msg(roundtrip(hand)).measured["points"], pts)
    for m, match in (({"voxel": 0.0, "points": arr(pts, "<f4")}, "positive"),
                     ({"voxel": 0.1, "points": arr(pts[:, :2], "<f4")}, "measured.points"),
                     ({"voxel": 0.1, "points": arr(pts, "<f8")}, "measured.points"),
                     ({"voxel": 0.1, "points": arr([[0, np.nan, 0]], "<f4")}, "non-finite"),
                     ({"points": arr(pts, "<f4")}, "voxel"), ([1, 2], "measured")):
        bad({**hand, "measured": m}, P.WeightSnapshot, match=match)


def test_surfel_map_roundtrip():
    n = 3
    rng = np.random.default_rng(1)
    surf = {"center": rng.normal(size=(n, 3)).astype(np.float32), "normal": np.tile([0, 0, 1], (n, 1)).astype(np.float32),
            "axis1": np.tile([1, 0, 0], (n, 1)).astype(np.float32), "axis2": np.tile([0, 1, 0], (n, 1)).astype(np.float32),
            "extent": np.ones((n, 2), np.float32), "direction": np.array([-1, 0, 1], np.int32),
            "keyframe": np.array([4, -1, 9], np.int64)}
    m = P.SurfelMap(2, 9.0, np.array([0, 0, 1.0]), np.array([[1.0, 0, 0], [0, 1, 0]]), surf)
    b = P.SurfelMap.from_msg(roundtrip(m.to_msg()))
    assert len(b) == 3 and b.version == 2
    for k in surf:
        np.testing.assert_array_equal(b.surfels[k], surf[k])
    empty = P.SurfelMap.from_msg(roundtrip(P.SurfelMap(0, 0.0, np.array([0, 0, 1.0]), np.zeros((0, 3))).to_msg()))
    assert len(empty) == 0 and empty.horizontal.shape == (0, 3)


def test_sdf_request_reply_roundtrip():
    pts = np.random.default_rng(2).normal(size=(10, 3))
    r = Q.SdfRequest.from_msg(roundtrip(Q.SdfRequest(pts, True, 0.5, "implicit").to_msg()))
    assert r.gradient and r.collision_epsilon == 0.5 and r.source == "implicit"
    np.testing.assert_allclose(r.points, pts.astype(np.float32))
    rep = Q.SdfReply(3, np.arange(10, dtype=np.float32), np.ones((10, 3), np.float32), np.zeros(10, np.float32))
    b = Q.SdfReply.from_msg(roundtrip(rep.to_msg()))
    assert b.map_version == 3 and b.gradient.shape == (10, 3) and b.collision.shape == (10,)
    b = Q.SdfReply.from_msg(roundtrip(Q.SdfReply(1, np.zeros(2, np.float32)).to_msg()))
    assert b.gradient is None and b.collision is None and b.unknown is None and b.surfel_version is None
    # 1.19: the surfel map behind the values, only when said; not an integer: refused
    assert Q.SdfReply.from_msg(roundtrip(Q.SdfReply(1, np.zeros(2, np.float32), surfel_version=4).to_msg())).surfel_version == 4
    with pytest.raises(P.ProtocolError):
        Q.SdfReply.from_msg({**Q.SdfReply(1, np.zeros(2, np.float32)).to_msg(), "surfel_version": "4"})
    # 1.6: "unknown" only when asked, both ways; absent from a request that does not ask.
    assert "unknown" not in Q.SdfRequest(pts).to_msg()
    assert Q.SdfRequest.from_msg(roundtrip(Q.SdfRequest(pts, unknown=True).to_msg())).unknown
    u = np.array([0.0, 0.25], np.float32)
    b = Q.SdfReply.from_msg(roundtrip(Q.SdfReply(1, np.zeros(2, np.float32), unknown=u).to_msg()))
    np.testing.assert_array_equal(b.unknown, u)
    with pytest.raises(P.ProtocolError):  # one distance per point
        Q.SdfReply.from_msg(roundtrip(Q.SdfReply(1, np.zeros(3, np.float32), unknown=u).to_msg()))
    with pytest.raises(P.ProtocolError):
        Q.SdfRequest.from_msg({**Q.SdfRequest(pts).to_msg(), "unknown": "yes"})


def test_mesh_roundtrip():
    assert Q.MeshRequest.from_msg(roundtrip(Q.MeshRequest(0.05).to_msg())).resolution == 0.05
    assert Q.MeshRequest.from_msg(roundtrip(Q.MeshRequest().to_msg())).resolution is None
    rep = Q.MeshReply(4, np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32))
    b = Q.MeshReply.from_msg(roundtrip(rep.to_msg()))
    assert b.map_version == 4 and b.faces.tolist() == [[0, 1, 2]]


def test_error_roundtrip():
    e = P.decode_error(P.pack(P.error_message("too_large", "1e9 points")))
    assert e.code == "too_large" and e.message == "1e9 points"
    assert P.decode_error(b"\xc1").code == "internal"


# ----------------------------------------------------------------------------- a stranger's messages


def test_hand_built_messages_decode():
    """Bytes built with msgpack alone, from protocol.md, not with this project's encoder."""
    raw = msgpack.packb(keyframe_msg(), use_bin_type=True)
    kf = P.Keyframe.from_msg(P.unpack(raw))
    assert kf.frame_id == 7 and kf.sensor == "kinect"
    assert np.allclose(kf.depth_m(), 2.0)
    req = msgpack.packb({"v": 1, "points": arr([[0, 0, 0], [1, 2, 3]], "<f8")}, use_bin_type=True)
    r = Q.SdfRequest.from_msg(P.unpack(req))
    assert r.points.shape == (2, 3) and not r.gradient and r.source == "fused" and r.collision_epsilon is None


def test_unknown_keys_are_ignored():
    m = keyframe_msg(future_field={"x": 1}, another=[1, 2])
    assert P.Keyframe.from_msg(P.unpack(P.pack(m))).frame_id == 7


# ----------------------------------------------------------------------------- malformed


def bad(msg_or_bytes, cls=P.Keyframe, code="bad_request", match=None):
    with pytest.raises(P.ProtocolError) as ei:
        raw = msg_or_bytes if isinstance(msg_or_bytes, (bytes, type(None))) else msgpack.packb(msg_or_bytes, use_bin_type=True)
        cls.from_msg(P.unpack(raw))
    assert ei.value.code == code
    if match:
        assert match in ei.value.message, ei.value.message
    return ei.value


@pytest.mark.parametrize(
    "payload, match",
    [
        (None, "empty"),
        (b"", "empty"),
        (b"\xc1\xc1\xc1", "MessagePack"),
        (msgpack.packb([1, 2, 3]), "map"),
        (msgpack.packb({"frame_id": 1}), "version"),
        (msgpack.packb({"v": 2}), "version 2"),
        (msgpack.packb({"v": "1"}), "integer"),
    ],
)
def test_malformed_envelopes(payload, match):
    bad(payload, match=match)


@pytest.mark.parametrize(
    "over, match",
    [
        ({"frame_id": "7"}, "frame_id"),
        ({"frame_id": True}, "frame_id"),
        ({"stamp": float("nan")}, "finite"),
        ({"depth": [1, 2, 3]}, "array map"),
        ({"depth": {"dtype": "<u2", "shape": [2, 2]}}, "missing 'data'"),
        ({"depth": {"dtype": "float32", "shape": [2, 2], "data": b"0" * 16}}, "dtype"),
        ({"depth": {"dtype": "<f8", "shape": [2, 2], "data": b"0" * 32}}, "not accepted"),
        ({"depth": {"dtype": "<u2", "shape": [120, 160], "data": b"00"}}, "bytes"),
        ({"depth": {"dtype": "<u2", "shape": [-1, 4], "data": b""}}, "non-negative"),
        ({"depth": {"dtype": "<u2", "shape": [19200], "data": bytes(38400)}}, "shape"),
        ({"depth": {"dtype": "<u2", "shape": [2, 3], "data": "abc"}}, "binary"),
        ({"depth_scale": 0}, "positive"),
        ({"depth_scale": "mm"}, "number"),
        ({"K": None}, "array map"),
        ({"K": arr(np.eye(4), "<f8")}, "3x3"),
        ({"K": arr(np.eye(3) * 0, "<f8")}, "pinhole"),
        ({"K": arr([[300, 0, 5000], [0, 300, 60], [0, 0, 1]], "<f8")}, "does not match K"),
        ({"T_WC": arr(np.eye(4) * 2, "<f8")}, "rigid"),
        ({"T_WC": arr(np.diag([1.0, 1, -1, 1]), "<f8")}, "rigid"),
        ({"T_WC": arr(np.full((4, 4), np.nan), "<f8")}, "rigid"),
        ({"sensor": 5}, "sensor"),
    ],
)
def test_malformed_keyframes(over, match):
    bad(keyframe_msg(**over), match=match)


def test_missing_keyframe_fields():
    for k in ("frame_id", "stamp", "depth", "K", "T_WC"):
        m = keyframe_msg()
        del m[k]
        bad(m)
    m = keyframe_msg()
    del m["depth_scale"]
    bad(m, match="depth_scale")


def test_negative_float_depth_rejected():
    d = np.full((120, 160), 1.0, np.float32)
    d[3, 3] = -1
    bad(keyframe_msg(depth=arr(d, "<f4")), match="negative")


@pytest.mark.parametrize(
    "msg, match",
    [
        ({"v": 1}, "points"),
        ({"v": 1, "points": arr(np.zeros((4, 2)), "<f4")}, "shape"),
        ({"v": 1, "points": arr(np.zeros(3), "<f4")}, "shape"),
        ({"v": 1, "points": arr(np.zeros((4, 3)), "<i4")}, "not accepted"),
        ({"v": 1, "points": arr([[np.nan, 0, 0]], "<f4")}, "non-finite"),
        ({"v": 1, "points": arr(np.zeros((1, 3)), "<f4"), "gradient": "yes"}, "gradient"),
        ({"v": 1, "points": arr(np.zeros((1, 3)), "<f4"), "gradient": 1}, "gradient"),
        ({"v": 1, "points": arr(np.zeros((1, 3)), "<f4"), "collision_epsilon": -1}, "positive"),
        ({"v": 1, "points": arr(np.zeros((1, 3)), "<f4"), "collision_epsilon": "2"}, "number"),
        ({"v": 1, "points": arr(np.zeros((1, 3)), "<f4"), "source": "magic"}, "source"),
    ],
)
def test_malformed_sdf_requests(msg, match):
    bad(msg, Q.SdfRequest, match=match)


def test_too_large_checked_before_decoding():
    msg = {"v": 1, "points": {"dtype": "<f4", "shape": [1_000_001, 3], "data": b""}}
    with pytest.raises(P.ProtocolError) as ei:
        Q.SdfRequest.from_msg(P.unpack(msgpack.packb(msg)), max_points=1_000_000)
    assert ei.value.code == "too_large"


def test_mesh_request_bad_resolution():
    bad({"v": 1, "resolution": 0}, Q.MeshRequest, match="positive")
    bad({"v": 1, "resolution": "fine"}, Q.MeshRequest, match="number")


def test_rigid_check():
    assert P.is_rigid(pose())
    assert not P.is_rigid(np.eye(3))
