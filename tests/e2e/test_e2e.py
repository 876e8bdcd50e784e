"""End to end: the real services as separate processes over real Zenoh on loopback
(explicit endpoints on unusual ports, multicast scouting off).

The clients here are the stranger's client of ``stranger_client.py`` (written from
protocol.md alone) and the project's own demo."""

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import torch

import stranger_client as sc
from aisdf import protocol
from aisdf.network import NetworkConfig, SDFNetwork, model_spec, state_to_numpy
from aisdf.stack import Stack, wait_for

pytestmark = pytest.mark.e2e
NS = "aisdf/e2e"
K = np.array([[120.0, 0, 79.5], [0, 120.0, 59.5], [0, 0, 1]])


def snapshot_payload(version=1):
    torch.manual_seed(0)
    net = SDFNetwork(NetworkConfig(width=32, n_layers=2, skip_layer=None))
    spec = model_spec(net)
    spec["bounds"] = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    return protocol.pack(protocol.WeightSnapshot(version, 0, 0.0, spec, state_to_numpy(net)).to_msg()), net


def good_request():
    return {"v": 1, "points": sc.arr(np.zeros((4, 3)), "<f4")}


MALFORMED = [
    b"",
    b"\xc1not msgpack",
    msgpack.packb([1, 2, 3]),
    msgpack.packb({"points": sc.arr(np.zeros((2, 3)), "<f4")}),  # no version
    msgpack.packb({"v": 99, "points": sc.arr(np.zeros((2, 3)), "<f4")}),
    msgpack.packb({"v": 1}),
    msgpack.packb({"v": 1, "points": "lots"}),
    msgpack.packb({"v": 1, "points": {"dtype": "<f4", "shape": [2, 3], "data": b"short"}}),
    msgpack.packb({"v": 1, "points": {"dtype": ">f4", "shape": [1, 3], "data": bytes(12)}}),
    msgpack.packb({"v": 1, "points": {"dtype": "<f4", "shape": [2, 2], "data": bytes(16)}}),
    msgpack.packb({"v": 1, "points": {"dtype": "<u2", "shape": [1, 3], "data": bytes(6)}}),
    msgpack.packb({"v": 1, "points": sc.arr([[np.inf, 0, 0]], "<f4")}),
    msgpack.packb({"v": 1, "points": sc.arr(np.zeros((1, 3)), "<f4"), "gradient": "yes"}),
    msgpack.packb({"v": 1, "points": sc.arr(np.zeros((1, 3)), "<f4"), "source": "oracle"}),
    msgpack.packb({"v": 1, "points": sc.arr(np.zeros((1, 3)), "<f4"), "collision_epsilon": 0}),
    msgpack.packb({"v": 1, "points": {"dtype": "<f4", "shape": [5000, 3], "data": bytes(60000)}}),  # too large
]


