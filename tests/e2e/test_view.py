"""``aisdf view --save``: the live viewer as a process next to the real services over real
Zenoh on loopback (explicit endpoints, multicast scouting off); the recording it writes is
opened with rerun's reader and counted."""

import re
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest

from aisdf import keys, protocol, transport
from aisdf.config import ZenohOptions
from aisdf.stack import Stack, endpoint, free_port, wait_for

rr = pytest.importorskip("rerun", reason="rerun-sdk is the viewer extra (aisdf[viewer], in [dev])")
from rerun.chunk import RrdReader  # noqa: E402

pytestmark = pytest.mark.e2e
NS = "aisdf/e2eview"
MAPPER = ["--preset", "cpu", "--set", "training.network.width=32"]
K = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])


def read_recording(path):
    """{entity path: [record batch, ...]} of the first recording in an .rrd file."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def rows(batches, column):
    """Every logged row of ``column`` (an archetype field such as 'DepthImage:buffer'), in order."""
    return [v for rb in batches if column in rb.schema.names for v in rb.column(column).to_pylist() if v is not None]


def start_viewer(tmp_path, port, connect, *extra):
    cmd = [sys.executable, "-m", "aisdf.cli", "view", "--save", str(tmp_path / "view.rrd"), "--namespace", NS,
           "--no-multicast-scouting", "--listen", endpoint(port), "--log-level", "INFO", *extra]
    for e in connect:
        cmd += ["--connect", e]
    log = open(tmp_path / "viewer.log", "w")  # noqa: SIM115 - closed by stop_viewer
    p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    p.log_file = log
    return p


def stop_viewer(p, tmp_path) -> str:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    p.log_file.close()
    return (tmp_path / "viewer.log").read_text()


def viewer_up(session) -> bool:
    for reply in session.liveliness().get(keys.status_key(NS, "viewer", "*"), timeout=1.0):
        if reply.ok is not None:
            return True
    return False


def info(session, name):
    return transport.get_latest(session, keys.key(NS, f"info/{name}"), 2.0)


def meshes_logged(log, n_vertices: int) -> bool:
    """At least three meshes in the viewer's log, one of at least ``n_vertices`` vertices."""
    sizes = [int(m) for m in re.findall(r"mesh of map v\d+: (\d+) vertices", log.read_text())]
    return len(sizes) >= 3 and max(sizes) >= n_vertices


def test_view_records_keyframes_surfels_and_meshes_of_a_running_stack(tmp_path):
    vport = free_port()
    frontend = ["--set", "n_frames=240", "--set", "width=80", "--set", "height=60", "--set", "linger=true",
                "--connect", endpoint(vport)]  # the frontend reaches the viewer as it starts: no keyframe missed
    st = Stack(namespace=NS, log_dir=tmp_path / "logs",
               args={"mapper": MAPPER, "query": ["--set", "bake=false"], "frontend": frontend})
    viewer = None
    try:
        st.start(["query", "mapper"])
        viewer = start_viewer(tmp_path, vport, st.endpoints, "--mesh-period", "1", "--mesh-resolution", "0.15")
        with transport.open_session(st.client_zenoh) as s:
            wait_for(lambda: info(s, "mapper"), 90, what="the mapper")
            wait_for(lambda: viewer_up(s), 60, what="the viewer")
            st.start(["frontend"])
            fi = wait_for(lambda: (lambda i: i if i and i["done"] and i["pending"] == 0 else None)(info(s, "frontend")),
                          120, what="every keyframe acknowledged")
            # Three meshes, one of them the room's (the first ones are of a map of a keyframe or
            # two: their size depends on how far training got when they were asked).
            wait_for(lambda: meshes_logged(tmp_path / "viewer.log", 2000), 120,
                     what="three meshes in the viewer, one of the room")
            smap = protocol.SurfelMap.from_msg(transport.get_latest(s, keys.key(NS, keys.MAP_SURFELS), 2.0))
        text = stop_viewer(viewer, tmp_path)
        assert viewer.returncode == 0, text[-3000:]
    finally:
        if viewer is not None and viewer.poll() is None:
            stop_viewer(viewer, tmp_path)
        st.stop()
    print(text.strip().splitlines()[-1])
    print(f"frontend: {fi['keyframes']} keyframes, {fi['sent']} sent, {fi['resent']} resent; "
          f"surfel map v{smap.version}: {len(smap)} surfels, {len(smap.horizontal)} horizontal directions")
    rec = read_recording(tmp_path / "view.rrd")

    # Keyframes: every one the frontend selected, once (resends are not logged again).
    depth = rows(rec["/world/cameras/depth/depth"], "DepthImage:buffer")
    assert fi["keyframes"] > 5 and len(depth) == fi["keyframes"]
    assert rows(rec["/world/cameras/depth"], "Pinhole:image_from_camera")
    assert len(rows(rec["/world/cameras/depth"], "Transform3D:translation")) == fi["keyframes"]
    path = rows(rec["/world/paths/depth"], "LineStrips3D:strips")
    assert len(path[-1][0]) == fi["keyframes"]  # the last strip runs through every keyframe

    # Surfels: boxes coloured by Atlanta direction, the frame as arrows.
    boxes = rows(rec["/world/surfels"], "Boxes3D:centers")
    classes = rows(rec["/world/surfels"], "Boxes3D:class_ids")
    assert len(smap) > 10 and len(boxes[-1]) > 10 and len(boxes[-1]) == len(classes[-1])
    m = len(smap.horizontal)
    assert m >= 1 and set(classes[-1]) <= set(range(m + 1)) and 0 in set(classes[-1])  # floor/ceiling and walls
    assert len(set(classes[-1])) >= 2
    arrows = rows(rec["/world/atlanta"], "Arrows3D:vectors")
    np.testing.assert_allclose(np.array(arrows[-1][0]), smap.vertical, atol=0.05)  # the newest map's vertical
    assert rows(rec["/world"], "AnnotationContext:context")

    # Meshes: at least three updates, each a surface, one of the room. Measured (2026-12-07):
    # [149, 94, 2897, 6881, 8513] and [149, 31, 1712, 5583] vertices.
    verts = rows(rec["/world/mesh"], "Mesh3D:vertex_positions")
    faces = rows(rec["/world/mesh"], "Mesh3D:triangle_indices")
    print(f"recording: {len(depth)} depth images, {len(boxes)} surfel maps (last {len(boxes[-1])} boxes), "
          f"{len(verts)} meshes of {[len(v) for v in verts]} vertices")
    assert len(verts) >= 3 and len(faces) == len(verts) and max(len(v) for v in verts) >= 2000
    for v, f in zip(verts, faces):
        f = np.asarray(f)
        assert len(v) >= 3 and len(f) >= 1 and f.min() >= 0 and f.max() < len(v)


