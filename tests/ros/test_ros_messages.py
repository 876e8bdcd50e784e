"""ROS messages and TF (aisdf.ros): depth images in every encoding, byte order and padding,
compressed depth, camera info, and the TF buffer (chain lookup, interpolation, errors, camera
extrinsics)."""

from __future__ import annotations

import io
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from aisdf.ros import messages
from aisdf.ros import record as rf
from aisdf.ros.tf import ConnectivityError, ExtrapolationError, TFBuffer, parse_extrinsic


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------ messages


def _image(depth_bytes, H, W, enc, step, big=False):
    hdr = SimpleNamespace(stamp=SimpleNamespace(sec=5, nanosec=7), frame_id="cam")
    return SimpleNamespace(header=hdr, height=H, width=W, encoding=enc, is_bigendian=int(big), step=step,
                           data=np.frombuffer(depth_bytes, np.uint8))


def test_depth_images_all_encodings_byte_orders_and_padding():
    rng = np.random.default_rng(0)
    mm = rng.integers(0, 5000, (5, 7)).astype(np.uint16)
    for big in (False, True):
        for pad in (0, 3):
            raw = mm.astype(">u2" if big else "<u2").view(np.uint8).reshape(5, -1)
            raw = np.concatenate([raw, np.full((5, pad), 255, np.uint8)], 1)
            d = messages.depth_from_image(_image(raw.tobytes(), 5, 7, "16UC1", 14 + pad, big))
            np.testing.assert_array_equal(d, mm.astype(np.float32) / 1000.0)
            assert d.dtype == np.float32
    m = rng.uniform(0.5, 4, (4, 6)).astype(np.float32)
    m[0, 0], m[1, 1], m[2, 2] = np.nan, np.inf, -1.0
    for big in (False, True):
        d = messages.depth_from_image(_image(m.astype(">f4" if big else "<f4").tobytes(), 4, 6, "32FC1", 24, big))
        want = m.copy()
        want[0, 0] = want[1, 1] = want[2, 2] = 0.0
        np.testing.assert_array_equal(d, want)
    with pytest.raises(ValueError, match="encoding 'rgb8'"):
        messages.depth_from_image(_image(bytes(5 * 7 * 3), 5, 7, "rgb8", 21))
    with pytest.raises(ValueError, match="needs"):
        messages.depth_from_image(_image(bytes(20), 5, 7, "16UC1", 14))
    with pytest.raises(ValueError, match="step"):
        messages.depth_from_image(_image(bytes(70), 5, 7, "16UC1", 10))


def test_compressed_png_depth_plain_and_compressed_depth():
    from PIL import Image

    mm = np.random.default_rng(1).integers(0, 9000, (6, 9)).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(mm).save(buf, format="PNG")
    png = buf.getvalue()
    for fmt, data in (("png", png), ("16UC1; png", png), ("16UC1; compressedDepth png", struct.pack("<iff", 0, 0, 0)
                                                                                   + png)):
        d = messages.depth_from_compressed(SimpleNamespace(format=fmt, data=np.frombuffer(data, np.uint8)))
        np.testing.assert_array_equal(d, mm.astype(np.float32) / 1000.0)
    # compressedDepth 32FC1: inverse depth quantised as v = A / z + B
    A, B = 1000.0, -1.0
    z = np.array([[1.0, 2.0], [0.0, 4.0]])
    v = np.where(z > 0, np.round(A / np.where(z > 0, z, 1) + B), 0).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(v).save(buf, format="PNG")
    d = messages.depth_from_compressed(SimpleNamespace(format="32FC1; compressedDepth png",
                                                       data=np.frombuffer(struct.pack("<iff", 0, A, B)
                                                                          + buf.getvalue(), np.uint8)))
    np.testing.assert_allclose(d, z, atol=1e-6)
    with pytest.raises(ValueError, match="PNG"):
        messages.depth_from_compressed(SimpleNamespace(format="jpeg", data=np.zeros(10, np.uint8)))
    rgb = io.BytesIO()
    Image.fromarray(np.zeros((3, 3, 3), np.uint8)).save(rgb, format="PNG")
    with pytest.raises(ValueError, match="16-bit"):
        messages.depth_from_compressed(SimpleNamespace(format="png", data=np.frombuffer(rgb.getvalue(), np.uint8)))