def test_query_service_errors_and_recovers():
    with Stack(services=("query",), namespace=NS, args={"query": ["--max-points", "1000"]}) as st:
        s = sc.open_session(st.endpoints)
        try:
            key = f"{NS}/query/sdf"
            # Before any map: no_map.
            status, msg = wait_for(lambda: (lambda r: r if r[0] != "timeout" else None)(sc.request(s, key, good_request(), 2.0)),
                                   60, what="the query service")
            assert status == "err" and msg["error"] == "no_map" and msg["v"] == 1
            payload, net = snapshot_payload()
            s.put(f"{NS}/map/weights", payload, encoding=sc.ENC)
            wait_for(lambda: sc.request(s, key, good_request(), 2.0)[0] == "ok", 30, what="the map to load")
            for bad in MALFORMED:
                t = time.monotonic()
                status, msg = sc.request(s, key, bad, 5.0)
                assert time.monotonic() - t < 1.0
                assert status == "err", bad
                assert msg["v"] == 1 and msg["error"] in ("bad_request", "too_large") and msg["message"]
                status, msg = sc.request(s, key, good_request(), 5.0)
                assert status == "ok" and msg["map_version"] == 1
            # The answers are the network's, with gradients and CHOMP costs.
            pts = np.random.default_rng(0).uniform(-1, 1, (50, 3))
            status, msg = sc.request(s, key, {"v": 1, "points": sc.arr(pts, "<f8"), "gradient": True,
                                              "collision_epsilon": 2.0, "source": "implicit"})
            assert status == "ok"
            with torch.no_grad():
                want = net(torch.tensor(pts, dtype=torch.float32)).reshape(-1).numpy()
            np.testing.assert_allclose(sc.unarr(msg["sdf"]), want, atol=1e-5)
            assert sc.unarr(msg["gradient"]).shape == (50, 3) and sc.unarr(msg["collision"]).shape == (50,)
            # A newer snapshot is swapped in; an older one is ignored; garbage does not break it.
            s.put(f"{NS}/map/weights", b"garbage", encoding=sc.ENC)
            s.put(f"{NS}/map/weights", snapshot_payload(3)[0], encoding=sc.ENC)
            wait_for(lambda: sc.request(s, key, good_request())[1].get("map_version") == 3, 30, what="version 3")
            s.put(f"{NS}/map/weights", snapshot_payload(2)[0], encoding=sc.ENC)
            time.sleep(1.0)
            assert sc.request(s, key, good_request())[1]["map_version"] == 3
            status, msg = sc.request(s, f"{NS}/query/mesh", {"v": 1, "resolution": -1})
            assert status == "err" and msg["error"] == "bad_request"
            assert st.alive("query")
        finally:
            s.close()


def rays_points(room, poses, K, H, W, n, rng):
    """iSDF's evaluation points: random valid pixels, one point uniform in [0.1, D] per ray."""
    out = []
    for T in poses:
        d = room.render(T, K, H, W)
        v, u = np.nonzero(d > 0)
        i = rng.choice(len(v), n // len(poses))
        z = d[v[i], u[i]]
        s = rng.uniform(0.1, 1.0, len(i)) * z
        s = np.maximum(s, 0.1)
        p_C = np.stack([(u[i] - K[0, 2]) / K[0, 0] * s, (v[i] - K[1, 2]) / K[1, 1] * s, s], -1)
        out.append(p_C @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out)


def test_stranger_client_maps_a_scene_the_project_never_saw():
    room = sc.BoxRoom()
    poses = room.poses(24)
    H, W = 120, 160
    with Stack(services=("query", "mapper"), namespace=NS, args={"mapper": ["--preset", "cpu"]}) as st:
        s = sc.open_session(st.endpoints)
        try:
            wait_for(lambda: sc.request(s, f"{NS}/query/sdf", good_request(), 2.0)[0] == "err", 60,
                     what="the query service")
            # The mapper declares its keyframe subscriber before its info queryable: once
            # info answers, a keyframe put from here reaches it.
            wait_for(lambda: sc.request(s, f"{NS}/info/mapper", {"v": 1}, 2.0)[0] == "ok", 60, what="the mapper")
            bad = sc.keyframe_payload(999, 0.0, room.render(poses[0], K, H, W), K, np.diag([2.0, 2, 2, 1]))
            s.put(f"{NS}/keyframes", bad, encoding=sc.ENC)
            for i, T in enumerate(poses):
                s.put(f"{NS}/keyframes", sc.keyframe_payload(i, i * 0.2, room.render(T, K, H, W), K, T, i % 2 == 0),
                      encoding=sc.ENC)
                time.sleep(0.2)
            rng = np.random.default_rng(0)
            pts = rays_points(room, poses, K, H, W, 4000, rng)
            gt = room.sdf(pts)
            untrained = float(np.mean(np.abs(gt)))  # what a network answering ~0 scores
            errors = []

            def good_enough():
                status, msg = sc.query_sdf(s, NS, pts, timeout=20.0)
                if status != "ok":
                    return False
                errors.append(float(np.mean(np.abs(sc.unarr(msg["sdf"]) - gt))))
                return errors[-1] < 0.08

            try:
                wait_for(good_enough, 240, period=5.0, what="the SDF error to fall below 8 cm")
            finally:
                print(f"untrained {untrained:.3f} m; errors over time {np.round(errors, 3).tolist()}")
            assert untrained > 0.4
            status, info = sc.request(s, f"{NS}/info/mapper", {"v": 1})
            assert status == "ok" and info["rejected"] == 1 and info["accepted"] == len(poses)
            check_surfel_map(s, room)
            # The explicit source answers with distances to the planar map.
            status, msg = sc.query_sdf(s, NS, pts[:500], source="explicit")
            assert status == "ok"
            near = np.abs(gt[:500]) < 0.3
            err = np.abs(sc.unarr(msg["sdf"])[near] - gt[:500][near])
            assert np.median(err) < 0.05
        finally:
            s.close()


def check_surfel_map(s, room):
    """The stranger gets the Atlanta frame and the surfels with a plain `get`, and they
    match its room: vertical, the two wall directions, surfels on the room's planes."""
    for r in s.get(f"{NS}/map/surfels", timeout=5.0):
        assert r.ok is not None
        m = msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)
    assert m["v"] == 1
    up, wx, wy = room.wall_normals_W()
    vert = sc.unarr(m["atlanta"]["vertical"])
    hor = sc.unarr(m["atlanta"]["horizontal"])
    assert np.degrees(np.arccos(min(1.0, abs(vert @ up)))) < 1.0
    for w in (wx, wy):
        assert np.degrees(np.arccos(min(1.0, np.max(np.abs(hor @ w))))) < 2.0
    assert len(hor) == 2  # a box room: no spurious direction
    surf = {k: sc.unarr(v) for k, v in m["surfels"].items()}
    n = len(surf["center"])
    assert n >= 4
    # Every surfel's centre lies on one of the room's planes (walls, floor, ceiling, pillar).
    c_R = room.to_room(surf["center"].astype(float))
    lo, hi, plo, phi = room.lo, room.hi, room.p_lo, room.p_hi
    d = np.min(np.abs(np.concatenate([c_R - lo, c_R - hi, c_R - plo, c_R - phi], axis=1)), axis=1)
    assert np.mean(d < 0.03) > 0.9, d
    assert set(np.unique(surf["direction"])) <= {-1, 0, 1}


