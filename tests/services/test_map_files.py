"""Map files (``aisdf.mapfiles``, ``aisdf map``) against the mapper service's wiring
(``MapperNode`` on a real Zenoh session on loopback, an unusual port, multicast scouting off)
and a real query service (``QueryNode``): save a trained map to a folder, load it into another
mapper (same keyframes, the same network weights, a new epoch the query service takes), refuse
files that are not maps without running anything in them, export PLY files, and the command's
exit code and sentence when no mapper is there."""

from __future__ import annotations

import io
import json
import os
import pickle
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
import trimesh

from aisdf import keys, mapfiles, protocol, query_messages, transport
from aisdf.config import ZenohOptions
from aisdf.stack import endpoint, free_port, wait_for
from aisdf.synthetic import SyntheticSequence
from aisdf_mapper.config import MapperConfig
from aisdf_mapper.main import MapperNode
from aisdf_query.config import QueryConfig
from aisdf_query.main import QueryNode

NS_A, NS_B = "maptest/a", "maptest/b"
ZOFF = dict(mode="peer", multicast_scouting=False)


def keyframe(seq, i) -> bytes:
    f = seq.frame(i)
    return protocol.pack(protocol.Keyframe(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]).to_msg())


def mapper(session, ns, tmp=None) -> MapperNode:
    cfg = MapperConfig(preset="cpu", namespace=ns, snapshot_period_s=0.3, checkpoint_dir=tmp,
                       training={"network": {"width": 16}, "n_rays": 20})
    node = MapperNode(cfg, session)
    node.start()
    return node


def steps(node, more=5, timeout=60):
    """Wait until ``node`` has trained ``more`` steps beyond now (and published)."""
    s0 = node.pipeline.steps
    wait_for(lambda: node.pipeline.steps >= s0 + more and node.version > 0, timeout, what="training steps")


class Maps:
    """A subscriber to a namespace's map keys: every message, in arrival order."""

    def __init__(self, session, ns):
        self.msgs: list[tuple[str, dict]] = []
        self.sub = session.declare_subscriber(keys.key(ns, "map/**"), self._on)

    def _on(self, sample):
        self.msgs.append((str(sample.key_expr), protocol.unpack(transport.payload_bytes(sample.payload))))


@pytest.fixture(scope="module")
def net(tmp_path_factory):
    """A server session holding mapper A (trained on the office's frames) and a query service
    on its namespace; a client session connected to it."""
    port = free_port()
    seq = SyntheticSequence(building="office", n_frames=200, H=48, W=64, seed=1, noise=None)
    with transport.open_session(ZenohOptions(listen=[endpoint(port)], **ZOFF)) as server, \
            transport.open_session(ZenohOptions(connect=[endpoint(port)], **ZOFF)) as client:
        a = mapper(server, NS_A)
        q = QueryNode(QueryConfig(namespace=NS_A, bake=False, device="cpu", mesh_resolution=0.1), server)
        q.start()
        for i in range(0, 100, 20):
            a.on_keyframe(keyframe(seq, i))
        steps(a, 20)
        wait_for(lambda: transport.get_latest(client, keys.key(NS_A, "info/mapper"), 1.0), 30,
                 what="the mapper, from the client")
        try:
            yield dict(server=server, client=client, a=a, q=q, seq=seq, port=port,
                       tmp=tmp_path_factory.mktemp("maps"))
        finally:
            q.stop()
            a.stop()


def sdf_reply(session, ns, pts):
    msg = transport.query(session, keys.key(ns, keys.QUERY_SDF),
                          query_messages.SdfRequest(pts.astype(np.float32), source="implicit", exact=True).to_msg())
    return query_messages.SdfReply.from_msg(msg)


