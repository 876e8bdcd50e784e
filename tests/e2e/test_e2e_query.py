"""End to end, the query service's protocol 1.1: a real ``aisdf-query`` process over real
Zenoh on loopback bakes a published map and answers from it (with radii and observed
flags, read with the stranger's plain msgpack client); under overload it answers ``busy``
at once and never lets a request time out."""

import threading
import time

import numpy as np
import pytest
import torch

import stranger_client as sc
from aisdf import protocol, query_messages
from aisdf.metrics import eval_points
from aisdf.network import NetworkConfig, SDFNetwork, model_spec, state_to_numpy
from aisdf.stack import Stack, wait_for
from aisdf.query.engine import QueryEngine
from helpers.small_map import publish_until_baked, train_small_map

pytestmark = pytest.mark.e2e
NS = "aisdf/e2eq"
torch.set_num_threads(1)


def info(s):
    status, msg = sc.request(s, f"{NS}/info/query", {"v": 1}, 2.0)
    return msg if status == "ok" else {}


@pytest.fixture(scope="module")
def small_map():
    seq, frames, p = train_small_map()
    return seq, frames, p.weight_snapshot(1), p.surfel_map(1)


def unknown_distance_brute_force(grid, pts: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest unobserved space of an ObservedGrid: the cubes
    of its unobserved voxels and everything outside it (0 for a point in unobserved space)."""
    occ = np.asarray(grid.occ)
    lo = np.asarray(grid.origin, np.float64)
    hi = lo + np.array(occ.shape) * grid.voxel
    centres = lo + (np.argwhere(~occ) + 0.5) * grid.voxel
    out = np.zeros(len(pts))
    for n, p in enumerate(np.asarray(pts, np.float64)):
        ijk = np.floor((p - lo) / grid.voxel).astype(int)
        if np.any(ijk < 0) or np.any(ijk >= occ.shape) or not occ[tuple(ijk)]:
            continue  # in unobserved space
        to_cube = np.linalg.norm(np.maximum(np.abs(centres - p) - 0.5 * grid.voxel, 0.0), axis=1).min()
        out[n] = min(to_cube, (p - lo).min(), (hi - p).min())
    return out


def test_query_service_bakes_the_map_and_answers_planner_fields(small_map):
    seq, frames, snap, smap = small_map
    with Stack(services=("query",), namespace=NS) as st:
        s = sc.open_session(st.endpoints)
        try:
            wait_for(lambda: info(s), 60, what="the query service")

            publish_until_baked(s, NS, snap, smap)
            pts = eval_points(frames, n_points=3000, every=1, rng=0)
            radii = np.random.default_rng(1).uniform(0, 0.2, len(pts))
            status, msg = sc.request(s, f"{NS}/query/sdf", {
                "v": 1, "points": sc.arr(pts, "<f8"), "gradient": True, "radii": sc.arr(radii, "<f8"),
                "observed": True, "collision_epsilon": 0.3}, 30.0)
            assert status == "ok", msg
            assert msg["baked"] is True and msg["map_version"] == 1
            # 1.5: the one-network map's measured points reached the service and its answers use them.
            assert snap.measured is not None and info(s)["measured_points"] == len(snap.measured["points"]) > 1000
            # The same map baked in-process answers the same (the wire carries float32).
            e = QueryEngine(device="cpu")
            e.set_weights(protocol.WeightSnapshot.from_msg(protocol.unpack(protocol.pack(snap.to_msg()))))
            if smap is not None:
                e.set_surfels(protocol.SurfelMap.from_msg(protocol.unpack(protocol.pack(smap.to_msg()))))
            e.bake_now()
            want = e.answer_sdf(query_messages.SdfRequest(pts, True, 0.3, radii=radii, observed=True))
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want.sdf, atol=1e-5)
            np.testing.assert_allclose(sc.unarr(msg["gradient"]), want.gradient, atol=1e-4)
            np.testing.assert_array_equal(sc.unarr(msg["observed"]).astype(bool), want.observed)
            assert sc.unarr(msg["observed"]).mean() > 0.99  # evaluation points lie along seen rays
            # Against the truth the bake is about as good as the network of the same map.
            exact = e.answer_sdf(query_messages.SdfRequest(pts, exact=True))
            gt = seq.gt_sdf(pts)
            err_b = np.abs(sc.unarr(msg["sdf"]) + radii - gt).mean()
            err_n = np.abs(exact.sdf - gt).mean()
            assert err_b < err_n + 0.005, (err_b, err_n)
            # 1.6, a hand-built request: each point's distance to unobserved space, as the same map
            # in-process gives it; taking the smaller of it and the answer (unknown space as
            # occupied) is never less safe: fewer answers more than 5 cm above the truth.
            status, m16 = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8"), "unknown": True}, 30.0)
            assert status == "ok", m16
            u = sc.unarr(m16["unknown"])
            np.testing.assert_allclose(u, e.answer_sdf(query_messages.SdfRequest(pts, unknown=True)).unknown, atol=1e-6)
            assert u.shape == (len(pts),) and u.min() >= 0 and u.max() > 0.2
            # ... and as computed here from the observed grid alone, by brute force over every
            # unobserved voxel's cube and the grid's faces (outside it nothing was observed).
            grid = e.state.observed
            some = np.random.default_rng(2).choice(len(pts), 60, replace=False)
            np.testing.assert_allclose(u[some], unknown_distance_brute_force(grid, pts[some]), atol=1e-5)
            safe = np.minimum(sc.unarr(m16["sdf"]), u)
            high, high_safe = np.mean(sc.unarr(m16["sdf"]) - gt > 0.05), np.mean(safe - gt > 0.05)
            print(f"answers > 5 cm too high: {100 * high:.2f} %, with unknown space as occupied {100 * high_safe:.2f} %")
            # Measured (pytest -s tests/e2e/test_e2e_query.py -k planner_fields, 34be166, 2026-12-05):
            # 4.17 % too high, 1.70 % with unknown space as occupied; bounds about 2x off.
            assert high_safe < 0.04 and high_safe < 0.7 * high, (high, high_safe)
            # 1.13: which answers rest on the predicted layout, as the same map in-process says.
            status, m13 = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts, "<f8"), "predicted": True},
                                     30.0)
            assert status == "ok", m13
            flag = sc.unarr(m13["predicted"]).astype(bool)
            np.testing.assert_array_equal(flag, e.answer_sdf(query_messages.SdfRequest(pts, predicted=True)).predicted)
            np.testing.assert_allclose(sc.unarr(m13["sdf"]), sc.unarr(m16["sdf"]), atol=1e-6)
            # Far from anything seen: not observed; an old (1.0) request still gets a 1.0 reply.
            status, msg = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr([[50.0, 50, 50]], "<f4"),
                                                           "observed": True})
            assert status == "ok" and not sc.unarr(msg["observed"]).any()
            status, msg = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts[:5], "<f4")})
            assert status == "ok" and sc.unarr(msg["sdf"]).shape == (5,) and "observed" not in msg
            assert "unknown" not in msg and "predicted" not in msg
            assert st.alive("query")
        finally:
            s.close()


def big_snapshot():
    torch.manual_seed(0)
    net = SDFNetwork(NetworkConfig(width=128))
    spec = model_spec(net)
    spec["bounds"] = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    return protocol.pack(protocol.WeightSnapshot(1, 0, 0.0, spec, state_to_numpy(net)).to_msg())


def test_overload_gets_busy_replies_never_timeouts():
    # One worker, one waiting request, network answers (no bake): 12 planners at once.
    args = ["--set", "workers=1", "--set", "queue_max=1", "--set", "bake=false", "--set", "torch_threads=1"]
    with Stack(services=("query",), namespace=NS, args={"query": args}) as st:
        s = sc.open_session(st.endpoints)
        try:
            key = f"{NS}/query/sdf"
            small = {"v": 1, "points": sc.arr(np.zeros((4, 3)), "<f4")}

            def loaded():
                s.put(f"{NS}/map/weights", big_snapshot(), encoding=sc.ENC)
                return sc.request(s, key, small, 2.0)[0] == "ok"

            wait_for(loaded, 60, period=1.0, what="the map to load")
            pts = np.random.default_rng(0).uniform(-1, 1, (100_000, 3))
            results = []
            lock = threading.Lock()

            def planner():
                for _ in range(3):
                    t = time.monotonic()
                    status, msg = sc.request(s, key, {"v": 1, "points": sc.arr(pts, "<f4"), "gradient": True}, 60.0)
                    with lock:
                        results.append((status, (msg or {}).get("error"), time.monotonic() - t))

            ths = [threading.Thread(target=planner) for _ in range(12)]
            for t in ths:
                t.start()
            for t in ths:
                t.join()
            kinds = [r[0] if r[0] != "err" else r[1] for r in results]
            assert len(results) == 36
            assert "timeout" not in kinds, kinds
            assert kinds.count("ok") >= 2 and kinds.count("busy") >= 10, kinds
            assert set(kinds) <= {"ok", "busy"}, kinds
            # The service still answers normally and counted what it refused.
            assert sc.request(s, key, small, 10.0)[0] == "ok"
            assert info(s)["busy"] == kinds.count("busy")
            assert st.alive("query")
        finally:
            s.close()