def test_view_skips_malformed_messages_and_keeps_going(tmp_path):
    vport, cport = free_port(), free_port()
    viewer = start_viewer(tmp_path, vport, [endpoint(cport)], "--mesh-period", "0")
    s = transport.open_session(ZenohOptions(mode="peer", listen=[endpoint(cport)], connect=[endpoint(vport)],
                                            multicast_scouting=False))
    try:
        wait_for(lambda: viewer_up(s), 60, what="the viewer")
        time.sleep(0.5)  # the viewer's subscriptions reach this session with its token
        good = protocol.SurfelMap(7, 1.0, np.array([0.0, 0.0, 1.0]), np.array([[1.0, 0.0, 0.0]]), {
            "center": np.array([[0, 0, 0], [1, 0, 1]], np.float32),
            "normal": np.array([[0, 0, 1], [1, 0, 0]], np.float32),
            "axis1": np.array([[1, 0, 0], [0, 1, 0]], np.float32),
            "axis2": np.array([[0, 1, 0], [0, 0, 1]], np.float32),
            "extent": np.array([[1, 2], [0.5, 0.5]], np.float32), "direction": np.array([-1, 0], np.int32),
            "keyframe": np.array([3, 4], np.int64)})
        bad_surfels = [b"", b"\xc1not msgpack", msgpack.packb([1, 2]), msgpack.packb({"v": 99}),
                       msgpack.packb({"v": 1, "version": 1, "stamp": 0.0}),
                       protocol.pack(dict(good.to_msg(), surfels={**good.to_msg()["surfels"],
                                                                  "extent": {"dtype": "<f4", "shape": [2, 2],
                                                                             "data": b"short"}}))]
        kf = protocol.Keyframe(1, 0.5, np.full((60, 80), 2.0, np.float32), K, np.eye(4))
        enc = transport.ENCODING
        for bad in bad_surfels:
            s.put(keys.key(NS, keys.MAP_SURFELS), bad, encoding=enc)
            time.sleep(0.05)
        s.put(keys.key(NS, keys.KEYFRAMES), b"garbage", encoding=enc)
        s.put(keys.key(NS, keys.MAP_WEIGHTS), msgpack.packb({"v": 1, "version": "x"}), encoding=enc)
        s.put(keys.key(NS, keys.MAP_INDEX), msgpack.packb({"v": 1, "version": 3, "stamp": 0.0, "grid": {}}),
              encoding=enc)
        time.sleep(0.3)
        grid = {"R_WG": np.eye(3).reshape(-1).tolist(), "origin": [0.0, 0.0, 0.0], "cell_m": 4.0,
                "cell_height_m": 3.0, "overlap_m": 0.5}
        index = protocol.SubmapIndex(5, 1.0, grid, {"0_0_0": {"version": 5, "step": 10}}, epoch=1)
        transport.put(s, keys.key(NS, keys.MAP_INDEX), index.to_msg())  # a submap mapper's map version (1.3)
        transport.put(s, keys.key(NS, keys.MAP_SURFELS), good.to_msg())
        transport.put(s, keys.key(NS, keys.KEYFRAMES), kf.to_msg())
        transport.put(s, keys.key(NS, keys.KEYFRAMES), kf.to_msg())  # a resend: logged once
        older = protocol.SurfelMap(6, 1.0, good.vertical, good.horizontal, protocol.SurfelMap.empty_surfels())
        transport.put(s, keys.key(NS, keys.MAP_SURFELS), older.to_msg())  # older than v7: not shown
        wait_for(lambda: "skipped a malformed message" in (tmp_path / "viewer.log").read_text(), 10,
                 what="the viewer's warnings")
        time.sleep(1.0)
        assert viewer.poll() is None  # still running
    finally:
        s.close()
        text = stop_viewer(viewer, tmp_path)
    assert viewer.returncode == 0, text[-3000:]
    summary = text.strip().splitlines()[-1]
    print(summary)
    assert "viewer: 1 keyframes (1 repeats skipped, 0 dropped), 1 surfel maps (last: 2 surfels)" in summary
    assert "0 weight snapshots, 1 submap indexes, 0 meshes" in summary
    assert f"{len(bad_surfels) + 3} malformed messages skipped" in summary
    rec = read_recording(tmp_path / "view.rrd")
    boxes = rows(rec["/world/surfels"], "Boxes3D:centers")
    assert len(boxes) == 1 and np.allclose(boxes[0], good.surfels["center"])
    assert rows(rec["/world/surfels"], "Boxes3D:class_ids") == [[0, 1]]  # vertical, horizontal 0
    assert len(rows(rec["/world/cameras/depth/depth"], "DepthImage:buffer")) == 1
    assert len(rows(rec["/log"], "TextLog:text")) == len(bad_surfels) + 3
    assert rows(rec["/stats/map_version"], "Scalars:scalars") == [[5.0]]


