"""ROS recordings as a source (aisdf.ros): the frame assembler, the rosbag source over the three
formats (rosbag2 sqlite3, rosbag2 MCAP, ROS 1) against the frames they were written from (the
synthetic building and real 7-Scenes frames), skipped frames, the wrong-TF check, the frontend's
--list and refusal, and the real services end to end. (The message readers and the TF buffer:
tests/ros/test_ros_messages.py.)

The bags are written by ``aisdf.ros.record`` with the same library the reader uses."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aisdf.datasets import open_dataset, require_data
from aisdf.ros import messages
from aisdf.ros import record as rf
from aisdf.ros.assemble import FrameAssembler
from aisdf.ros.bag import RosbagSource
from aisdf.ros.check import check_source
from aisdf.synthetic import SyntheticSequence

SEVEN = "7scenes-redkitchen"


def selected(frames, cfg=None):
    from aisdf.keyframes import KeyframeConfig
    from aisdf.keyframes import KeyframeSelector

    sel = KeyframeSelector(cfg or KeyframeConfig())
    return [i for i, f in enumerate(frames) if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"])]


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
