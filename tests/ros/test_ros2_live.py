"""The live ROS 2 source over rmw_zenoh.

Unit tests hold aisdf.ros.rmw_zenoh to the examples of rmw_zenoh's docs/design.md (data keys,
liveliness tokens, the attachment) and to zenoh-ext's serializer; Zenoh tests run a ROS-side
router and nodes in-process (late-joining /tf_static, a malformed message, discovery). The
end-to-end test runs the real processes over real Zenoh on loopback: a ROS-side router
(aisdf-router), the rmw_zenoh-style robot (python -m aisdf.ros.replay: the synthetic building
as depth Image + CameraInfo + /tf + /tf_static, one malformed depth message), and
aisdf-frontend --source ros2 with a real aisdf-mapper."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh.ext as zext

from aisdf.ros import rmw_zenoh as rz
from aisdf.stack import endpoint, free_port

STRING = "std_msgs/msg/String"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # design.md
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


# ----------------------------------------------------------------------------- wire formats


def test_data_keys_match_the_design_doc_examples():
    jazzy = rz.open_typestore("jazzy")
    dds = rz.dds_type_name(STRING)
    assert dds == "std_msgs::msg::dds_::String_"
    assert rz.type_hash(jazzy, STRING, "jazzy") == STRING_HASH  # rosbags computes REP-2016's hash
    assert rz.topic_key(0, "/chatter", dds, STRING_HASH) == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert rz.topic_key(0, rz.qualify("chatter", "/robot1"), dds, STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    srv = "example_interfaces::srv::dds_::AddTwoInts_"
    assert rz.topic_key(2, "/add_two_ints", srv, ADD_TWO_INTS_HASH) == f"2/add_two_ints/{srv}/{ADD_TWO_INTS_HASH}"
    assert rz.ros_type_name(srv) == "example_interfaces/srv/AddTwoInts"
    assert rz.parse_topic_key(f"0/robot1/chatter/{dds}/{STRING_HASH}") == (0, "/robot1/chatter", dds, STRING_HASH)
    # Humble's rmw_zenoh has no type hashes
    assert rz.type_hash(rz.open_typestore("humble"), STRING, "humble") == "TypeHashNotSupported"
    for bad in ("Image", "sensor_msgs/Image", "a//b"):
        with pytest.raises(ValueError):
            rz.dds_type_name(bad)
    with pytest.raises(ValueError):
        rz.parse_topic_key("chatter/std_msgs")


DOC_TOKENS = {  # design.md, "Graph Cache", examples using demo_nodes_cpp
    "listener node": "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    "listener subscription": "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
                             f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,",
    "talker publisher": "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,",
    "service server": "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
                      f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,",
    "service client": "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/%add_two_ints/"
                      f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,",
}


def test_liveliness_tokens_match_the_design_doc_examples():
    node = rz.Entity(2, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "0", rz.NODE, "/", "/", "listener")
    assert node.key() == DOC_TOKENS["listener node"]
    sub = rz.Entity(2, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "10", rz.SUBSCRIPTION, "/", "/", "listener",
                    "/chatter", rz.dds_type_name(STRING), STRING_HASH, rz.QoS(depth=10))
    assert sub.key() == DOC_TOKENS["listener subscription"]
    pub = rz.Entity(2, "8b20917502ee955ac4476e0266340d5c", "0", "10", rz.PUBLISHER, "/", "/", "talker",
                    "/chatter", rz.dds_type_name(STRING), STRING_HASH, rz.QoS(depth=7))
    assert pub.key() == DOC_TOKENS["talker publisher"]
    for key in DOC_TOKENS.values():  # parse -> key is the identity
        assert rz.Entity.parse(key).key() == key
    e = rz.Entity.parse(DOC_TOKENS["service server"])
    assert (e.kind, e.domain_id, e.node_name, e.topic, e.msgtype, e.qos.depth) == \
        (rz.SERVICE, 2, "add_two_ints_server", "/add_two_ints", "example_interfaces/srv/AddTwoInts", 10)
    # namespaces and nested topics are mangled
    ns = rz.Entity(0, "ab", "0", "11", rz.PUBLISHER, "/", "/robot1", "cam", "/robot1/camera/depth",
                   "sensor_msgs::msg::dds_::Image_", "TypeHashNotSupported", rz.QoS())
    assert ns.key() == ("@ros2_lv/0/ab/0/11/MP/%/%robot1/cam/%robot1%camera%depth/sensor_msgs::msg::dds_::Image_/"
                        "TypeHashNotSupported/::,:,:,:,,")
    assert rz.Entity.parse(ns.key()) == ns
    for bad in ("@ros2_lv/0/ab/0/0/NN/%/%", "@other/0/ab/0/0/NN/%/%/n", "@ros2_lv/x/ab/0/0/NN/%/%/n",
                "@ros2_lv/0/ab/0/0/XX/%/%/n", "@ros2_lv/0/ab/0/10/MP/%/%/n/%t",
                "@ros2_lv/0/ab/0/10/MP/%/%/n/%t/T_/h/1:2"):
        with pytest.raises(ValueError):
            rz.Entity.parse(bad)


def test_qos_key_form_round_trips_and_names_only_non_defaults():
    assert rz.qos_to_keyexpr(rz.DEFAULT_QOS) == "::,:,:,:,,"
    assert rz.qos_to_keyexpr(rz.TF_STATIC_QOS) == ":1:,1:,:,:,,"  # TRANSIENT_LOCAL, depth 1
    assert rz.qos_to_keyexpr(rz.SENSOR_QOS) == "2::,5:,:,:,,"  # BEST_EFFORT, depth 5
    q = rz.QoS(rz.BEST_EFFORT, rz.TRANSIENT_LOCAL, rz.KEEP_ALL, 3, (1, 500), (2, 0), 3, (4, 5))
    assert rz.keyexpr_to_qos(rz.qos_to_keyexpr(q)) == q
    for bad in ("::,", "a::,:,:,:,,", "::,:,:,:,"):
        with pytest.raises(ValueError):
            rz.keyexpr_to_qos(bad)


def test_attachment_is_zenoh_ext_serialization_of_seq_stamp_gid():
    gid = bytes(range(200, 216))
    a = rz.Attachment(42, 1_733_000_000_123_456_789, gid)
    raw = a.to_bytes()
    ref = zext.z_serialize((zext.Int64(42), zext.Int64(1_733_000_000_123_456_789), [zext.UInt8(b) for b in gid]))
    assert raw == ref.to_bytes()  # what rmw_zenoh's AttachmentData::serialize_to_zbytes writes
    assert len(raw) == 33 and raw[16] == 16
    assert rz.Attachment.from_bytes(raw) == a
    with pytest.raises(ValueError):
        rz.Attachment.from_bytes(raw[:-1])
    with pytest.raises(ValueError):
        rz.Attachment.from_bytes(raw[:16] + b"\x08" + raw[17:])
    assert rz.entity_gid("x") == rz.entity_gid("x") != rz.entity_gid("y") and len(rz.entity_gid("x")) == 16


def test_replay_messages_through_the_assembler_give_back_the_synthetic_frames():
    """The robot's messages (CDR round trip) fed to the FrameAssembler in stamp order give the
    sequence's frames: same depth and K, T_WC through map->odom->base_link->camera_link->optical."""
    from aisdf.ros import replay
    from aisdf.ros.assemble import FrameAssembler
    from aisdf.synthetic import SyntheticSequence

    seq = SyntheticSequence(n_frames=30, H=30, W=40)
    ts = rz.open_typestore("jazzy")
    m = replay.Messages(ts)
    t0 = 1_700_000_000_123_456_789
    TF = "tf2_msgs/msg/TFMessage"

    def cdr(msg, t):
        return ts.deserialize_cdr(ts.serialize_cdr(msg, t), t)

    asm = FrameAssembler(replay.DEPTH_TOPIC, replay.INFO_TOPIC, "map")
    static = m.tf([m.transform(t0, "base_link", "camera_link", replay.T_BASE_CAMERA_LINK),
                   m.transform(t0, "camera_link", replay.OPTICAL_FRAME, replay.T_CAMERA_LINK_OPTICAL)])
    out = asm.feed("/tf_static", TF, t0, cdr(static, TF))
    events = replay.synthetic_events(seq, t0)
    assert sum(k == "image" for _, k, _ in events) == 30 and sum(k == "tf" for _, k, _ in events) > 60
    for stamp, kind, payload in events:
        if kind == "tf":
            out += asm.feed("/tf", TF, stamp, cdr(m.tf([m.transform(stamp, *p) for p in payload]), TF))
        else:
            f = seq.frame(payload)
            out += asm.feed(replay.INFO_TOPIC, "sensor_msgs/msg/CameraInfo", stamp,
                            cdr(m.camera_info(stamp, f["K"], 30, 40), "sensor_msgs/msg/CameraInfo"))
            out += asm.feed(replay.DEPTH_TOPIC, "sensor_msgs/msg/Image", stamp,
                            cdr(m.depth_image(stamp, f["depth"]), "sensor_msgs/msg/Image"))
    out += asm.flush()
    assert [f["frame_id"] for f in out] == list(range(30)) and asm.counts["skipped"] == 0
    for f in out:
        g = seq.frame(f["frame_id"])
        assert np.array_equal(f["depth"], g["depth"]) and np.array_equal(f["K"], g["K"])
        assert np.abs(f["T_WC"] - g["T_WC"]).max() < 1e-12
        assert abs((f["stamp"] - t0 * 1e-9) - g["stamp"]) < 1e-6


