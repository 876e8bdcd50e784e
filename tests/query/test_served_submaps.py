"""The query service answering from submaps, end to end over real Zenoh on loopback (a real
``aisdf-query`` process, read with the stranger's plain msgpack client): a lost submap sample
recovered through ``map/index``, a late joiner, malformed messages; and the real submap mapper,
frontend and query service answering planners as an in-process engine fed the same messages."""

import threading
import time

import numpy as np
import torch

import stranger_client as sc
from aisdf import protocol, query_messages
from aisdf.metrics import eval_points
from aisdf.stack import Stack, wait_for
from aisdf.submaps.grid import cell_id
from aisdf.synthetic import SyntheticSequence
from aisdf.query.engine import QueryEngine
from helpers.submap_map import CELLS, EPOCH, band_points, engine_of, index

torch.set_num_threads(1)
NS = "aisdf/e2esub"


def info(s):
    status, msg = sc.request(s, f"{NS}/info/query", {"v": 1}, 2.0)
    return msg if status == "ok" else {}


def test_e2e_lost_submap_sample_late_joiner_and_malformed_messages(submap_map):
    """A real aisdf-query over real Zenoh. The test process plays the submap mapper: it
    publishes two of the three submaps, loses the third, and its index lists all three;
    the service gets the third through its key. Then malformed messages, then a restarted
    (late-joining) service gets everything with gets."""
    m = submap_map
    snaps = {c: protocol.pack(m["snaps"][c].to_msg()) for c in CELLS}
    lost = (1, -1, 0)
    asked = []
    served = {"on": False}

    def on_get(q):  # the mapper's queryable on map/submaps/**
        asked.append(str(q.key_expr))
        if not served["on"]:
            return
        for c in CELLS:
            k = f"{NS}/map/submaps/{cell_id(c)}"
            if sc.zenoh.KeyExpr(str(q.key_expr)).intersects(sc.zenoh.KeyExpr(k)):
                q.reply(k, snaps[c], encoding=sc.ENC)

    idx_msg = protocol.pack(index(m["grid"], {c: 1 for c in CELLS}, 2).to_msg())
    with Stack(services=("query",), namespace=NS) as st:
        s = sc.open_session(st.endpoints)
        try:
            qa = s.declare_queryable(f"{NS}/map/submaps/**", on_get)
            qi = s.declare_queryable(f"{NS}/map/index", lambda q: q.reply(f"{NS}/map/index", idx_msg, encoding=sc.ENC)
                                     if served["on"] else None)
            wait_for(lambda: info(s), 60, what="the query service")

            def two_loaded():
                for c in CELLS:
                    if c != lost:
                        s.put(f"{NS}/map/submaps/{cell_id(c)}", snaps[c], encoding=sc.ENC)
                return info(s).get("submaps") == 2

            wait_for(two_loaded, 60, period=1.0, what="two submaps")
            assert info(s)["version"] == 1
            # The index lists the third (lost) submap: the service gets it by its key.
            served["on"] = True
            asked.clear()

            def recovered():
                s.put(f"{NS}/map/index", idx_msg, encoding=sc.ENC)
                i = info(s)
                return i.get("submaps") == 3 and i.get("version") == 2 and i.get("baked_version") == 2

            wait_for(recovered, 90, period=1.0, what="the lost submap fetched and the map baked")
            assert f"{NS}/map/submaps/{cell_id(lost)}" in asked, asked
            assert info(s)["fetched"] >= 1
            # Answers: the same as the in-process engine's, from the baked blended field.
            e = engine_of(m)
            e.set_index(index(m["grid"], {c: 1 for c in CELLS}, 2))
            e.bake_now()
            pts = band_points(m, 2000, np.random.default_rng(4))
            req = {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True, "observed": True}
            status, msg = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok", msg
            want = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, observed=True))
            assert msg["baked"] is True and msg["map_version"] == 2 and msg["map_epoch"] == EPOCH
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(msg["gradient"]), want.gradient, atol=1e-4)
            np.testing.assert_array_equal(sc.unarr(msg["observed"]).astype(bool), want.observed)
            # Malformed submap and index messages: logged and skipped, the map unchanged.
            good = m["snaps"][(1, 0, 0)].to_msg()
            for key, payload in [
                ("map/submaps/1_0_0", b"\xc1not msgpack"),
                ("map/submaps/1_0_0", protocol.pack({"v": 1, "version": "x"})),
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "submap": {"id": "1_0", "grid": {}}})),
                ("map/submaps/2_0_0", protocol.pack({**good, "version": 50})),  # id and key disagree
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "state": {}})),
                ("map/submaps/1_0_0", protocol.pack({**good, "version": 50, "submap": None})),
                ("map/index", protocol.pack({"v": 1, "version": 60, "stamp": 0.0, "grid": {"R_WG": [1]},
                                             "submaps": {}})),
                ("map/index", protocol.pack({"v": 1, "version": 60, "stamp": 0.0, "grid": m["grid"].to_msg(),
                                             "submaps": {"a_b": {"version": 1}}})),
                ("map/index", protocol.pack({"v": 9})),
            ]:
                s.put(f"{NS}/{key}", payload, encoding=sc.ENC)
            time.sleep(2.0)
            assert st.alive("query")
            i = info(s)
            assert i["submaps"] == 3 and i["version"] == 2, i
            status, msg2 = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok" and msg2["map_version"] == 2
            np.testing.assert_array_equal(sc.unarr(msg2["sdf"]), sc.unarr(msg["sdf"]))
            # A late joiner: the service restarted gets every submap and the index with gets.
            st.stop_one("query")
            st.start(only=["query"])
            wait_for(lambda: info(s).get("submaps") == 3 and info(s).get("baked_version") == 2, 90, period=1.0,
                     what="the restarted service to get the whole map")
            status, msg3 = sc.request(s, f"{NS}/query/sdf", req, 30.0)
            assert status == "ok" and msg3["map_version"] == 2 and msg3["baked"] is True
            np.testing.assert_allclose(sc.unarr(msg3["sdf"]), want.sdf, atol=1e-5)
            qa.undeclare()
            qi.undeclare()
        finally:
            s.close()