# Measured by ``pytest -s tests/e2e/test_e2e.py -k maps_the_synthetic`` at 34be166 on 2026-12-05
# (2 CPU cores, shared with another job): served 1.01 cm, the network alone 6.50 cm, the exact
# fused answer 0.91 cm (the README's full demo, 183 s: 0.84-0.98 cm). The bound is 2.5x that.
DEMO_BOUND_CM = 2.5


def test_demo_maps_the_synthetic_building(tmp_path):
    """The README's demo, shortened: three processes, live progress, artefacts, error bound."""
    r = subprocess.run([sys.executable, "-m", "aisdf.cli", "demo", "--duration", "75", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    figures = {k: summary[k] for k in ("sdf_error_cm", "sdf_error_implicit_cm", "sdf_error_fused_network_cm")}
    print("demo, 75 s:", figures)
    # The served answer (fused with the surfels and the measured points), measured 1.01 cm above;
    # the network alone scores several times as much (6.5 cm), and with the served answer reduced to the
    # network alone the demo scored 5.59 cm: both bounds fail then.
    assert summary["sdf_error_cm"] < DEMO_BOUND_CM, figures
    assert summary["sdf_error_cm"] < 0.6 * summary["sdf_error_implicit_cm"], figures
    assert summary["history"][-1]["keyframes"] > 5 and summary["history"][-1]["steps"] > 50
    assert (tmp_path / "demo.rrd").stat().st_size > 10_000
    assert (tmp_path / "mesh.ply").exists()


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    stat = f.read()
            except OSError:
                continue
            if int(stat[stat.rindex(")") + 2:].split()[1]) == pid:
                out.append(int(d))
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_demo_sigterm_stops_its_services_and_still_reports(tmp_path):
    """SIGTERM (``timeout``, ``kill``, a supervisor) stops the demo as Ctrl-C does: its services,
    which run in sessions of their own, are stopped, and the final evaluation is written."""
    p = subprocess.Popen([sys.executable, "-m", "aisdf.cli", "demo", "--duration", "600", "--out", str(tmp_path)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in p.stdout], daemon=True).start()
    seen, end, services = [], time.monotonic() + 240, []
    try:
        while not any("SDF error" in x for x in seen):  # a map is published and answered
            assert time.monotonic() < end and p.poll() is None, "".join(seen)[-3000:]
            try:
                seen.append(lines.get(timeout=1.0))
            except queue.Empty:
                pass
        services = _children(p.pid)
        assert len(services) >= 3, services  # query, mapper, frontend (and the viewer)
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=180) == 0
        wait_for(lambda: not any(_alive(c) for c in services), 30, what="the services to stop")
    finally:  # a failing run leaves nothing behind
        if p.poll() is None:
            p.kill()
        for c in services:
            if _alive(c):
                os.kill(c, signal.SIGKILL)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["history"][-1]["map_version"] > 0 and summary["sdf_error_cm"] < 50.0, summary


def test_demo_stopped_before_any_map_stops_its_services_and_writes_nothing(tmp_path):
    """SIGTERM while the demo is still starting its services (before the mapper answers, so
    before any map): it exits 0, says there was no map to evaluate, writes no summary, and
    leaves no service running."""
    p = subprocess.Popen([sys.executable, "-m", "aisdf.cli", "demo", "--duration", "600", "--out", str(tmp_path)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    services: list[int] = []
    try:
        # query and mapper are started first; the front end only once the mapper answers
        services = wait_for(lambda: (lambda c: c if len(c) >= 2 else None)(_children(p.pid)), 60,
                            what="the demo's first services")
        p.send_signal(signal.SIGTERM)
        out, _ = p.communicate(timeout=180)
        assert p.returncode == 0, out[-3000:]
        wait_for(lambda: not any(_alive(c) for c in services), 30, what="the services to stop")
    finally:
        if p.poll() is None:
            p.kill()
        for c in services:
            if _alive(c):
                os.kill(c, signal.SIGKILL)
    assert "stopped before the mapper published a map: no evaluation" in out, out[-3000:]
    assert "SDF error" not in out and not (tmp_path / "summary.json").exists()


def test_mapper_resumes_its_map_after_a_restart(tmp_path):
    room = sc.BoxRoom()
    poses = room.poses(24)[::4]
    H, W = 60, 80
    K2 = K.copy()
    K2[:2] /= 2
    args = ["--preset", "cpu", "--checkpoint-dir", str(tmp_path), "--set", "checkpoint_period_s=1",
            "--set", "training.network.width=32"]
    with Stack(services=("mapper",), namespace=NS, args={"mapper": args}) as st:
        s = sc.open_session(st.endpoints)
        try:
            info = lambda: (lambda r: r[1] if r[0] == "ok" else None)(sc.request(s, f"{NS}/info/mapper", {"v": 1}, 2.0))  # noqa: E731
            wait_for(info, 60, what="the mapper")
            for i, T in enumerate(poses):
                s.put(f"{NS}/keyframes", sc.keyframe_payload(i, i * 0.5, room.render(T, K2, H, W), K2, T),
                      encoding=sc.ENC)
                time.sleep(0.1)
            before = wait_for(lambda: (lambda i: i if i and i["keyframes"] == len(poses) and i["steps"] > 20 else None)(info()),
                              90, what="training")
            assert st.stop_one("mapper") == 0  # SIGTERM: clean exit, checkpoint written
            assert (tmp_path / "mapper-checkpoint.pt").exists()
            st.start(["mapper"])
            after = wait_for(info, 60, what="the restarted mapper")
            assert after["keyframes"] == len(poses) and after["steps"] >= before["steps"]
            assert after["version"] >= before["version"]
            # the map (protocol 1.3: submaps and their index) is served at once, every submap resumed
            status, msg = sc.request(s, f"{NS}/map/index", {"v": 1}, 5.0)
            assert status == "ok" and msg["version"] >= before["version"]
            assert sum(x["step"] for x in msg["submaps"].values()) >= before["steps"]
        finally:
            s.close()