# ----------------------------------------------------------------------------- over Zenoh, in-process


def test_nodes_talk_discover_and_fetch_static_transforms_late(ros_router, capsys):
    ep, _router = ros_router
    s_pub, s_sub = rz.open_ros_session([ep]), rz.open_ros_session([ep])
    talker = listener = None
    try:
        talker = rz.Node(s_pub, "talker", distro="jazzy")
        String = talker.typestore.types[STRING]
        static = talker.create_publisher("/tf_static_like", STRING, rz.TF_STATIC_QOS)
        static.publish(String(data="published before anyone listened"))
        time.sleep(0.3)
        listener = rz.Node(s_sub, "listener", distro="humble")  # a Humble node hears Jazzy's keys (any hash)
        got, late = [], []
        sub = listener.create_subscription("chatter", STRING, lambda m, i: got.append((m.data, i)), rz.QoS(depth=10))
        listener.create_subscription("/tf_static_like", STRING, lambda m, i: late.append(m.data),
                                     rz.TF_STATIC_LISTENER_QOS)
        pub = talker.create_publisher("chatter", STRING, rz.QoS(depth=7))
        time.sleep(0.5)
        for k in range(3):
            pub.publish(String(data=f"hello {k}"))
        s_pub.put(pub.key, b"\x00\x01\x00\x00 not CDR of a String", attachment=rz.Attachment(9, 0, pub.gid).to_bytes())
        pub.publish(String(data="after the bad one"))
        deadline = time.monotonic() + 5
        while (len(got) < 4 or not late) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert late == ["published before anyone listened"]  # transient local: from the publisher's cache
        assert [m for m, _ in got] == ["hello 0", "hello 1", "hello 2", "after the bad one"]
        info = got[0][1]
        assert info.key == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
        assert info.attachment.sequence_number == 1 and info.attachment.gid == pub.gid
        assert abs(info.attachment.source_timestamp - time.time_ns()) < 10e9
        assert sub.counts.malformed == 1 and sub.counts.delivered == 4
        # and the other way: a Humble publisher (TypeHashNotSupported key) to a Jazzy subscription
        from_humble = []
        talker.create_subscription("/from_humble", STRING, lambda m, i: from_humble.append((m.data, i.key)))
        time.sleep(0.3)
        listener.create_publisher("/from_humble", STRING).publish(String(data="humble says hi"))
        deadline = time.monotonic() + 5
        while not from_humble and time.monotonic() < deadline:
            time.sleep(0.05)
        assert from_humble == [("humble says hi", "0/from_humble/std_msgs::msg::dds_::String_/TypeHashNotSupported")]
        graph = rz.discover(s_sub, 0)
        kinds = {(e.kind, e.node_name, e.topic, e.type_hash) for e in graph}
        assert (rz.NODE, "listener", None, None) in kinds and (rz.NODE, "talker", None, None) in kinds
        assert (rz.SUBSCRIPTION, "listener", "/chatter", "TypeHashNotSupported") in kinds  # it announces itself
        assert (rz.PUBLISHER, "talker", "/chatter", STRING_HASH) in kinds
        static_pub = next(e for e in graph if e.kind == rz.PUBLISHER and e.topic == "/tf_static_like")
        assert static_pub.qos == rz.TF_STATIC_QOS
        assert rz.discover(s_sub, 1) == []  # another domain sees nothing
        capsys.readouterr()
        assert rz.main(["--connect", ep, "--timeout", "1"]) == 0  # python -m aisdf.ros.rmw_zenoh
        listing = capsys.readouterr().out
        assert "/talker\n" in listing and "publishes  /chatter  [std_msgs/msg/String]  qos ::,7:,:,:,," in listing
        assert "subscribes /tf_static_like  [std_msgs/msg/String]  qos :1:,100:,:,:,," in listing
    finally:
        for n in (listener, talker):
            if n:
                n.close()
        s_pub.close()
        s_sub.close()