def test_round_trip_to_a_fresh_mapper_with_a_new_epoch_the_query_service_takes(net):
    client, seq = net["client"], net["seq"]
    folder = mapfiles.save_map(client, NS_A, net["tmp"] / "office")
    meta = json.loads((folder / mapfiles.MAP_JSON).read_text())
    saved = mapfiles.checkpoint_from_bytes((folder / mapfiles.MAP_PT).read_bytes())
    assert meta["format"] == mapfiles.FORMAT and meta["kind"] == "submaps" and meta["keyframes"] == 5
    assert meta["map_version"] == saved["version"] and meta["submaps"] == len(saved["pipeline"]["submaps"]) > 0
    assert sorted(saved["seen"]) == sorted(net["a"].seen) and len(saved["seen"]) == 5

    # mapper B maps other frames of its own, a query service follows it; then B loads A's map
    b = mapper(net["server"], NS_B, net["tmp"] / "ckpt-b")
    qb = QueryNode(QueryConfig(namespace=NS_B, bake=False, device="cpu"), net["server"])
    qb.start()
    try:
        for i in (150, 170, 190):
            b.on_keyframe(keyframe(seq, i))
        steps(b, 10)
        pts = np.array([[0.5, 0.5, 1.0], [1.0, 0.0, 1.2]])
        wait_for(lambda: _answers(client, NS_B, pts), 30, what="B's map at the query service")
        before = (b.epoch, b.version)
        maps = Maps(client, NS_B)
        time.sleep(0.5)  # the subscriber is known to the server
        rep = mapfiles.load_map(client, NS_B, folder)
        assert rep["keyframes"] == 5 and rep["kind"] == "submaps"
        assert rep["epoch"] > before[0] and rep["version"] > max(before[1], saved["version"])
        assert b.seen == {tuple(k) for k in saved["seen"]}  # the loaded map's keyframes, only
        assert b.pipeline.keyframe_keys() == [tuple(k) for k in saved["seen"]]

        # published at once: every submap of the new epoch, with the saved weights exactly
        def first_of_epoch():
            out: dict = {}
            for k, m in list(maps.msgs):  # the first of each: training goes on and publishes again
                if m.get("epoch") == rep["epoch"] and "/map/submaps/" in k:
                    out.setdefault(k, m)
            return out if len(out) == len(saved["pipeline"]["submaps"]) else None
        got = wait_for(first_of_epoch, 30, what="the loaded map's submaps")
        for sd in saved["pipeline"]["submaps"]:
            cid = "_".join(str(int(c)) for c in sd["cell"])
            snap = protocol.WeightSnapshot.from_msg(got[keys.key(NS_B, f"{keys.MAP_SUBMAPS}/{cid}")])
            assert snap.version == rep["version"] and set(snap.state) == set(sd["state"])
            for name, arr in sd["state"].items():
                np.testing.assert_array_equal(snap.state[name], arr)

        # the query service replaces B's map with the loaded one (a newer epoch)
        r = wait_for(lambda: _answers(client, NS_B, pts, rep["epoch"]), 30, what="the loaded map at the query")
        assert r.map_epoch == rep["epoch"] and r.map_version >= rep["version"]
        # B's checkpoint is the loaded map now: a restart resumes it, in a yet newer epoch
        ck = torch.load(net["tmp"] / "ckpt-b" / "mapper-checkpoint.pt", weights_only=False)
        assert ck["epoch"] == rep["epoch"] and {tuple(k) for k in ck["seen"]} == b.seen
        steps(b, 3)  # and it trains on
    finally:
        maps.sub.undeclare()
        qb.stop()
        b.stop()


def _answers(session, ns, pts, epoch=None):
    try:
        r = sdf_reply(session, ns, pts)
    except (protocol.ProtocolError, TimeoutError):
        return None
    return r if epoch is None or r.map_epoch == epoch else None


class Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class Big:
    def __reduce__(self):
        return bytes, (10**6,)


MALICIOUS = ("torch file that runs os.system", "pickle that runs os.system", "bytes(n)")