def test_view_without_rerun_fails_clearly(tmp_path):
    # A Python where `import rerun` fails: a module of that name that raises ImportError.
    (tmp_path / "rerun.py").write_text("raise ImportError('no rerun here')\n")
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}
    r = subprocess.run([sys.executable, "-m", "aisdf.cli", "view", "--save", str(tmp_path / "x.rrd")],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 1 and "pip install 'aisdf[viewer]'" in r.stderr, r.stderr
    assert not (tmp_path / "x.rrd").exists()


def test_box_rotations_take_the_box_axes_to_the_surfel_axes():
    from scipy.spatial.transform import Rotation

    from aisdf.mapview import box_quaternions, vertex_normals

    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=1).as_matrix()
    a1, a2 = R[:, :, 0] * rng.uniform(0.5, 2, (50, 1)), R[:, :, 1]  # axis1 need not be unit
    got = Rotation.from_quat(box_quaternions(a1, a2)).as_matrix()
    np.testing.assert_allclose(got, R, atol=1e-9)
    # A unit square in z = 0, two triangles: every vertex normal is +z.
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    np.testing.assert_allclose(vertex_normals(v, np.array([[0, 1, 2], [0, 2, 3]])), [[0, 0, 1]] * 4, atol=1e-6)


def test_map_view_colours_surfels_by_atlanta_direction(tmp_path):
    from aisdf.mapview import MapView

    rec = rr.RecordingStream("aisdf-test")
    rec.save(str(tmp_path / "v.rrd"))
    view = MapView(rec)
    sf = protocol.SurfelMap.empty_surfels()
    n = 4
    sf.update(center=np.zeros((n, 3), np.float32), normal=np.tile([0, 0, 1], (n, 1)).astype(np.float32),
              axis1=np.tile([1, 0, 0], (n, 1)).astype(np.float32), axis2=np.tile([0, 1, 0], (n, 1)).astype(np.float32),
              extent=np.ones((n, 2), np.float32), direction=np.array([-1, 0, 1, 7], np.int32),
              keyframe=np.arange(n, dtype=np.int64))
    horizontal = np.array([[1.0, 0, 0], [0.6, 0.8, 0]])
    assert view.surfel_map(protocol.SurfelMap(3, 0.0, np.array([0, 0, 1.0]), horizontal, sf, epoch=2))
    assert not view.surfel_map(protocol.SurfelMap(9, 0.0, np.array([0, 0, 1.0]), horizontal, sf, epoch=1))  # older
    rec.flush()
    rec.disconnect()
    got = read_recording(tmp_path / "v.rrd")
    # vertical -> 0, horizontal k -> k + 1, a label outside the frame -> M + 1.
    assert rows(got["/world/surfels"], "Boxes3D:class_ids") == [[0, 1, 2, 3]]
    assert rows(got["/world/surfels"], "Boxes3D:half_sizes")[0][0] == pytest.approx([0.5, 0.5, 0.005])
    assert rows(got["/world/atlanta"], "Arrows3D:class_ids") == [[0, 1, 2]]