# ----------------------------------------------------------------------------- end to end


@pytest.mark.e2e
def test_live_ros2_robot_maps_like_the_protocol_v1_frontend(tmp_path):
    """The ROS 2 path delivers to the mapper the very keyframes the protocol-v1 frontend
    selects on the same synthetic frames (same ids; depth and K equal; poses through the TF
    chain within 1e-9), every one acknowledged; a malformed depth message is dropped and
    counted; and the same short training on each path's keyframes gives errors within 1.1x."""
    from aisdf.bench import ros2_live as cmp

    n, W, H = 90, 80, 60
    r = cmp.run_path("ros2", n, W, H, log_dir=tmp_path, garbage_after=10,
                     mapper_args=["--preset", "cpu", "--set", "training.network.width=32"])
    fi, mi = r["frontend"], r["mapper"]
    src = fi["source"]
    print("ROS 2 source:", json.dumps(src))
    assert src["images"] == n and src["frames"] == n and src["skipped"] == 0
    assert src["topics"]["depth"]["malformed"] == 1 and src["topics"]["tf_static"]["received"] >= 1
    ref = cmp.reference_keyframes(n, W, H)
    c = cmp.compare_keyframes(ref, r["keyframes"])
    print("keyframes: protocol v1", c["ids_a"], "ROS 2", c["ids_b"],
          {k: c.get(k) for k in ("depth", "K", "T_WC", "stamp")})
    assert c["same_ids"] and len(ref) >= 3
    assert c["depth"] == 0.0 and c["K"] == 0.0 and c["T_WC"] < 1e-9 and c["stamp"] < 1e-5
    assert fi["keyframes"] == fi["acked"] == mi["keyframes"] == len(ref)
    pts, gt = cmp.eval_setup(n, W, H, n_points=20_000)
    e_ref, steps = cmp.trained_error(ref, pts, gt, steps_first=30, steps_per=10, width=32)
    e_ros, _ = cmp.trained_error(r["keyframes"], pts, gt, steps_first=30, steps_per=10, width=32)
    print(f"same training ({steps} steps): protocol v1 {100 * e_ref:.2f} cm, ROS 2 {100 * e_ros:.2f} cm")
    assert e_ros <= 1.1 * e_ref and e_ref < 0.5


