"""End to end, protocol 1.14: mapper shards. Three mappers in one namespace share the map of
one robot's walk (each trains the regions it ranks first for), one is killed with SIGKILL
mid-walk and a survivor serves its submaps, a fourth joins and takes its share; a query
service follows the submaps of all of them. Real processes over real Zenoh on loopback
(explicit endpoints, multicast scouting off)."""

import threading
import time

import numpy as np
import pytest

from aisdf import keys, protocol, transport
from aisdf.stack import Stack, wait_for
from aisdf.bench import cluster as bench_cluster

pytestmark = pytest.mark.e2e
NS = "aisdf/e2e14"
MAPPER = ["--preset", "cpu", "--set", "training.network.width=32", "--set", "submap.cell_m=2", "--cluster",
          "--set", "cluster.region_cells=1", "--set", "log_level=INFO"]
FRONTEND = ["--set", "n_frames=600", "--set", "width=80", "--set", "height=60", "--set", "linger=true",
            "--set", "building=office", "--set", "hold_max=1000"]


def mapper_infos(s) -> dict[str, dict]:
    """Every mapper's info/mapper (with the keys of its keyframes), by mapper id."""
    return bench_cluster.mapper_infos(s, NS)


def missing_at_owners(infos: dict[str, dict]) -> list:
    """(keyframe, region) pairs whose region's rank 1 among ``infos``' mappers lacks the keyframe."""
    from aisdf.cluster import ownership as own

    keys_of = {m: {tuple(k) for k in i["keys"]} for m, i in infos.items()}
    touched = {}
    for i in infos.values():
        for k, t in zip(i["keys"], i["touched"]):
            if t is not None:
                touched[tuple(k)] = t
    return [(k, r) for k, t in touched.items() for r in t if k not in keys_of[own.owners(r, list(infos))[0]]]


