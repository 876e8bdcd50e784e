"""End to end, query replicas (protocol 1.12): real ``aisdf-query`` processes sharing one
namespace over real Zenoh on loopback, a small map put on it as a mapper publishes it, and
planners (threads, each its own ``SdfClient``) sending 10,000-point requests.

* Two replicas under 8 planners: their ``evaluated`` counters add up to the requests sent
  (each evaluated once, not twice) and each evaluated at least a quarter of them.
* An old-style planner (a plain ``get`` on the shared ``query/sdf``, Zenoh's default target)
  gets exactly one answer, evaluated by one replica.
* A third replica that has no map (it joined after the map was put, with no mapper to get it
  from) never fails a request: the clients ask another.
* One of the mapped replicas killed with SIGKILL while the planners keep asking: for the next
  15 s nothing is lost and nothing fails (the clients fail over).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch
import zenoh

import stranger_client as sc
from aisdf import protocol
from aisdf.client import SdfClient
from aisdf.metrics import eval_points
from aisdf.replicas import replica_infos
from aisdf.stack import Stack, wait_for
from helpers.small_map import train_small_map

pytestmark = pytest.mark.e2e
NS = "aisdf/e2erep"
PLANNERS = 8
POINTS = 10_000
torch.set_num_threads(1)


def infos(s) -> dict[str, dict]:
    """Every replica's ``info/query``, by replica id (one reply each: consolidation off)."""
    return replica_infos(s, NS)


def evaluated(s) -> dict[str, int]:
    return {rid: m["evaluated"] for rid, m in infos(s).items()}


def run_planners(clients, pts, until=None, per_planner=None):
    """Each client in its own thread sends POINTS-point requests with gradients: ``per_planner``
    of them, or until ``until`` (monotonic). Returns [(start, end, outcome)], outcome "ok" or
    what was raised."""
    out, lock = [], threading.Lock()

    def planner(i, c):
        rng = np.random.default_rng(i)
        n = 0
        while (per_planner is None or n < per_planner) and (until is None or time.monotonic() < until):
            q = pts[rng.integers(0, len(pts), POINTS)]
            t = time.monotonic()
            try:
                r = c.query(q, gradient=True)
                kind = "ok" if r.sdf.shape == (POINTS,) and np.isfinite(r.sdf).all() else "bad reply"
            except Exception as e:  # noqa: BLE001 - every failure counts
                kind = f"{type(e).__name__}: {e}"
            with lock:
                out.append((t, time.monotonic(), kind))
            n += 1

    ths = [threading.Thread(target=planner, args=(i, c)) for i, c in enumerate(clients)]
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    return out


def test_replicas_share_planners_and_fail_over():
    seq, frames, p = train_small_map()
    snap, smap = p.weight_snapshot(1), p.surfel_map(1)
    pts = eval_points(frames, n_points=50_000, every=1, rng=0).astype(np.float32)
    st = Stack(services=("query", "query2", "query3"), namespace=NS,
               args={n: ["--replica-id", rid] for n, rid in (("query", "a"), ("query2", "b"), ("query3", "c"))})
    st.start(only=["query", "query2"])
    s = sc.open_session(st.endpoints)
    clients = []
    try:
        wait_for(lambda: len(infos(s)) == 2, 60, what="two query replicas")

        def baked():  # the map as a mapper puts it, again until both replicas baked it
            s.put(f"{NS}/map/surfels", protocol.pack(smap.to_msg()), encoding=sc.ENC)
            time.sleep(0.2)
            s.put(f"{NS}/map/weights", protocol.pack(snap.to_msg()), encoding=sc.ENC)
            return all(m.get("baked_version") == 1 for m in infos(s).values())

        wait_for(baked, 90, period=2.0, what="both replicas to bake the map")
        clients = [SdfClient(NS, st.client_zenoh, timeout=10.0) for _ in range(PLANNERS)]
        # the client's liveliness get at opening already knows both (its first request is spread too)
        assert clients[0].replica_ids() == ["a", "b"], clients[0].replica_ids()
        wait_for(lambda: all(c.replica_ids() == ["a", "b"] for c in clients), 20, what="the clients to see a and b")

        # 1. 8 planners x 4 requests: each evaluated once, spread over both.
        e0 = evaluated(s)
        res = run_planners(clients, pts, per_planner=4)
        e1 = evaluated(s)
        kinds = [k for _, _, k in res]
        assert kinds == ["ok"] * 32, kinds
        delta = {r: e1[r] - e0[r] for r in ("a", "b")}
        print("evaluated per replica, 8 planners x 4 requests:", delta)
        assert sum(delta.values()) == 32 and min(delta.values()) >= 8, delta

        # 2. An old planner's plain get on the shared key: one answer, one evaluation.
        e0 = evaluated(s)
        replies = list(s.get(f"{NS}/query/sdf", payload=protocol.pack({"v": 1, "points": sc.arr(pts[:POINTS], "<f4")}),
                             encoding=sc.ENC, timeout=10.0, consolidation=zenoh.ConsolidationMode.NONE))
        assert len(replies) == 1 and replies[0].ok is not None
        assert sc.unarr(protocol.unpack(replies[0].ok.payload.to_bytes())["sdf"]).shape == (POINTS,)
        e1 = evaluated(s)
        assert sum(e1.values()) - sum(e0.values()) == 1, (e0, e1)
        # ... and the stranger's client (protocol 1.11, written from protocol.md alone) as before
        status, msg = sc.request(s, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts[:5], "<f8")})
        assert status == "ok" and sc.unarr(msg["sdf"]).shape == (5,)

        # 3. A replica with no map joins: it is asked (and says no_map), no request fails.
        st.start(only=["query3"])
        wait_for(lambda: all(c.replica_ids() == ["a", "b", "c"] for c in clients), 30, what="the clients to see c")
        res = run_planners(clients, pts, per_planner=3)
        kinds = [k for _, _, k in res]
        c = infos(s)["c"]
        print("replica without a map:", {k: c[k] for k in ("version", "evaluated", "errors")}, "requests:", len(kinds))
        assert kinds == ["ok"] * 24, kinds
        assert c["version"] is None and c["evaluated"] == 0 and c["errors"] >= 1

        # 4. Replica a killed while the planners ask: the next 15 s lose nothing, fail nothing.
        e0 = evaluated(s)
        t_kill = time.monotonic() + 2.0
        killer = threading.Timer(2.0, st.procs["query"].kill)  # SIGKILL
        killer.start()
        res = run_planners(clients, pts, until=t_kill + 15.0)
        killer.join()
        after = [k for t0, t1, k in res if t1 >= t_kill]
        fails = [k for k in after if k != "ok"]
        e1 = evaluated(s)
        failovers = sum(cl.failovers for cl in clients)
        print(f"failover: {len(res)} requests, {len(after)} ending after the kill, {len(fails)} failed, "
              f"{failovers} failovers in all; evaluated since: b {e1['b'] - e0['b']}, c {e1['c'] - e0['c']}")
        assert not st.alive("query")
        assert fails == [] and len(after) >= 16, fails[:5]
        assert e1["c"] == 0 and e1["b"] - e0["b"] >= len(after)
        assert set(e1) == {"b", "c"} and all(cl.replica_ids() == ["b", "c"] for cl in clients)
        assert st.alive("query2") and st.alive("query3")
    finally:
        for cl in clients:
            cl.close()
        s.close()
        st.stop()