def test_replay_republishes_a_rosbag2_recording(ros_router, tmp_path):
    import threading

    from rosbags.rosbag2 import StoragePlugin, Writer

    from aisdf.ros.replay import replay_bag

    ep, _router = ros_router
    ts = rz.open_typestore("jazzy")
    String = ts.types[STRING]
    bag = tmp_path / "chatter"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/chatter", STRING, typestore=ts)
        for k in range(3):
            w.write(c, 1_000_000_000 + k * 10_000_000, ts.serialize_cdr(String(data=f"recorded {k}"), STRING))
    s_play, s_sub = rz.open_ros_session([ep]), rz.open_ros_session([ep])
    node = None
    try:
        node = rz.Node(s_sub, "listener")
        got = []
        node.create_subscription("/chatter", STRING, lambda m, i: got.append(m.data))
        time.sleep(0.5)
        out = replay_bag(s_play, bag, threading.Event(), rate=1.0)
        deadline = time.monotonic() + 5
        while len(got) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert out == {"messages": 3, "topics": ["/chatter"]}
        assert got == ["recorded 0", "recorded 1", "recorded 2"]
        with pytest.raises(ValueError, match="ROS 1 bag"):
            replay_bag(s_play, tmp_path / "old.bag", threading.Event())
    finally:
        if node:
            node.close()
        s_play.close()
        s_sub.close()


