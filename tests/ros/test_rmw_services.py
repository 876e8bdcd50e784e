"""ROS 2 services over rmw_zenoh (aisdf.ros.rmw_services, aisdf.ros.interfaces).

The service type hashes are held to the values rosidl generates (rmw_zenoh's design.md for
AddTwoInts; rosidl-generated std_srvs and example_interfaces code for the others). Zenoh tests
run a router, a server and a client on their own sessions over loopback: round trips, the key and
the SS/SC tokens as rmw_zenoh writes them, a request built by hand as a C++ rmw_zenoh client
sends it, and requests that must not stop the server."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext as zext
from aisdf.ros import interfaces as ifc
from aisdf.ros import rmw_zenoh as rz

ADD_TWO_INTS = "example_interfaces/srv/AddTwoInts"
KNOWN_HASHES = {  # jazzy
    ADD_TWO_INTS: "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a",  # design.md
    # rosidl-generated std_srvs code (std_srvs__srv__Trigger__TYPE_HASH), also in other ROS 2 clients' tests
    "std_srvs/srv/Trigger": "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
    "std_srvs/srv/SetBool": "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a",
    "std_srvs/srv/Empty": "RIHS01_5888399dedec5ccc85ea6451949fd2c9f97bfdf963f9a588821639fcd31b5d19",
}
# ours: pinned so that a change to the definition (which docs/ros.md documents) is noticed
GET_DISTANCE_WINDOW_HASH = "RIHS01_c394b0655a0a910b828ced401c96814ecac897ad8b14697daa14453ccab2e41d"


def test_service_type_hashes_are_rosidls():
    ts = rz.open_typestore("jazzy")
    for srvtype, want in KNOWN_HASHES.items():
        assert ifc.service_type_hash(ts, srvtype, "jazzy") == want, srvtype
    assert ifc.service_type_hash(ts, ifc.GET_DISTANCE_WINDOW) == GET_DISTANCE_WINDOW_HASH
    # the pieces, from rosidl's generated example_interfaces/srv/detail/add_two_ints__description.c
    assert ts.hash_rihs01(ADD_TWO_INTS + "_Request").startswith("RIHS01_000c5fd92d6b2e1a05949348f584d6d6")
    assert ifc.rihs01(ts.fielddefs, ADD_TWO_INTS + "_Event").startswith("RIHS01_32c1d140259c71e5c355115942bcb31d")
    # a .msg char is a uint8 in rosidl's description (rosbags' own hash takes it for a char)
    assert ifc.rihs01(ts.fielddefs, "service_msgs/msg/ServiceEventInfo").startswith("RIHS01_41bcbbe07a75c9b52bc96bfd")
    assert ifc.rihs01(ts.fielddefs, "std_msgs/msg/String") == ts.hash_rihs01("std_msgs/msg/String")
    # example_interfaces/srv/Trigger: same definition as std_srvs', another name (rosidl-generated code)
    ifc.register_service(ts, "example_interfaces/srv/Trigger", ifc.SERVICES[ifc.TRIGGER])
    assert ifc.service_type_hash(ts, "example_interfaces/srv/Trigger") == \
        "RIHS01_cfeeee47f8105dd7685e4c92d46d4074669cb1c477402be1dea37486542a69e0"
    assert ifc.service_type_hash(rz.open_typestore("humble"), ifc.TRIGGER, "humble") == "TypeHashNotSupported"
    with pytest.raises(ValueError):
        ifc.service_type_hash(ts, "nobody/srv/Unknown")
    with pytest.raises(ValueError):
        ifc.request_type("std_srvs/msg/Trigger")


def test_interfaces_register_idempotently_and_round_trip():
    ts = rz.open_typestore("jazzy")
    ifc.register_interfaces(ts)
    ifc.register_interfaces(ts)
    for t in ("aisdf/srv/GetDistanceWindow_Request", "aisdf/srv/GetDistanceWindow_Response",
              "aisdf/srv/GetDistanceWindow_Event", "std_srvs/srv/Trigger_Request", "std_srvs/srv/Trigger_Response"):
        assert t in ts.types
    with pytest.raises(ValueError, match="another definition"):
        ifc.register_service(ts, ifc.TRIGGER, "int8 x\n---\n")
    resp = distance_window_response(ts)
    R = "aisdf/srv/GetDistanceWindow_Response"
    back = ts.deserialize_cdr(ts.serialize_cdr(resp, R), R)
    assert back.map_version == 7 and back.header.frame_id == "map" and back.esdf_and_gradients.layout.dim[3].size == 4
    assert np.array_equal(back.esdf_and_gradients.data, resp.esdf_and_gradients.data)
    # humble's typestore gets the request and response (no service introspection there)
    h = rz.open_typestore("humble")
    ifc.register_interfaces(h)
    assert "aisdf/srv/GetDistanceWindow_Response" in h.types and "aisdf/srv/GetDistanceWindow_Event" not in h.types


def distance_window_response(ts, box=(2, 3, 4), version=7):
    T = ts.types
    data = np.arange(np.prod(box) * 4, dtype=np.float32)
    dims = [T["std_msgs/msg/MultiArrayDimension"](label=n, size=s, stride=int(np.prod((list(box) + [4])[i:])))
            for i, (n, s) in enumerate(zip("xyzc", list(box) + [4]))]
    dims[3].label = "channel"
    return T["aisdf/srv/GetDistanceWindow_Response"](
        success=True, message="", header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=12, nanosec=5), frame_id="map"),
        origin_m=T["geometry_msgs/msg/Point"](x=1.0, y=-2.0, z=0.5),
        esdf_and_gradients=T["std_msgs/msg/Float32MultiArray"](
            layout=T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0), data=data),
        map_version=version)


# ----------------------------------------------------------------------------- over Zenoh


@pytest.fixture
def two_nodes(ros_router):
    ep, _router = ros_router
    sessions = [rz.open_ros_session([ep]), rz.open_ros_session([ep])]
    nodes = []
    try:
        nodes = [rz.Node(sessions[0], "aisdf_server"), rz.Node(sessions[1], "planner")]
        yield nodes
    finally:
        for n in nodes:
            n.close()
        for s in sessions:
            s.close()


def test_trigger_and_distance_window_round_trips_and_the_graph(two_nodes, ros_router, capsys):
    server, planner = two_nodes
    ts = server.typestore
    calls = []

    def trigger(req):
        calls.append(req)
        return ts.types["std_srvs/srv/Trigger_Response"](success=True, message=f"triggered {len(calls)}")

    def window(req):
        box = tuple(round(s / req.voxel_size_m) for s in (req.aabb_size_m.x, req.aabb_size_m.y, req.aabb_size_m.z))
        resp = distance_window_response(ts, box)
        resp.origin_m = req.aabb_min_m
        resp.message = f"gradient={req.gradient}"
        return resp

    s1 = server.create_service("save_map", ifc.TRIGGER, trigger)
    s2 = server.create_service("/aisdf/get_distance_window", ifc.GET_DISTANCE_WINDOW, window)
    c1 = planner.create_client("/save_map", ifc.TRIGGER)
    c2 = planner.create_client("aisdf/get_distance_window", ifc.GET_DISTANCE_WINDOW)
    assert c1.wait_for_service(5) and c2.wait_for_service(5)
    assert s1.key == f"0/save_map/std_srvs::srv::dds_::Trigger_/{KNOWN_HASHES[ifc.TRIGGER]}" == c1.key
    assert s2.key == f"0/aisdf/get_distance_window/aisdf::srv::dds_::GetDistanceWindow_/{GET_DISTANCE_WINDOW_HASH}"
    assert c1.call(c1.request_class()(), 5).message == "triggered 1"
    assert c1.call(c1.request_class()(), 5).message == "triggered 2"
    T = planner.typestore.types
    req = c2.request_class()(aabb_min_m=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
                             aabb_size_m=T["geometry_msgs/msg/Vector3"](x=0.4, y=0.6, z=0.8),
                             voxel_size_m=0.2, gradient=True)
    resp = c2.call(req, 5)
    assert resp.success and resp.message == "gradient=True" and resp.map_version == 7
    assert (resp.origin_m.x, resp.origin_m.y, resp.origin_m.z) == (1.0, 2.0, 3.0)
    assert [d.size for d in resp.esdf_and_gradients.layout.dim] == [2, 3, 4, 4]
    assert resp.esdf_and_gradients.data.shape == (96,) and resp.esdf_and_gradients.data[-1] == 95
    assert s1.counts.answered == 2 and s2.counts.answered == 1 and s1.counts.malformed == 0
    # the graph: SS and SC tokens with the service types, hashes and rmw's services QoS
    graph = rz.discover(planner.session, 0)
    got = {(e.kind, e.node_name, e.topic, e.msgtype, e.type_hash, e.qos.depth) for e in graph if e.kind != rz.NODE}
    assert (rz.SERVICE, "aisdf_server", "/save_map", ifc.TRIGGER, KNOWN_HASHES[ifc.TRIGGER], 10) in got
    assert (rz.CLIENT, "planner", "/save_map", ifc.TRIGGER, KNOWN_HASHES[ifc.TRIGGER], 10) in got
    assert (rz.SERVICE, "aisdf_server", "/aisdf/get_distance_window", ifc.GET_DISTANCE_WINDOW,
            GET_DISTANCE_WINDOW_HASH, 10) in got
    token = next(e for e in graph if e.kind == rz.SERVICE and e.topic == "/save_map").key()
    assert token == (f"@ros2_lv/0/{server.zid}/0/{s1.entity.entity_id}/SS/%/%/aisdf_server/%save_map/"
                     f"std_srvs::srv::dds_::Trigger_/{KNOWN_HASHES[ifc.TRIGGER]}/::,10:,:,:,,")
    capsys.readouterr()
    assert rz.main(["--connect", ros_router[0], "--timeout", "1"]) == 0
    listing = capsys.readouterr().out
    assert "serves     /save_map  [std_srvs/srv/Trigger]" in listing
    assert "calls      /aisdf/get_distance_window  [aisdf/srv/GetDistanceWindow]" in listing


def cpp_attachment(seq: int, gid: bytes) -> bytes:
    """What rmw_zenoh's AttachmentData::serialize_to_zbytes writes (zenoh-ext's serializer)."""
    return zext.z_serialize((zext.Int64(seq), zext.Int64(time.time_ns()), [zext.UInt8(b) for b in gid])).to_bytes()


def raw_get(session, key, payload, attachment, timeout=3.0):
    return list(session.get(key, target=zenoh.QueryTarget.ALL_COMPLETE, consolidation=zenoh.ConsolidationMode.NONE,
                            payload=payload, attachment=attachment, timeout=timeout))


def test_a_request_built_as_rmw_zenoh_sends_it_and_requests_that_must_not_stop_the_server(two_nodes):
    server, planner = two_nodes
    ts = server.typestore
    fail_next = []

    def add(req):
        if fail_next:
            fail_next.pop()
            raise ZeroDivisionError("the handler broke")
        return ts.types[ADD_TWO_INTS + "_Response"](sum=req.a + req.b)

    srv = server.create_service("/add_two_ints", ADD_TWO_INTS, add)
    key = f"0/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{KNOWN_HASHES[ADD_TWO_INTS]}"
    assert srv.key == key
    client = planner.create_client("add_two_ints", ADD_TWO_INTS)
    assert client.wait_for_service(5)
    s = planner.session
    gid = bytes(range(100, 116))
    cdr = b"\x00\x01\x00\x00" + struct.pack("<qq", 40, 2)  # CDR LE header, int64 a, int64 b
    replies = raw_get(s, key, cdr, cpp_attachment(7, gid))
    assert len(replies) == 1 and replies[0].ok is not None
    sample = replies[0].ok
    assert str(sample.key_expr) == key
    assert sample.payload.to_bytes() == b"\x00\x01\x00\x00" + struct.pack("<q", 42)
    att = rz.Attachment.from_bytes(sample.attachment.to_bytes())
    assert att.sequence_number == 7 and att.gid == gid and abs(att.source_timestamp - time.time_ns()) < 10e9
    # a wrong type hash reaches no server (rmw_zenoh's keys carry the hash)
    assert raw_get(s, key.replace("RIHS01_e1", "RIHS01_00"), cdr, cpp_attachment(8, gid), timeout=1) == []
    # malformed requests are answered with an error and counted; the server goes on
    for payload, attachment in ((b"\x00\x01\x00\x00\x01", cpp_attachment(9, gid)),  # truncated CDR
                                (cdr, None),  # no attachment
                                (cdr, b"\x01\x02\x03")):  # not an attachment
        replies = raw_get(s, key, payload, attachment)
        assert len(replies) == 1 and replies[0].ok is None
        assert "malformed example_interfaces/srv/AddTwoInts_Request" in replies[0].err.payload.to_bytes().decode()
    assert srv.counts.malformed == 3
    Req = client.request_class()
    assert client.call(Req(a=1, b=2), 5).sum == 3  # the next call works
    fail_next.append(True)
    with pytest.raises(RuntimeError, match="ZeroDivisionError: the handler broke"):
        client.call(Req(a=1, b=1), 5)
    assert client.call(Req(a=-5, b=2), 5).sum == -3 and srv.counts.failed == 1
    assert srv.counts.answered == 3 and srv.counts.requests == 7
    # a client's request carries its GID and sequence numbers from 1, as rmw_zenoh's
    seen = []
    spy = s.declare_queryable(key.replace("add_two_ints", "spy"),
                              lambda q: (seen.append(rz.Attachment.from_bytes(q.attachment.to_bytes())), q.drop()),
                              complete=True)
    try:
        spy_client = planner.create_client("/spy", ADD_TWO_INTS)
        with pytest.raises(TimeoutError):
            spy_client.call(Req(a=1, b=1), 1)
        assert [(a.sequence_number, a.gid) for a in seen] == [(1, spy_client.gid)]
    finally:
        spy.undeclare()
    # nobody serves: a clear TimeoutError
    with pytest.raises(TimeoutError, match="no response from service /nobody"):
        planner.create_client("/nobody", ADD_TWO_INTS).call(Req(a=1, b=1), 1)
    srv.close()  # its token goes: the client sees no server (once the router has heard)
    deadline = time.monotonic() + 5
    while client.service_is_ready(0.5) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not client.service_is_ready(0.5)