def test_camera_info_ros1_and_ros2_field_names():
    K = [500.0, 0, 320, 0, 501.0, 240, 0, 0, 1]
    np.testing.assert_array_equal(messages.K_from_camera_info(SimpleNamespace(k=K)), np.reshape(K, (3, 3)))
    np.testing.assert_array_equal(messages.K_from_camera_info(SimpleNamespace(K=np.array(K))), np.reshape(K, (3, 3)))
    with pytest.raises(ValueError, match="focal"):
        messages.K_from_camera_info(SimpleNamespace(k=[0.0] * 9))
    with pytest.raises(ValueError, match="9 expected"):
        messages.K_from_camera_info(SimpleNamespace(k=[1.0] * 4))
    assert messages.stamp_ns(SimpleNamespace(sec=3, nanosec=25)) == 3_000_000_025


# ------------------------------------------------------------------ TF buffer


def test_tf_chain_lookup_interpolation_and_errors():
    b = TFBuffer(cache_s=None)
    M_mo, B_cl, L_o = _T([0, 0, 0.3], [1, 2, 0]), _T([0, 0.1, 0], [0.1, 0, 0.4]), _T([0.2, 0, 0], [0, 0.01, 0])
    A, B = _T([0.1, -0.2, 0.3], [0, 0, 0]), _T([0.4, 0.1, -0.2], [1.0, -1.0, 0.5])
    b.set_transform("map", "odom", 0, M_mo, static=True)
    b.set_transform("odom", "base", 100, A)
    b.set_transform("odom", "base", 200, B)
    b.set_transform("base", "link", 0, B_cl, static=True)
    b.set_transform("/link", "/optical", 0, L_o, static=True)  # ROS 1 leading slashes
    T = b.lookup("map", "optical", 150)
    s = Slerp([0, 1], Rotation.from_matrix([A[:3, :3], B[:3, :3]]))
    mid = np.eye(4)
    mid[:3, :3], mid[:3, 3] = s([0.5]).as_matrix()[0], (A[:3, 3] + B[:3, 3]) / 2
    np.testing.assert_allclose(T, M_mo @ mid @ B_cl @ L_o, atol=1e-12)
    np.testing.assert_allclose(b.lookup("optical", "map", 150), np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(b.lookup("link", "odom", 200), np.linalg.inv(B @ B_cl), atol=1e-12)  # exact sample
    assert [e[:2] for e in b.chain("map", "optical")] == [("link", "optical"), ("base", "link"), ("odom", "base"),
                                                           ("map", "odom")]
    with pytest.raises(ExtrapolationError, match="before the oldest") as e:
        b.lookup("map", "optical", 99)
    assert not e.value.future
    with pytest.raises(ExtrapolationError, match="after the newest") as e:
        b.lookup("map", "optical", 201)
    assert e.value.future
    with pytest.raises(ConnectivityError, match="'nowhere' is not in the TF tree"):
        b.lookup("map", "nowhere", 150)
    b.set_transform("world", "other", 0, np.eye(4), static=True)
    with pytest.raises(ConnectivityError, match="no TF chain between 'map' and 'other'"):
        b.lookup("map", "other", 150)
    with pytest.raises(ValueError):
        b.set_transform("a", "a", 0, np.eye(4))
    # bounded history: samples older than cache_s before the newest are dropped
    c = TFBuffer(cache_s=1.0)
    for k in range(30):
        c.set_transform("odom", "base", k * 100_000_000, np.eye(4))
    assert c.time_range("odom", "base") == (1_900_000_000, 2_900_000_000)


def test_camera_extrinsic_forms():
    T = parse_extrinsic("1 2 3 0 0 0 1")
    np.testing.assert_allclose(T, _T([0, 0, 0], [1, 2, 3]))
    np.testing.assert_allclose(parse_extrinsic("optical")[:3, :3], rf.R_LINK_OPTICAL)
    np.testing.assert_allclose(parse_extrinsic(" ".join(map(str, rf.T_BASE_LINK.ravel()))), rf.T_BASE_LINK)
    np.testing.assert_allclose(parse_extrinsic("0 0 0 1.5707963267948966 0 0")[:3, :3],
                               Rotation.from_euler("z", 90, degrees=True).as_matrix(), atol=1e-12)
    assert np.array_equal(parse_extrinsic(None), np.eye(4))
    for bad in ("1 2", "a b c d e f g", "0 0 0 0 0 0 0", " ".join(["2"] * 16)):
        with pytest.raises(ValueError):
            parse_extrinsic(bad)

