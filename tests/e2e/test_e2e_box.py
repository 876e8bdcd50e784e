"""End to end, protocol 1.9's local distance window: a real ``aisdf-query`` process answers a
``box`` request (a few bytes) with the dense grid of a lattice, exactly as it answers the
same lattice sent as points; the library's ``SdfClient.box`` reshapes it; malformed and
oversized boxes are refused at once and the service goes on."""

import numpy as np
import pytest
import torch

import stranger_client as sc
from aisdf import protocol, query_messages
from aisdf.client import SdfClient
from aisdf.stack import Stack, wait_for
from helpers.small_map import publish_until_baked, train_small_map

pytestmark = pytest.mark.e2e
NS = "aisdf/e2ebox"
torch.set_num_threads(1)


def info(s):
    status, msg = sc.request(s, f"{NS}/info/query", {"v": 1}, 2.0)
    return msg if status == "ok" else {}


def test_box_request_answers_the_lattice_as_points_would():
    _, frames, p = train_small_map()
    snap, smap = p.weight_snapshot(1), p.surfel_map(1)
    T = np.asarray(frames[0]["T_WC"])
    lo = T[:3, 3] + 1.5 * T[:3, 2] - [0.6, 0.5, 0.4]  # a box 1.5 m ahead of the first camera
    size, res = [1.2, 1.0, 0.8], 0.1
    with Stack(services=("query",), namespace=NS, args={"query": ["--max-points", "5000"]}) as st:
        s = sc.open_session(st.endpoints)
        try:
            wait_for(lambda: info(s), 60, what="the query service")

            publish_until_baked(s, NS, snap, smap)
            # A hand-built box request: 13 x 11 x 9 samples, 0.1 m apart, from the corner.
            status, msg = sc.request(s, f"{NS}/query/sdf", {
                "v": 1, "box": {"min": lo.tolist(), "size": size, "resolution": res}, "gradient": True,
                "observed": True}, 30.0)
            assert status == "ok", msg
            assert msg["box"]["shape"] == [13, 11, 9] and msg["box"]["resolution"] == res
            np.testing.assert_allclose(msg["box"]["origin"], lo, atol=0)
            n = 13 * 11 * 9
            box_sdf, box_grad = sc.unarr(msg["sdf"]), sc.unarr(msg["gradient"])
            assert box_sdf.shape == (n,) and box_grad.shape == (n, 3) and msg["baked"] is True
            # The same lattice sent as points, in the documented order (C order, z fastest).
            ii, jj, kk = np.meshgrid(np.arange(13), np.arange(11), np.arange(9), indexing="ij")
            pts = lo + res * np.stack([ii, jj, kk], -1).reshape(-1, 3)
            status, ref = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True,
                                                           "observed": True}, 30.0)
            assert status == "ok", ref
            np.testing.assert_array_equal(box_sdf, sc.unarr(ref["sdf"]))
            np.testing.assert_array_equal(box_grad, sc.unarr(ref["gradient"]))
            np.testing.assert_array_equal(sc.unarr(msg["observed"]), sc.unarr(ref["observed"]))
            # (the points' answers are held to the truth by the other query tests); the box lies
            # where the camera looked
            assert sc.unarr(msg["observed"]).mean() > 0.9
            # The library: one call, the grid in its shape.
            with SdfClient(NS, st.client_zenoh, timeout=30.0) as c:
                r = c.box(lo, size, res, gradient=True)
                assert r.grid("sdf").shape == (13, 11, 9) and r.grid("gradient").shape == (13, 11, 9, 3)
                np.testing.assert_array_equal(r.grid("sdf")[2, 3, 4], box_sdf[(2 * 11 + 3) * 9 + 4])
                # a box that is one sample thick along z: a 2D slice
                r2 = c.box(lo, [1.2, 1.0, 0.0], res)
                assert r2.grid("sdf").shape == (13, 11, 1)
                np.testing.assert_array_equal(r2.grid("sdf")[:, :, 0], r.grid("sdf")[:, :, 0])
                # beyond the service's 5,000 points: too_large, answered at once
                with pytest.raises(protocol.ProtocolError) as e:
                    c.box(lo, [3.0, 3.0, 3.0], res)
                assert e.value.code == "too_large" and "box" in e.value.message
            # Malformed boxes: bad_request, each with a sentence; the service goes on.
            for bad in ({"min": [0, 0], "size": [1, 1, 1], "resolution": 0.1},
                        {"min": [0, 0, 0], "size": [1, -1, 1], "resolution": 0.1},
                        {"min": [0, 0, 0], "size": [1, 1, 1], "resolution": 0},
                        {"min": [0, 0, float("nan")], "size": [1, 1, 1], "resolution": 0.1},
                        {"min": [0, 0, 0], "size": [1, 1, 1]}, "a box"):
                status, err = sc.request(s, f"{NS}/query/sdf", {"v": 1, "box": bad}, 10.0)
                assert status == "err" and err["error"] == "bad_request" and err["message"], (bad, err)
            status, err = sc.request(s, f"{NS}/query/sdf", {"v": 1, "box": {"min": [0, 0, 0], "size": [1, 1, 1],
                                                                            "resolution": 0.5},
                                                           "points": sc.arr(pts[:3], "<f4")}, 10.0)
            assert status == "err" and "not both" in err["message"]
            status, msg = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts[:5], "<f4")})
            assert status == "ok" and "box" not in msg  # a points request's reply is unchanged
            assert st.alive("query")
        finally:
            s.close()


def test_box_messages_round_trip_and_check_their_sizes():
    b = query_messages.Box.around([0.0, 1.0, 2.0], [0.25, 0.0, 0.1], 0.05)
    assert b.shape == (6, 1, 3) and b.count == 18
    req = query_messages.SdfRequest.from_msg(
        protocol.unpack(protocol.pack(query_messages.SdfRequest(np.zeros((0, 3)), box=b).to_msg())))
    assert req.box == b and req.points.shape == (18, 3)
    np.testing.assert_allclose(req.points[-1], [0.25, 1.0, 2.1], atol=1e-12)
    rep = query_messages.SdfReply(3, np.arange(18, dtype=np.float32), box=b)
    back = query_messages.SdfReply.from_msg(protocol.unpack(protocol.pack(rep.to_msg())))
    assert back.box == b and back.grid().shape == (6, 1, 3) and back.grid()[5, 0, 2] == 17
    bad = rep.to_msg()
    bad["box"]["shape"] = [6, 1, 4]
    with pytest.raises(protocol.ProtocolError):
        query_messages.SdfReply.from_msg(bad)
    bad["box"]["shape"] = [float("inf"), 1, 1]
    with pytest.raises(protocol.ProtocolError):
        query_messages.SdfReply.from_msg(bad)
    # sizes that overflow, far corners that are not finite: refused, never a wrapped shape
    with pytest.raises(protocol.ProtocolError) as e:
        query_messages.Box.around([0, 0, 0], [1e10, 0, 0], 1e-10)
    assert e.value.code == "too_large"
    with pytest.raises(protocol.ProtocolError) as e:
        query_messages.Box.around([1e308, 0, 0], [1e308, 0, 0], 1.0)
    assert e.value.code == "bad_request"
    assert query_messages.Box.around([0, 0, 0], [4.0, 0, 0], 0.05).shape == (81, 1, 1)
