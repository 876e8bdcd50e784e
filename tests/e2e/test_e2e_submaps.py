"""End to end, protocol 1.3: a submap mapper publishes only the submaps that changed, late
joiners get every submap, a restarted mapper resumes every submap from its checkpoint, and
two robots (two front ends with their own sensor names) build one map in one namespace.
Real processes over real Zenoh on loopback (explicit endpoints, multicast scouting off)."""

import json
import os
import threading
import time

import pytest
import zenoh

from aisdf import keys, protocol, transport
from aisdf.stack import Stack, wait_for

pytestmark = pytest.mark.e2e
NS = "aisdf/e2e13"
MAPPER = ["--preset", "cpu", "--mapper", "submaps", "--set", "training.network.width=32", "--set", "submap.cell_m=3",
          "--set", "log_level=INFO"]


def frontend_args(n_frames, sensor="depth", start=0, max_frames=None):
    a = ["--set", f"n_frames={n_frames}", "--set", "width=80", "--set", "height=60", "--set", "linger=true",
         "--set", f"sensor={sensor}", "--set", f"start={start}", "--fast"]
    return a + (["--set", f"max_frames={max_frames}"] if max_frames else [])


def info(session, name):
    return transport.get_latest(session, keys.key(NS, f"info/{name}"), 2.0)


def get_all(session, key, timeout=5.0) -> dict[str, bytes]:
    out = {}
    for r in session.get(key, timeout=timeout):
        if r.ok is not None:
            out[str(r.ok.key_expr)] = transport.payload_bytes(r.ok.payload)
    return out


def index(session) -> protocol.SubmapIndex | None:
    got = get_all(session, keys.key(NS, keys.MAP_INDEX))
    return protocol.SubmapIndex.from_msg(protocol.unpack(next(iter(got.values())))) if got else None


def test_only_changed_submaps_go_out_late_joiners_get_all_and_a_restart_resumes_every_submap(tmp_path):
    args = MAPPER + ["--checkpoint-dir", str(tmp_path)]
    st = Stack(services=("mapper", "frontend"), namespace=NS, args={"mapper": args, "frontend": frontend_args(600)})
    puts: list[tuple[int, str]] = []  # (map version, submap id) of every submap put
    lock = threading.Lock()

    def on_submap(sample):
        snap = protocol.WeightSnapshot.from_msg(protocol.unpack(transport.payload_bytes(sample.payload)))
        with lock:
            puts.append((snap.version, snap.submap["id"]))

    try:
        st.start()
        with transport.open_session(st.client_zenoh) as s:
            sub = s.declare_subscriber(keys.key(NS, keys.MAP_SUBMAPS) + "/*", on_submap)
            wait_for(lambda: (lambda f: f and f["done"] and f["pending"] == 0)(info(s, "frontend")), 180,
                     what="every keyframe acknowledged")
            time.sleep(4.0)
            sub.undeclare()
            idx = wait_for(lambda: index(s), 30, what="map/index")
            n = len(idx.submaps)
            assert n >= 3, f"the office walk should make several 3 m submaps, got {n}"
            with lock:
                per_version: dict[int, set] = {}
                for v, sid in puts:
                    per_version.setdefault(v, set()).add(sid)
            sizes = [len(x) for x in per_version.values()]
            print(f"{n} submaps; submaps per publication: mean {sum(sizes) / len(sizes):.2f}, max {max(sizes)}")
            assert max(sizes) < n  # never the whole map: only what was trained since the last period
            # a late joiner gets every submap, each on its own key, at the version the index says
            got = get_all(s, keys.key(NS, keys.MAP_SUBMAPS) + "/**")
            snaps = {k.rsplit("/", 1)[1]: protocol.WeightSnapshot.from_msg(protocol.unpack(v)) for k, v in got.items()}
            assert set(snaps) == set(idx.submaps)
            idx2 = index(s)
            for sid, snap in snaps.items():
                assert snap.submap["id"] == sid and snap.epoch == idx2.epoch
                assert snap.version <= idx2.version
            one = next(iter(snaps))
            one_key = keys.key(NS, f"{keys.MAP_SUBMAPS}/{one}")
            assert set(get_all(s, one_key)) == {one_key}  # one id: just that submap
            before = info(s, "mapper")
            assert st.stop_one("mapper") == 0  # clean stop: the checkpoint holds every submap
            st.start(["mapper"])
            idx3 = wait_for(lambda: (lambda i: i if i and i.epoch > idx2.epoch else None)(index(s)), 90,
                            what="the resumed mapper's index")
            assert set(idx3.submaps) == set(idx2.submaps)
            assert all(idx3.submaps[k]["step"] >= idx2.submaps[k]["step"] for k in idx2.submaps)
            after = wait_for(lambda: info(s, "mapper"), 30, what="the resumed mapper")
            assert after["keyframes"] == before["keyframes"] and after["steps"] >= before["steps"]
    finally:
        st.stop()


def _settled(session, ns, n_fronts):
    mi = transport.get_latest(session, keys.key(ns, "info/mapper"), 2.0)
    if not mi or mi["pending"]:
        return None
    fronts = []
    for r in session.get(keys.key(ns, "info/frontend"), target=zenoh.QueryTarget.ALL,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0):
        if r.ok is not None:
            fronts.append(protocol.unpack(transport.payload_bytes(r.ok.payload)))
    if len(fronts) == n_fronts and all(f["done"] and f["pending"] == 0 for f in fronts):
        return mi, fronts
    return None