def bad_files(tmp) -> dict[str, bytes]:
    marker = tmp / "pwned"
    out = {}
    buf = io.BytesIO()
    torch.save({"pipeline": {"x": Evil(marker)}, "version": 1, "epoch": 1}, buf)
    out["torch file that runs os.system"] = buf.getvalue()
    out["pickle that runs os.system"] = pickle.dumps(Evil(marker), protocol=2)
    buf = io.BytesIO()
    torch.save({"pipeline": {"x": Big()}, "version": 1}, buf)
    out["bytes(n)"] = buf.getvalue()
    out["random bytes"] = np.random.default_rng(0).bytes(4096)
    buf = io.BytesIO()
    torch.save({"weights": np.zeros(3)}, buf)
    out["a torch file of another kind"] = buf.getvalue()
    buf = io.BytesIO()
    torch.save({"pipeline": {"format": "aisdf-submaps-checkpoint"}, "version": 1, "epoch": 1}, buf)
    out["a broken checkpoint"] = buf.getvalue()
    return out


def test_files_that_are_not_maps_are_refused_and_nothing_runs(net):
    a, client, tmp = net["a"], net["client"], net["tmp"]
    marker = tmp / "pwned"
    keys_before, epoch, version = a.pipeline.keyframe_keys(), a.epoch, a.version
    for what, data in bad_files(tmp).items():
        with pytest.raises(ValueError) as e:  # the checks alone
            mapfiles.restore_checked(data)
        assert "not a map" in str(e.value) or "not a usable map" in str(e.value), what
        if what in MALICIOUS:  # refused for what it would run, before anything of it runs
            assert str(e.value).startswith("refused: the file is not a map;"), what
            assert str(e.value).endswith("(nothing was run)"), what
        d = tmp / f"bad-{abs(hash(what))}"
        d.mkdir()
        (d / mapfiles.MAP_PT).write_bytes(data)
        (d / mapfiles.MAP_JSON).write_text(json.dumps({"format": mapfiles.FORMAT, "format_version": 1}))
        with pytest.raises(ValueError):  # the client refuses before sending
            mapfiles.load_map(client, NS_A, d)
        with pytest.raises(protocol.ProtocolError) as e:  # the mapper refuses what is sent anyway
            transport.query(client, keys.key(NS_A, mapfiles.LOAD_KEY), {"v": 1, "map": data}, 30)
        assert e.value.code == "bad_request" and e.value.message, what
    with pytest.raises(protocol.ProtocolError) as e:
        transport.query(client, keys.key(NS_A, mapfiles.LOAD_KEY), {"v": 1, "map": "text"}, 30)
    assert e.value.code == "bad_request"
    assert not marker.exists()
    assert a.pipeline.keyframe_keys() == keys_before and a.epoch == epoch and a.version >= version
    steps(a, 3)  # still training its own map
    assert a.epoch == epoch


def test_save_refuses_a_folder_that_is_not_a_map_and_replaces_a_map(net):
    client, tmp = net["client"], net["tmp"]
    other = tmp / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not a map folder"):
        mapfiles.save_map(client, NS_A, other)
    assert (other / "todo.txt").read_text() == "keep me"
    first = mapfiles.save_map(client, NS_A, tmp / "maps" / "one")
    time.sleep(0.01)
    steps(net["a"], 2)
    second = mapfiles.save_map(client, NS_A, tmp / "maps" / "two")
    again = mapfiles.save_map(client, NS_A, first)  # a map folder is replaced
    assert again == first and mapfiles.read_meta(first)["created"] > mapfiles.read_meta(second)["created"]
    assert mapfiles.newest_map(tmp / "maps") == first
    assert mapfiles.newest_map(tmp / "empty-nothing") is None
    assert [p.name for p in (tmp / "maps").iterdir()] in (["one", "two"], ["two", "one"])  # no leftovers