@pytest.mark.e2e
def test_live_source_waits_for_its_robot_and_ends_on_sigterm(tmp_path):
    """No robot yet (nothing on the ROS side): the frontend runs, answers info/frontend with a
    live source (no total), and SIGTERM ends it cleanly and promptly."""
    from aisdf import keys, transport
    from aisdf.stack import Stack, wait_for

    ns = "aisdf/ros2term"
    st = Stack(services=("frontend",), namespace=ns, log_dir=tmp_path,
               args={"frontend": ["--source", "ros2", "--ros-connect", endpoint(free_port()),
                                  "--set", "reliable=false"]})
    try:
        st.start()
        with transport.open_session(st.client_zenoh) as s:
            try:
                fi = wait_for(lambda: (lambda i: i if i and "source" in i else None)(
                    transport.get_latest(s, keys.key(ns, "info/frontend"), 1.0)), 60, what="the live source to start")
            except TimeoutError as e:  # timed out once under the full suite (2026-12-02): say what the frontend did
                log = (tmp_path / "frontend.log").read_text()[-3000:]
                raise AssertionError(f"{e}; frontend alive: {st.alive('frontend')}, ports {st.ports}; its log:\n{log}")
            assert fi["total"] is None and fi["frames"] == 0 and fi["source"]["images"] == 0
        t = time.monotonic()
        assert st.stop_one("frontend", timeout=20) == 0
        assert time.monotonic() - t < 10
    finally:
        st.stop()


@pytest.mark.e2e
def test_a_robot_whose_tf_lacks_the_optical_rotation_is_refused_in_words(tmp_path):
    """The replay robot (map z up, as REP 105 asks) with /tf_static missing camera_link ->
    optical: the frontend checks its first 90 frames, maps nothing and exits saying why."""
    from aisdf.bench import ros2_live as cmp
    from aisdf.stack import Stack

    port = free_port()
    st = Stack(services=("frontend",), namespace="aisdf/ros2badtf", log_dir=tmp_path,
               args={"frontend": ["--source", "ros2", "--ros-connect", endpoint(port), "--ros-idle-timeout", "3",
                                  "--set", "reliable=false"]})
    router, rlog = cmp.popen(cmp.router_command(port), tmp_path / "router.log")
    replay = None
    try:
        st.start()
        replay, plog = cmp.popen(cmp.replay_command(port, 120, 80, 60, extra=[
            "--wait-subscriber", "30", "--no-optical-rotation", "--world-frame", "identity"]),
                                 tmp_path / "replay.log")
        rc = st.procs["frontend"].wait(90)
        log = (tmp_path / "frontend.log").read_text()
        print(log[-1500:])
        assert rc != 0
        assert "refusing to map the live robot's frames" in log and "TF check FAILED" in log
        assert "camera_link -> optical rotation" in log and "done:" not in log  # nothing was mapped
    finally:
        st.stop()
        if replay is not None:
            cmp.stop_proc(replay, plog)
        cmp.stop_proc(router, rlog)