def test_e2e_real_submap_mapper_answers_planners(tmp_path):
    """The real mapper with ``--submaps`` (protocol 1.3) and the real frontend and query
    service: the query service holds every submap the index lists, answers planners from
    the baked blend of them, and its answers equal an in-process engine fed the same
    messages (heard by this test on the same keys) and come near the truth."""
    ns = NS + "/real"
    mapper = ["--preset", "cpu", "--mapper", "submaps", "--set", "training.network.width=32", "--set", "submap.cell_m=3"]
    frontend = ["--set", "n_frames=200", "--set", "width=80", "--set", "height=60", "--set", "linger=true", "--fast"]
    heard: dict = {"submaps": {}, "index": None, "surfels": None}
    lock = threading.Lock()

    def on_surfels(sample):
        smap = protocol.SurfelMap.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            old = heard["surfels"]
            if old is None or (smap.epoch, smap.version) > (old.epoch, old.version):
                heard["surfels"] = smap

    def on_submap(sample):
        snap = protocol.WeightSnapshot.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            old = heard["submaps"].get(snap.submap["id"])
            if old is None or (snap.epoch, snap.version) > (old.epoch, old.version):
                heard["submaps"][snap.submap["id"]] = snap

    def on_index(sample):
        idx = protocol.SubmapIndex.from_msg(protocol.unpack(sample.payload.to_bytes()))
        with lock:
            if heard["index"] is None or (idx.epoch, idx.version) > (heard["index"].epoch, heard["index"].version):
                heard["index"] = idx

    def qinfo(s):
        status, msg = sc.request(s, f"{ns}/info/query", {"v": 1}, 2.0)
        return msg if status == "ok" else {}

    with Stack(services=("query", "mapper", "frontend"), namespace=ns,
               args={"mapper": mapper, "frontend": frontend}) as st:
        s = sc.open_session(st.endpoints)
        try:
            subs = [s.declare_subscriber(f"{ns}/map/submaps/*", on_submap),
                    s.declare_subscriber(f"{ns}/map/index", on_index),
                    s.declare_subscriber(f"{ns}/map/surfels", on_surfels)]

            def fe_done():
                status, msg = sc.request(s, f"{ns}/info/frontend", {"v": 1}, 2.0)
                return status == "ok" and msg.get("done") and msg.get("pending") == 0

            wait_for(fe_done, 240, period=2.0, what="every keyframe acknowledged")
            time.sleep(3.0)
            # This test joined late too: what it missed, it gets (the subscription keeps the newest).
            for r in s.get(f"{ns}/map/submaps/**", timeout=5.0):
                if r.ok is not None:
                    on_submap(r.ok)
            assert st.stop_one("mapper") == 0  # the map stops changing: its last messages stand
            time.sleep(2.0)
            with lock:
                idx, snaps, surfels = heard["index"], dict(heard["submaps"]), heard["surfels"]
            assert idx is not None and len(idx.submaps) >= 2, idx
            assert surfels is not None
            assert set(snaps) == set(idx.submaps)
            wait_for(lambda: (lambda i: i.get("submaps") == len(idx.submaps) and i.get("version") == idx.version
                              and i.get("baked_version") == idx.version)(qinfo(s)), 120, period=1.0,
                     what="the query service to hold and bake the final map")
            assert qinfo(s)["measured_points"] == sum(len(sn.measured["points"]) for sn in snaps.values()) > 0
            e = QueryEngine(device="cpu")
            for snap in snaps.values():
                assert e.set_submap(snap)
            assert e.set_index(idx) == [] and e.state.version == idx.version
            e.set_surfels(surfels)
            seq = SyntheticSequence(building="office", n_frames=200, H=60, W=80, seed=0)
            pts = eval_points([seq.frame(i) for i in range(0, 200, 20)], n_points=3000, every=1, rng=0)
            req = {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True, "source": "implicit"}
            status, msg = sc.request(s, f"{ns}/query/sdf", req, 60.0)
            assert status == "ok", msg
            want = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, source="implicit"))
            assert msg["map_version"] == idx.version and msg["map_epoch"] == idx.epoch
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(msg["gradient"]), want.gradient, atol=1e-4)
            err = np.abs(sc.unarr(msg["sdf"]) - seq.gt_sdf(pts)).mean()
            status, fused = sc.request(s, f"{ns}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8")}, 60.0)
            assert status == "ok" and fused["baked"] is True
            err_f = np.abs(sc.unarr(fused["sdf"]) - seq.gt_sdf(pts)).mean()
            # 1.4: every submap carries its measured points; the service's exact fused answer is
            # the in-process engine's (the measured-surface rule), the 1.3 answer (measured off)
            # another.
            assert all(sn.measured is not None and len(sn.measured["points"]) > 0 for sn in snaps.values())
            status, ex = sc.request(s, f"{ns}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8"), "exact": True,
                                                           "gradient": True}, 60.0)
            assert status == "ok" and ex["baked"] is False
            want = e.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
            np.testing.assert_allclose(sc.unarr(ex["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(ex["gradient"]), want.gradient, atol=1e-4)
            e13 = QueryEngine(device="cpu", measured=False)
            for snap in snaps.values():
                assert e13.set_submap(snap)
            e13.set_surfels(surfels)
            err_x = np.abs(want.sdf - seq.gt_sdf(pts)).mean()
            err_13 = np.abs(e13.answer_sdf(query_messages.SdfRequest(pts, exact=True)).sdf - seq.gt_sdf(pts)).mean()
            print(f"{len(idx.submaps)} submaps, map version {idx.version}: SDF error {100 * err:.1f} cm (blend), "
                  f"{100 * err_f:.1f} cm (fused, baked), {100 * err_x:.1f} cm (fused, exact; 1.3's answer "
                  f"{100 * err_13:.1f} cm)")
            # Against the truth (a walk of seconds trains each submap a few dozen steps). Measured by
            # ``pytest -s tests/query/test_served_submaps.py -k real_submap`` at 34be166 on 2026-12-05,
            # two runs: blend 14.1 / 15.9 cm, fused baked 5.9 / 6.6, fused exact 5.9 / 6.6, 1.3's
            # answer 12.7 / 13.6. The served answer (1.4: measured points) is well below 1.3's and
            # the blend's, and the bake as good as the exact answer.
            assert err_x < 0.15 and err_f < 0.15 and err < 0.4 and err_13 < 0.35, (err, err_f, err_x, err_13)
            assert err_x < 0.7 * err_13 and err_x < 0.7 * err and err_f < err_x + 0.01, (err, err_f, err_x, err_13)
            # A whole-map mesh, tiled.
            status, mesh = sc.request(s, f"{ns}/query/mesh", {"v": 1, "resolution": 0.1}, 120.0)
            assert status == "ok" and sc.unarr(mesh["faces"]).shape[0] > 1000
            for d in subs:
                d.undeclare()
        finally:
            s.close()