def test_export_writes_a_mesh_and_two_triangles_per_surfel(net):
    client, tmp = net["client"], net["tmp"]
    done = mapfiles.export(client, NS_A, mesh=tmp / "mesh.ply", surfels=tmp / "surfels.ply", resolution=0.1)
    mesh = trimesh.load(tmp / "mesh.ply", process=False)
    assert len(mesh.faces) == done["mesh"]["faces"] > 100
    surf = trimesh.load(tmp / "surfels.ply", process=False)
    n = done["surfels"]["surfels"]
    assert n > 0 and len(surf.faces) == 2 * n and len(surf.vertices) == 4 * n
    sm = protocol.SurfelMap.from_msg(transport.get_latest(client, keys.key(NS_A, keys.MAP_SURFELS)))
    if len(sm) == n:  # the same surfel map: each rectangle's area and colour
        area = surf.area_faces.reshape(-1, 2).sum(1)
        np.testing.assert_allclose(area, sm.surfels["extent"].prod(1), rtol=1e-3)
        colours = surf.visual.face_colors[::2, :3]
        horizontal = sm.surfels["direction"] < 0
        assert len({tuple(c) for c in colours[horizontal]}) <= 1
        assert not {tuple(c) for c in colours[horizontal]} & {tuple(c) for c in colours[~horizontal]}


def aisdf_map(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "aisdf.cli", "map", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_cli_saves_and_says_so_and_fails_in_a_sentence_without_a_mapper(net, tmp_path):
    conn = ["--connect", endpoint(net["port"]), "--no-multicast-scouting"]
    r = aisdf_map("save", str(tmp_path / "cli-map"), "--namespace", NS_A, *conn)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("saved the map of 'maptest/a' to ") and "keyframes" in r.stdout
    assert len(r.stdout.strip().splitlines()) == 1 and mapfiles.read_meta(tmp_path / "cli-map")["keyframes"] == 5

    r = aisdf_map("save", str(tmp_path / "none"), "--namespace", "maptest/nobody", *conn, "--timeout", "5")
    assert r.returncode == 1 and not r.stdout
    assert "aisdf map save: no mapper answered on maptest/nobody/control/mapper/save" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "none").exists()
    r = aisdf_map("load", str(tmp_path), "--namespace", NS_A, *conn)  # a folder of maps: the newest
    assert r.returncode == 0 and "loaded " in r.stdout and "5 keyframes" in r.stdout, r.stderr
    r = aisdf_map("load", str(tmp_path / "cli-map" / "map.json"), *conn)
    assert r.returncode == 1 and "is not a folder" in r.stderr and "Traceback" not in r.stderr
    r = aisdf_map("export", *conn)
    assert r.returncode == 1 and "nothing to export" in r.stderr


@pytest.mark.parametrize("kind", ["single", "submaps"])
def test_both_kinds_of_map_load_safely_with_every_array_and_generator_equal(kind):
    """A map file of either mapper, read by the safe loader and restored: its checkpoint again,
    array for array (weights, AdamW moments, keyframes, generator states)."""
    from aisdf.mapper.factory import make_mapper

    seq = SyntheticSequence(building="office", n_frames=100, H=30, W=40, seed=2, noise=None)
    m = make_mapper(kind, "cpu", {"network": {"width": 16}, "n_rays": 10})
    for i in (0, 30, 60):
        f = seq.frame(i)
        m.add_keyframe(protocol.Keyframe(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
    for _ in range(3):
        m.step()
    ck = {"pipeline": m.checkpoint(), "version": 7, "epoch": 9, "seen": sorted(m.keyframe_keys())}
    loaded = mapfiles.restore_checked(mapfiles.checkpoint_to_bytes(ck))
    assert loaded.version == 7 and loaded.seen == set(m.keyframe_keys()) and loaded.pipeline.kind == kind
    _same(loaded.pipeline.checkpoint(), ck["pipeline"])
    pts = np.random.default_rng(0).uniform(-2, 2, (50, 3))
    np.testing.assert_array_equal(loaded.pipeline.sdf(pts), m.sdf(pts))


def _same(a, b, path="") -> None:
    assert type(a) is type(b) or isinstance(a, (int, float)), path
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype, path
        np.testing.assert_array_equal(a, b, err_msg=path)
    else:
        assert a == b, path
