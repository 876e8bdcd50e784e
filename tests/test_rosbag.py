"""ROS recordings as a source (aisdf.ros): message readers, the TF buffer, the frame assembler,
the rosbag source over the three formats (rosbag2 sqlite3, rosbag2 MCAP, ROS 1) against the
frames they were written from (the synthetic building and real 7-Scenes frames), skipped
frames, the wrong-TF check, the frontend's --list and refusal, and the real services end to end.

The bags are written by ``aisdf.ros.record`` with the same library the reader uses."""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from aisdf.datasets import open_dataset, require_data
from aisdf.ros import messages
from aisdf.ros import record as rf
from aisdf.ros.assemble import FrameAssembler
from aisdf.ros.bag import RosbagSource
from aisdf.ros.check import check_source
from aisdf.ros.tf import ConnectivityError, ExtrapolationError, TFBuffer, parse_extrinsic
from aisdf.synthetic import SyntheticSequence

SEVEN = "7scenes-redkitchen"


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def selected(frames, cfg=None):
    from aisdf.keyframes import KeyframeConfig
    from aisdf.keyframes import KeyframeSelector

    sel = KeyframeSelector(cfg or KeyframeConfig())
    return [i for i, f in enumerate(frames) if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"])]


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


# ------------------------------------------------------------------ the synthetic building in bags


@pytest.fixture(scope="module")
def office():
    return SyntheticSequence("office", n_frames=45, H=48, W=64, noise=True, seed=1)


def _write(tmp, seq, fmt, name, **kw):
    kw.setdefault("T_map_world", seq.scene.T_canon_W if hasattr(seq, "scene") else None)
    return rf.write_bag(rf.path_for(tmp, fmt, name), seq, fmt, **kw)


@pytest.mark.parametrize("fmt", rf.FORMATS)
def test_synthetic_bag_frames_equal_the_source(tmp_path, office, fmt):
    src_frames = [office.frame(i) for i in range(len(office))]
    for enc in ("32FC1", "16UC1", "png"):
        # TF at 50 Hz, not aligned with the 30 Hz images: poses within the interpolation bound.
        wb = _write(tmp_path, office, fmt, f"s_{enc}", encoding=enc, big_endian=(enc == "32FC1"),
                    row_pad=(4 if enc == "16UC1" else 0))
        et, er = rf.interpolation_bound(wb)
        assert et.max() > 1e-4  # the bound is not vacuous: these samples do not fall on the images
        with RosbagSource(wb.path) as src:
            assert len(src) == len(office) and src.counts["skipped"] == 0
            assert src.fixed_frame == "map" and src.camera_frame == rf.OPTICAL_FRAME
            frames = [src.frame(i) for i in range(len(src))]
        for k, (f, g) in enumerate(zip(frames, src_frames)):
            assert f["frame_id"] == k and f["stamp"] == pytest.approx(wb.stamps[k], abs=1e-9)
            np.testing.assert_allclose(f["K"], g["K"])
            if enc == "32FC1":
                np.testing.assert_array_equal(f["depth"], g["depth"])
            else:  # millimetres
                np.testing.assert_array_equal(f["depth"], np.round(g["depth"] * 1000).astype(np.float32) / 1000)
            dt = np.linalg.norm(f["T_WC"][:3, 3] - wb.T_WC[k][:3, 3])
            dr = Rotation.from_matrix(f["T_WC"][:3, :3].T @ wb.T_WC[k][:3, :3]).magnitude()
            assert dt <= 1.5 * et[k] + 1e-6 and dr <= 1.5 * er[k] + 1e-6, (k, dt, et[k], dr, er[k])
    # TF samples that also fall on the image stamps: the poses exactly (to 1e-6).
    wb = _write(tmp_path, office, fmt, "s_exact", encoding="32FC1", tf_at_images=True)
    with RosbagSource(wb.path) as src:
        frames = [src.frame(i) for i in range(len(src))]
    for k, f in enumerate(frames):
        np.testing.assert_allclose(f["T_WC"], wb.T_WC[k], atol=1e-6)
    if fmt != "ros1":  # the storage file alone (a .db3 or .mcap without its folder's metadata.yaml)
        single = tmp_path / f"alone.{'db3' if fmt == 'sqlite3' else fmt}"
        next(wb.path.glob(f"*{single.suffix}")).rename(single)
        with RosbagSource(single) as alone:
            np.testing.assert_array_equal(alone.frame(len(alone) - 1)["depth"], frames[-1]["depth"])
            assert len(alone) == len(office) and alone.storage.startswith("rosbag2")
    # the same keyframes as the source in the map frame
    in_map = [dict(g, T_WC=wb.T_WC[k]) for k, g in enumerate(src_frames)]
    assert selected(frames) == selected(in_map) and len(selected(frames)) > 3


def test_streaming_assembler_holds_images_until_tf_and_matches_the_pre_scan(tmp_path, office):
    """Fed in arrival order (as a live source is), each frame comes out only once TF after its
    stamp has arrived, and the frames equal the pre-scanned source's."""
    from rosbags.highlevel import AnyReader

    wb = _write(tmp_path, office, "mcap", "stream", encoding="16UC1")
    asm = FrameAssembler(rf.DEPTH_TOPIC, rf.INFO_TOPIC, "map", cache_s=5.0)
    out, newest_tf = [], 0
    with AnyReader([wb.path]) as r:
        for c, t, raw in r.messages():
            msg = r.deserialize(raw, c.msgtype)
            if c.topic == "/tf":
                newest_tf = max([newest_tf] + [messages.stamp_ns(x.header.stamp) for x in msg.transforms
                                               if x.child_frame_id == "base_link"])
            for f in asm.feed(c.topic, c.msgtype, t, msg):
                assert newest_tf >= int(round(f["stamp"] * 1e9))  # never placed ahead of the TF
                out.append(f)
    out += asm.flush()
    assert asm.counts["frames"] == len(office) and asm.counts["skipped"] == 0
    with RosbagSource(wb.path) as src:
        for f in out:
            g = src.frame(f["frame_id"])
            np.testing.assert_array_equal(f["depth"], g["depth"])
            np.testing.assert_allclose(f["T_WC"], g["T_WC"], atol=1e-12)


def test_frames_the_tf_cannot_place_are_skipped_and_counted(tmp_path, office):
    n = len(office)
    wb = _write(tmp_path, office, "sqlite3", "gaps", tf_first_frame=3, tf_last_frame=n - 5)
    with RosbagSource(wb.path) as src:
        assert len(src) == n - 3 - 4
        c = src.counts
        assert c["images"] == n and c["skipped"] == 7 and c["skipped_reasons"] == {"stamp_outside_tf": 7}
        assert [src.frame(i)["frame_id"] for i in (0, len(src) - 1)] == [3, n - 5]  # ids stay the image indices
        assert "7 skipped: stamp outside the TF buffer" in src.summary()
    # No /tf_static: the depth frame hangs in no chain. Named fixed frame: all skipped, counted.
    wb = _write(tmp_path, office, "ros1", "nostatic", no_static=True)
    with pytest.raises(ValueError, match="is in no TF chain.*--fixed-frame"):
        RosbagSource(wb.path)
    with RosbagSource(wb.path, fixed_frame="map") as src:
        assert len(src) == 0 and src.counts["skipped_reasons"] == {"missing_transform": n}
    # Streaming: an image that waits for a transform which never comes is dropped after max_wait_s.
    from rosbags.highlevel import AnyReader

    asm = FrameAssembler(rf.DEPTH_TOPIC, rf.INFO_TOPIC, "map", max_wait_s=0.5)
    with AnyReader([wb.path]) as r:
        for c, t, raw in r.messages():
            assert asm.feed(c.topic, c.msgtype, t, r.deserialize(raw, c.msgtype)) == []
        assert asm.counts["skipped"] > n // 2 and asm.counts["pending"] < n // 2  # dropped as they aged
    assert asm.flush() == [] and asm.counts["skipped"] == n


def test_pose_topic_with_camera_extrinsic(tmp_path, office):
    wb = _write(tmp_path, office, "mcap", "odom", odom_topic=True, tf_at_images=True)
    ext = " ".join(repr(float(v)) for v in (rf.T_BASE_LINK @ rf.T_LINK_OPTICAL).ravel())
    with RosbagSource(wb.path, pose_topic="/odom", camera_extrinsic=ext) as src:
        assert src.fixed_frame == "odom" and len(src) == len(office)
        for k in (0, 10, len(src) - 1):
            np.testing.assert_allclose(src.frame(k)["T_WC"], np.linalg.inv(rf.T_MAP_ODOM) @ wb.T_WC[k], atol=1e-6)
        assert "/odom" in src.describe()
    with pytest.raises(ValueError, match="not a pose topic"):
        RosbagSource(wb.path, pose_topic="/tf")
    with pytest.raises(ValueError, match="depth topic '/nope'"):
        RosbagSource(wb.path, depth_topic="/nope")


def test_discovery_asks_when_there_is_no_obvious_choice(tmp_path, office):
    wb = _write(tmp_path, office, "sqlite3", "two", second_camera=True, max_frames=10)
    with pytest.raises(ValueError, match=r"several depth image topics \(/camera/aligned_depth_to_color/image_raw, "
                       r"/camera/depth/image_rect_raw\); name one with --depth-topic"):
        RosbagSource(wb.path)
    for depth, info in ((rf.DEPTH_TOPIC, rf.INFO_TOPIC), ("/camera/aligned_depth_to_color/image_raw",
                                                          "/camera/aligned_depth_to_color/camera_info")):
        with RosbagSource(wb.path, depth_topic=depth) as src:  # the camera info beside it is found
            assert src.info_topic == info and len(src) == 10
    with pytest.raises(ValueError, match="camera info topic '/tf'"):
        RosbagSource(wb.path, depth_topic=rf.DEPTH_TOPIC, info_topic="/tf")


def test_wrong_chain_is_detected_in_words(tmp_path, office):
    wb = _write(tmp_path, office, "mcap", "wrong", optical_rotation=False)
    with RosbagSource(wb.path) as src:
        v = check_source(src)
    assert not v.ok
    assert "missing the camera_link -> optical rotation" in v.message and "consecutive depth images disagree" in \
        v.message
    assert v.figures["image_down_vs_gravity_deg"] > 80
    wb = _write(tmp_path, office, "mcap", "right")
    with RosbagSource(wb.path) as src:
        v = check_source(src)
    assert v.ok, v.message
    assert v.figures["image_down_vs_gravity_deg"] < 45 and v.figures["consistent_pairs"] == v.figures["moving_pairs"]


def _frontend(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "aisdf_frontend.main", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def test_frontend_list_and_refusal(tmp_path, office):
    good = _write(tmp_path, office, "ros1", "good", encoding="png")
    r = _frontend("--source", "rosbag", "--path", good.path, "--list")
    assert r.returncode == 0, r.stderr
    for words in ("ROS 1 bag", "/camera/depth/image_rect_raw/compressedDepth", "<- depth", "/camera/depth/camera_info",
                  "/tf_static", "fixed frame 'map'", "camera_link -> camera_depth_optical_frame (static)",
                  "odom -> base_link: dynamic", "45 depth images, 45 placed, 0 skipped", "TF check passed"):
        assert words in r.stdout, (words, r.stdout)
    bad = _write(tmp_path, office, "sqlite3", "bad", optical_rotation=False)
    r = _frontend("--source", "rosbag", "--path", bad.path, "--list")
    assert r.returncode == 0 and "TF check FAILED" in r.stdout and "optical rotation" in r.stdout
    from aisdf.stack import endpoint, free_port

    r = _frontend("--source", "rosbag", "--path", bad.path, "--fast", "--no-multicast-scouting", "--listen",
                  endpoint(free_port()), "--set", "reliable=false")
    assert r.returncode != 0
    assert "refusing to map" in r.stderr and "optical rotation" in r.stderr and "--no-tf-check" in r.stderr
    r = _frontend("--source", "rosbag", "--path", tmp_path / "absent.mcap", "--list")
    assert r.returncode != 0 and "no recording at" in r.stderr


def test_no_tf_check_streams_the_wrong_chain_and_counts_skips(tmp_path, office):
    from aisdf_frontend.config import FrontendConfig
    from aisdf_frontend.main import stream

    bad = _write(tmp_path, office, "mcap", "bad2", optical_rotation=False, tf_last_frame=len(office) - 3)
    sent = []
    cfg = FrontendConfig(source="rosbag", path=bad.path, realtime=False, rosbag={"tf_check": False})
    counts = stream(cfg, sent.append, threading.Event())
    assert counts["frames"] == len(office) - 2 and counts["keyframes"] == len(sent) > 0
    assert counts["source"]["skipped_reasons"] == {"stamp_outside_tf": 2}
    with pytest.raises(ValueError, match="refusing to map"):
        stream(FrontendConfig(source="rosbag", path=bad.path, realtime=False), sent.append, threading.Event())


# ------------------------------------------------------------------ real 7-Scenes frames


@pytest.fixture(scope="module")
def seven():
    root = require_data(SEVEN) / "data"
    ds = open_dataset("7scenes", root)
    return ds, rf.sevenscenes_alignment(root)


@pytest.mark.parametrize("fmt", rf.FORMATS)
def test_sevenscenes_bags_equal_the_folder_frames(tmp_path, seven, fmt):
    ds, T_mw = seven
    n = 36
    folder = [ds.frame(i) for i in range(n)]
    enc = {"sqlite3": "16UC1", "mcap": "png", "ros1": "compressedDepth"}[fmt]
    wb = rf.write_bag(rf.path_for(tmp_path, fmt, "kitchen"), ds, fmt, encoding=enc, T_map_world=T_mw, max_frames=n)
    et, er = rf.interpolation_bound(wb)
    with RosbagSource(wb.path) as src:
        assert len(src) == n and src.counts["skipped"] == 0
        frames = [src.frame(i) for i in range(n)]
        assert check_source(src).ok
    T_wm = np.linalg.inv(T_mw)
    for k, (f, g) in enumerate(zip(frames, folder)):
        np.testing.assert_array_equal(f["depth"], g["depth"])  # millimetres: exact
        np.testing.assert_array_equal(f["K"], g["K"])
        assert f["stamp"] - frames[0]["stamp"] == pytest.approx(g["stamp"] - folder[0]["stamp"], abs=1e-6)
        dt = np.linalg.norm(f["T_WC"][:3, 3] - wb.T_WC[k][:3, 3])
        dr = Rotation.from_matrix(f["T_WC"][:3, :3].T @ wb.T_WC[k][:3, :3]).magnitude()
        assert dt <= 1.5 * et[k] + 1e-6 and dr <= 1.5 * er[k] + 1e-6, (k, dt, et[k], dr, er[k])
        np.testing.assert_allclose(wb.T_WC[k], T_mw @ g["T_WC"], atol=1e-12)
    # the same keyframes as the folder (poses compared in the folder's world frame)
    back = [dict(f, T_WC=T_wm @ f["T_WC"]) for f in frames]
    assert selected(back) == selected(folder) and len(selected(folder)) > 3


# ------------------------------------------------------------------ end to end


@pytest.mark.e2e
def test_e2e_frontend_rosbag_to_the_real_mapper(tmp_path, office):
    from aisdf import keys, transport
    from aisdf.stack import Stack, wait_for

    ns = "aisdf/e2ebag"
    wb = _write(tmp_path, office, "mcap", "e2e", encoding="16UC1", tf_at_images=True)
    with RosbagSource(wb.path) as src:
        want = selected([src.frame(i) for i in range(len(src))])
    st = Stack(services=("mapper", "frontend"), namespace=ns, log_dir=tmp_path / "logs", args={
        "mapper": ["--preset", "cpu", "--set", "training.network.width=32"],
        "frontend": ["--source", "rosbag", "--path", str(wb.path), "--fast", "--set", "linger=true"]})
    with st, transport.open_session(st.client_zenoh) as s:
        def done():
            fi = transport.get_latest(s, keys.key(ns, "info/frontend"), 2.0)
            mi = transport.get_latest(s, keys.key(ns, "info/mapper"), 2.0)
            return (fi, mi) if fi and mi and fi["done"] and fi["pending"] == 0 and mi["keyframes"] >= fi["keyframes"] \
                else None

        fi, mi = wait_for(done, 120, what="the recording mapped")
        print(json.dumps({"frontend": fi, "mapper_keyframes": mi["keyframes"]}, default=str))
        assert fi["frames"] == len(office) and fi["keyframes"] == len(want) and mi["keyframes"] == len(want)
        assert fi["source"]["skipped"] == 0 and fi["source"]["images"] == len(office)
        assert st.alive("frontend") and st.alive("mapper")