def test_three_mapper_shards_share_a_map_survive_a_kill_and_take_in_a_joiner(tmp_path):
    import stranger_client as sc

    from aisdf.metrics import eval_points
    from aisdf.synthetic import SyntheticSequence

    ids = {"mapper": "m1", "mapper2": "m2", "mapper3": "m3", "mapper4": "m4"}
    st = Stack(services=("query", "mapper", "mapper2", "mapper3", "mapper4", "frontend"), namespace=NS,
               args={**{k: MAPPER + ["--mapper-id", v] for k, v in ids.items()}, "frontend": FRONTEND},
               log_dir=tmp_path / "logs")
    pubs: list[tuple[float, str, str, int, int]] = []  # (time, submap id, mapper, term, version) of every put
    served: list[tuple[int, int]] = []  # (epoch, version) of every sdf reply a planner got
    lock = threading.Lock()
    stop = threading.Event()

    def on_submap(sample):
        m = protocol.unpack(transport.payload_bytes(sample.payload))
        with lock:
            pubs.append((time.monotonic(), m["submap"]["id"], m["submap"]["mapper"], m["submap"]["term"],
                         m["version"]))

    seq = SyntheticSequence(building="office", n_frames=600, H=60, W=80, fps=30.0, noise=True, seed=0)
    pts = eval_points([seq.frame(i) for i in range(0, 600, 20)], n_points=3000, every=1,
                      rng=np.random.default_rng(0), far_margin=0.1)
    gt = seq.gt_sdf(pts)

    def planner():  # asks all along for the newest map's answer (exact: not a bake, whose map may trail
        # the newest one served before, 1.7-1.10); the map it is served never goes back
        with sc.open_session(st.endpoints) as cs:
            while not stop.wait(0.5):
                status, reply = sc.request(cs, f"{NS}/query/sdf", {"v": 1, "points": sc.arr(pts[:200], "<f8"),
                                                                   "exact": True}, 10.0)
                if status == "ok":
                    served.append((int(reply.get("map_epoch", 0)), int(reply["map_version"])))

    def owners_of(t0, t1):
        with lock:
            return [p for p in pubs if t0 <= p[0] < t1]

    try:
        st.start(only=["query", "mapper", "mapper2", "mapper3"])
        with transport.open_session(st.client_zenoh) as s:
            sub = s.declare_subscriber(keys.key(NS, keys.MAP_SUBMAPS) + "/*", on_submap)
            wait_for(lambda: (lambda i: len(i) == 3 and all(len(v["cluster"]["members"]) == 3 for v in i.values()))(
                mapper_infos(s)), 180, what="three members")  # three torch processes starting on 2 cores
            st.start(only=["frontend"])
            th = threading.Thread(target=planner, daemon=True)
            th.start()
            # mid-walk, once m2 has published submaps of its own: SIGKILL
            wait_for(lambda: len({p[1] for p in owners_of(0, 1e18) if p[2] == "m2"}) >= 2, 120,
                     what="m2 publishing")
            t_kill = time.monotonic()
            st.procs["mapper2"].kill()
            front = wait_for(lambda: (lambda f: f and f["done"] and f["pending"] == 0 and f)(
                transport.get_latest(s, keys.key(NS, "info/frontend"), 2.0)), 120, what="every keyframe acknowledged")
            # the killed mapper's submaps are published by a survivor within 10 s, with a newer term
            m2_cells = {p[1]: p[3] for p in owners_of(0, t_kill) if p[2] == "m2"}
            wait_for(lambda: all(any(p[1] == c and p[2] != "m2" for p in owners_of(t_kill, 1e18)) for c in m2_cells),
                     10.0, what="m2's submaps from a survivor")
            for c, term in m2_cells.items():
                took = min(p for p in owners_of(t_kill, 1e18) if p[1] == c and p[2] != "m2")
                assert took[3] > term and took[0] - t_kill < 10.0, (c, took, term)
            # no acknowledged keyframe is lost: the survivors hold every one, and the owner of every
            # region a keyframe touches holds it (it trains on it)
            infos = mapper_infos(s)
            assert set(infos) == {"m1", "m3"}
            held = set().union(*({tuple(k) for k in i["keys"]} for i in infos.values()))
            assert front["acked"] + front["rejected"] == front["keyframes"] and front["acked"] >= 20, front
            assert len(held) == front["acked"], (len(held), front)
            wait_for(lambda: not missing_at_owners(mapper_infos(s)), 15.0, what="every region's owner has its keyframes")
            # a fourth mapper joins: within 30 s it owns a share and publishes it
            t_join = time.monotonic()
            st.start(only=["mapper4"])
            wait_for(lambda: any(p[2] == "m4" for p in owners_of(t_join, 1e18)), 30.0, what="m4 publishing its share")
            info4 = wait_for(lambda: mapper_infos(s).get("m4"), 10.0, what="m4's info")
            assert info4["cluster"]["owned"], info4["cluster"]
            time.sleep(3.0)
            stop.set()
            th.join(30)
            sub.undeclare()
            # one mapper at a time per submap: the publishers of a submap follow each other, each
            # once, with rising terms (no two train it at once, none comes back)
            with lock:
                by_cell: dict[str, list] = {}
                for t, sid, m, term, v in sorted(pubs):
                    by_cell.setdefault(sid, []).append((m, term))
            for sid, seq_ in by_cell.items():
                runs = [seq_[0]] + [b for a, b in zip(seq_, seq_[1:]) if b != a]
                assert len({m for m, _ in runs}) == len(runs), (sid, runs)
                assert [t for _, t in runs] == sorted(t for _, t in runs), (sid, runs)
            moved = [sid for sid, r in by_cell.items() if r[-1][0] == "m4"]
            assert moved, by_cell
            # planners were never served an older map than one already served
            assert len(served) >= 10 and served == sorted(served), served[-20:]
            # the served map: bounded error at the end
            time.sleep(2.0)
            with sc.open_session(st.endpoints) as cs:
                status, reply = sc.query_sdf(cs, NS, pts, timeout=30.0)
            assert status == "ok", reply
            err = float(np.abs(sc.unarr(reply["sdf"]) - gt).mean())
            print(f"{front['keyframes']} keyframes, {len(by_cell)} submaps, m4 took {sorted(moved)}; served error "
                  f"{100 * err:.2f} cm")
            assert err < 0.10, err  # 4.2 and 5.2 cm measured (2026-12-05, a loaded 2-core machine)
    finally:
        stop.set()
        st.stop()