def test_two_robots_walking_halves_map_as_well_as_one_robot_walking_all():
    """One namespace, two front ends (sensors robot1 and robot2, each half of the walk)
    against one front end walking all of it, both stacks at once (same machine load). After
    the same number of mapper steps, the stranger's client (tests/stranger_client.py, the
    planners' view) measures each map's error against the exact SDF on the same points.

    Single runs spread: two front ends' keyframes interleave in a different order each run, and
    500 steps in the maps are far from trained. Seven runs (2026-12-03) gave two robots / one
    robot 0.98-1.10 for the map's answer, the service's default (networks, surfels and measured
    points fused) and 0.88-1.07 for the networks alone. Six runs on 2026-12-05, with 30 keyframes
    in each map, gave 1.02-1.23 for the default answer (one robot 1.86-1.96 cm, two 1.99-2.28 cm; CI failed once at 1.23 against the
    then bound of 1.2) and 0.92-1.10 for the networks alone (one robot 5.24-5.30 cm, two
    4.88-5.76 cm). The test holds the default answer to 1.35x and the networks alone to 1.25x,
    beyond that spread, and both maps' default answers to 3 cm of the exact SDF (a robot's
    keyframes missing from the map leaves part of the walk unmapped, far above either)."""
    import numpy as np
    import stranger_client as sc

    from aisdf.metrics import eval_points
    from aisdf.synthetic import SyntheticSequence

    # AISDF_TWO_ROBOTS_BUILDING=floor (and a larger AISDF_TWO_ROBOTS_STEPS) runs it on the floor
    building = os.environ.get("AISDF_TWO_ROBOTS_BUILDING", "office")
    steps_after = int(os.environ.get("AISDF_TWO_ROBOTS_STEPS", "500"))
    # the floor's walk is 200 s: 300 frames at 1.5 fps, about one keyframe a second of the walk. The
    # front ends stream as fast as they can and hold every keyframe until the mapper has it (a floor
    # keyframe takes the mapper ~0.7 s on this machine: with the default hold_max, 128, the oldest
    # would be dropped)
    n, fps, settle_s = (600, 30.0, 240) if building == "office" else (300, 1.5, 900)
    building_args = ["--set", f"building={building}", "--set", f"fps={fps}", "--set", "hold_max=1000"]
    mapper = ["--preset", "cpu", "--mapper", "submaps", "--set", "training.network.width=64", "--set", "log_level=INFO"]
    one = Stack(services=("query", "mapper", "frontend"), namespace=NS + "/one",
                args={"mapper": mapper, "frontend": frontend_args(n, "robot0") + building_args})
    two = Stack(services=("query", "mapper", "frontend", "frontend2"), namespace=NS + "/two",
                args={"mapper": mapper, "frontend": frontend_args(n, "robot1", 0, n // 2) + building_args,
                      "frontend2": frontend_args(n, "robot2", n // 2) + building_args})
    seq = SyntheticSequence(building=building, n_frames=n, H=60, W=80, fps=fps, noise=True, seed=0)
    pts = eval_points([seq.frame(i) for i in range(0, n, 10)], n_points=6000, every=1,
                      rng=np.random.default_rng(0), far_margin=0.1)
    gt = seq.gt_sdf(pts)
    try:
        one.start()
        two.start()
        errors, networks, counts = {}, {}, {}
        with transport.open_session(one.client_zenoh) as s1, transport.open_session(two.client_zenoh) as s2:
            runs = {"one robot": (one, s1, 1), "two robots": (two, s2, 2)}
            done = {k: wait_for(lambda s=s, ns=st.namespace, m=m: _settled(s, ns, m), settle_s, what=f"{k}: keyframes in")
                    for k, (st, s, m) in runs.items()}
            for k, (st, s, _) in runs.items():
                mi, fronts = done[k]
                counts[k] = (mi["keyframes"], [f["keyframes"] for f in fronts])
                # every keyframe is accounted for: in the map, or rejected by the mapper as unusable
                # (e.g. too few valid depth pixels facing a wall up close); none lost
                said = f"{k}: mapper {json.dumps(mi, default=str)}; front ends {json.dumps(fronts, default=str)}"
                assert all(f["acked"] + f["rejected"] == f["keyframes"] for f in fronts), said
                assert mi["keyframes"] == sum(f["acked"] for f in fronts), said
            target = {k: done[k][0]["steps"] + steps_after for k in runs}
            for k, (st, s, _) in runs.items():
                wait_for(lambda s=s, ns=st.namespace, t=target[k]: (lambda i: i and i["steps"] >= t)(
                    transport.get_latest(s, keys.key(ns, "info/mapper"), 2.0)), 600, what=f"{k}: training")
                mi = transport.get_latest(s, keys.key(st.namespace, "info/mapper"), 2.0)
                time.sleep(3.0)  # the query service has the map of these steps (published every second)
                with sc.open_session(st.endpoints) as cs:
                    status, reply = sc.query_sdf(cs, st.namespace, pts, source="implicit", timeout=30.0)
                    assert status == "ok", reply
                    status2, reply2 = sc.query_sdf(cs, st.namespace, pts, timeout=30.0)  # the default answer
                    assert status2 == "ok", reply2
                networks[k] = float(np.abs(sc.unarr(reply["sdf"]) - gt).mean())
                errors[k] = float(np.abs(sc.unarr(reply2["sdf"]) - gt).mean())
                print(f"{k}: keyframes {counts[k]}, {mi['stats'].get('submaps')} submaps, after {mi['steps']} "
                      f"steps: error {100 * errors[k]:.2f} cm, networks alone {100 * networks[k]:.2f} cm")
        if building == "office":  # the floor's maps are far from trained after 800 steps (README)
            assert max(errors.values()) < 0.03, errors
        assert errors["two robots"] <= 1.35 * errors["one robot"], errors
        assert networks["two robots"] <= 1.25 * networks["one robot"], networks
    finally:
        one.stop()
        two.stop()
