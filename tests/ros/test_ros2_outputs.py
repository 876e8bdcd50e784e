"""The map for ROS 2 (``aisdf ros2``): the ground and the slice (aisdf.ros.slices), the grid's
cells placed in the world by the message alone, and end to end a real ``aisdf-query`` process
with the ROS node in-process: a late-joining ROS 2 subscriber (as Nav2's static layer, transient
local) decodes the real message definitions with rosbags and only on the exact type hash; the
grid agrees with the building's true geometry; the distance window service returns the box's
grid; save_map without a mapper says why."""

from __future__ import annotations


import time

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

import stranger_client as sc
from aisdf import protocol, transport
from aisdf.ros import interfaces, outmsgs, slices
from aisdf.ros import rmw_zenoh as rz
from aisdf.ros.outputs import MapOutputs, Ros2OutputsConfig
from aisdf.client import SdfClient
from aisdf.ros.outputs_services import MapServices
from aisdf.stack import Stack, wait_for
from helpers.small_map import publish_until_baked, train_small_map

torch.set_num_threads(1)
NS = "aisdf/ros2out"


def surfels(*rects):
    """rects: (centre, normal, extent (2,), direction) -> a surfel dict (axes orthogonal to the normal)."""
    c, n, a1, a2, e, d = [], [], [], [], [], []
    for centre, normal, ext, direction in rects:
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        c.append(centre), n.append(normal), a1.append(u), a2.append(np.cross(normal, u)), e.append(ext)
        d.append(direction)
    return {"center": np.array(c, float), "normal": np.array(n), "axis1": np.array(a1), "axis2": np.array(a2),
            "extent": np.array(e, float), "direction": np.array(d)}


def room(Q=np.eye(3), ceiling=True):
    """A floor at height 0 (two big surfels), a table top at 0.75 m, a ceiling at 2.6 m and a wall,
    all rotated by Q."""
    up = Q @ [0, 0, 1.0]
    rects = [(Q @ [0, 0, 0.0], up, (3, 3), -1), (Q @ [3, 0, 0.01], up, (3, 2), -1),
             (Q @ [1, 1, 0.75], up, (1.5, 1.0), -1), (Q @ [-1.5, 0, 1.3], Q @ [1.0, 0, 0], (3, 2.6), 0)]
    if ceiling:
        rects.append((Q @ [0, 0, 2.6], -up, (3, 3), -1))
    return surfels(*rects)


def test_ground_finds_up_and_the_floor_in_any_world_frame():
    g = slices.ground_from_surfels([0, 0, 1.0], room())
    assert g.z_up and g.height == pytest.approx(0.0036, abs=1e-3)  # area-weighted: 9 m2 at 0, 6 m2 at 0.01
    # the vertical's sign does not matter; a vertical 0.3 degrees off z snaps to z, 2 degrees does not
    assert slices.ground_from_surfels([0, 0, -1.0], room()).z_up
    assert slices.ground_from_surfels(Rotation.from_euler("x", 0.3, degrees=True).apply([0, 0, 1.0]), room()).z_up
    tilted = slices.ground_from_surfels(Rotation.from_euler("x", 2, degrees=True).apply([0, 0, 1.0]), room())
    assert not tilted.z_up and tilted.up[2] > 0.99
    # a world frame that is not z-up: up from the surfels (the side facing up covers more area)
    for euler in ((100, 20, 0), (-120, 0, 45), (60, 0, 90)):
        Q = Rotation.from_euler("xyz", euler, degrees=True).as_matrix()
        for v_sign in (1, -1):
            for ceiling in (True, False):
                g = slices.ground_from_surfels(v_sign * (Q @ [0, 0, 1.0]), room(Q, ceiling))
                np.testing.assert_allclose(g.up, Q @ [0, 0, 1.0], atol=1e-9)
                assert g.height == pytest.approx(0.0036, abs=1e-3) and not g.z_up
                np.testing.assert_allclose(g.R.T @ g.R, np.eye(3), atol=1e-9)
                # grid coordinates: the floor at height 0, the table top at 0.75
                assert g.to_grid(Q @ [1, 1, 0.75])[2] == pytest.approx(0.75 - g.height)
    # no floor seen: no height (the grid waits), unless given
    wall_only = surfels(([0, 0, 1.0], [1.0, 0, 0], (2, 2), 0))
    assert slices.ground_from_surfels([0, 0, 1.0], wall_only).height is None
    assert slices.ground_from_surfels([0, 0, 1.0], wall_only, floor=0.2).height == 0.2
    # a room whose ceiling was seen more than its floor: up is wrong unless given
    Q = Rotation.from_euler("xyz", (100, 20, 0), degrees=True).as_matrix()
    big_ceiling = surfels((Q @ [0, 0, 0.0], Q @ [0, 0, 1.0], (2, 2), -1), (Q @ [0, 0, 2.6], Q @ [0, 0, -1.0], (4, 4), -1))
    assert slices.ground_from_surfels(Q @ [0, 0, 1.0], big_ceiling).up @ (Q @ [0, 0, 1.0]) < 0
    g = slices.ground_from_surfels(Q @ [0, 0, 1.0], big_ceiling, up=Q @ [0, 0, 2.0])
    np.testing.assert_allclose(g.up, Q @ [0, 0, 1.0], atol=1e-9)
    assert g.height == pytest.approx(0.0, abs=1e-9)


def test_slice_and_occupancy_values():
    levels = slices.band_levels((0.1, 1.0), 0.05)
    assert levels[0] == 0.1 and levels[-1] == 1.0 and np.diff(levels).max() <= 0.1 + 1e-12
    sdf = np.full((30, 20, len(levels)), 1.0)
    seen = np.ones_like(sdf, bool)
    sdf[10, 5, 4] = 0.02  # a surface near one sample of one column
    sdf[20, 15, 2] = -0.3  # inside something, but never observed: not an obstacle
    seen[20, 15, 2] = False
    seen[25:, :, :] = False  # unobserved columns
    s = slices.slice_columns(sdf, seen, 0.05)
    assert s.obstacle.sum() == 1 and s.obstacle[10, 5] and s.observed[:25].all() and not s.observed[25:].any()
    grid, clear = slices.occupancy(s.obstacle, s.observed, 0.05, 0.2)
    ii, jj = np.meshgrid(np.arange(30), np.arange(20), indexing="ij")
    d = 0.05 * np.hypot(ii - 10, jj - 5)
    np.testing.assert_allclose(clear, d, atol=1e-12)
    assert (grid[d < 0.2] == 100).all() and (grid[(d >= 0.2) & (ii < 25)] == 0).all()
    assert (grid[(d >= 0.2) & (ii >= 25)] == -1).all()
    # radius 0 (Nav2's inflation layer inflates): the obstacle columns alone
    grid0, _ = slices.occupancy(s.obstacle, s.observed, 0.05, 0.0)
    assert grid0[10, 5] == 100 and (grid0 == 100).sum() == 1


def test_grid_message_places_each_cell_in_the_world():
    ts = rz.open_typestore("jazzy")
    Q = Rotation.from_euler("xyz", (100, 20, 30), degrees=True).as_matrix()
    ground = slices.ground_from_surfels(Q @ [0, 0, 1.0], room(Q))
    grid = np.zeros((40, 25), np.int8)
    grid[31, 7] = 100
    origin = np.array([-1.2, 0.35])
    msg = outmsgs.occupancy_grid(ts, grid, ground, origin, 0.05, "map", 1_700_000_000_123_456_789)
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"), "nav_msgs/msg/OccupancyGrid")
    assert (back.info.width, back.info.height) == (40, 25) and back.header.frame_id == "map"
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    row, col = divmod(int(np.flatnonzero(back.data == 100)[0]), back.info.width)
    o, q = back.info.origin, back.info.origin.orientation
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    cell_W = np.array([o.position.x, o.position.y, o.position.z]) + R @ [(col + 0.5) * 0.05, (row + 0.5) * 0.05, 0]
    want = ground.to_world(np.array([[origin[0] + 31 * 0.05, origin[1] + 7 * 0.05, 0.0]]))[0]
    np.testing.assert_allclose(cell_W, want, atol=1e-6)


def _truth_grid(out: MapOutputs, seq):
    """The grid the node would publish from the building's true SDF at the same samples, the
    observed columns of the service's answers, and the samples (world points)."""
    cfg, T = out.cfg, out.cfg.tile
    lo = np.array(min(out.tiles)), np.array(max(out.tiles))
    obstacle, observed, origin = out.assemble(*lo)
    levels = slices.band_levels(cfg.band, cfg.resolution)
    nx, ny = obstacle.shape
    g = np.stack(np.meshgrid(origin[0] + cfg.resolution * np.arange(nx), origin[1] + cfg.resolution * np.arange(ny),
                             levels, indexing="ij"), -1).reshape(-1, 3)
    gt = seq.gt_sdf(out.ground.to_world(g)).reshape(nx, ny, len(levels))
    true_obstacle = (gt < cfg.resolution).any(-1)
    grid, _ = slices.occupancy(true_obstacle, observed, cfg.resolution, cfg.robot_radius)
    assert T and len(out.tiles) > 1
    return grid, observed, out.ground.to_world(g)


def test_ros2_outputs_end_to_end():
    seq, _, p = train_small_map()
    snap, smap = p.weight_snapshot(1), p.surfel_map(1)
    assert abs(smap.vertical[2]) < 0.9  # this building's world frame is not z-up
    with Stack(services=("query",), namespace=NS) as st:
        s = sc.open_session(st.endpoints)
        sess = transport.open_session(st.client_zenoh)
        ros = rz.open_ros_session([st.endpoints[0]])
        ros2 = rz.open_ros_session([st.endpoints[0]])
        node = listener = None
        try:
            cfg = Ros2OutputsConfig(namespace=NS, zenoh=st.client_zenoh, map_dir=st.log_dir or "maps-none")
            node = rz.Node(ros, "aisdf")
            out, services = MapOutputs(cfg, sess, node), MapServices(cfg, sess, node)
            time.sleep(0.5)

            publish_until_baked(s, NS, snap, smap)  # the surfels first: the first bake holds them
            wait_for(lambda: out.surfel_map is not None, 10, what="the surfel map")
            out.tick()
            assert out.baked == (0, 1, smap.version)  # the bake's map and surfel map (1.19), from the probe
            assert out.counts["grids"] == 1 and out.counts["surfel_maps"] == 1 and out.counts["meshes"] == 1
            # Nothing changed: nothing is sampled again.
            tiles = out.counts["tiles"]
            out.tick()
            assert out.counts["tiles"] == tiles and out.counts["grids"] == 1
            # The grid is the one the served answers give: the same samples asked here as one batch
            # of points, sliced, equal it cell for cell (columns the node's coarse pass found far
            # from observed space it did not ask about: unobserved either way).
            truth, observed, pts = _truth_grid(out, seq)
            got = out.last_grid
            with SdfClient(NS, st.client_zenoh, timeout=60) as cl:
                r = cl.query(pts.astype(np.float32), observed=True, fresh=False)  # the bake, as the node asks
            sl = slices.slice_columns(r.sdf.reshape(*got.shape, -1), r.observed.reshape(*got.shape, -1), 0.05)
            np.testing.assert_array_equal(got, slices.occupancy(sl.obstacle, sl.observed, 0.05, 0.2)[0])
            # ... and against the true geometry's grid: nearly every true obstacle is one (this toy
            # map, 30 steps, also puts obstacles where there are none: its answers, not the slice)
            agree = (got == truth)[observed].mean()
            recall = ((got == 100) & (truth == 100) & observed).sum() / ((truth == 100) & observed).sum()
            print(f"cells agreeing with the true geometry's grid: {100 * agree:.1f} % of {observed.sum()} observed; "
                  f"true obstacles found: {100 * recall:.1f} %")
            # measured (2026-12-05): 70.1 % agree, 95.9 % found
            assert agree > 0.5 and recall > 0.85, (agree, recall)

            # A late joiner, as Nav2's static layer (transient local), on the exact type hash.
            got_msgs: dict[str, list] = {}
            listener = rz.Node(ros2, "nav2_listener", node_id=1)
            latched = rz.QoS(durability=rz.TRANSIENT_LOCAL, depth=1)
            for topic, typ, qos in (("/aisdf/occupancy_grid", "nav_msgs/msg/OccupancyGrid", latched),
                                    ("/aisdf/surfels", "visualization_msgs/msg/MarkerArray", latched),
                                    ("/aisdf/mesh", "visualization_msgs/msg/Marker", latched)):
                listener.create_subscription(topic, typ, lambda m, info, t=topic: got_msgs.setdefault(t, []).append(
                    (m, info)), qos, any_hash=False)
            wait_for(lambda: len(got_msgs) == 3, 15, what="the latched messages")
            grid_msg, info = got_msgs["/aisdf/occupancy_grid"][-1]
            ts = rz.open_typestore("jazzy")
            assert info.key.endswith("nav_msgs::msg::dds_::OccupancyGrid_/" + ts.hash_rihs01("nav_msgs/msg/OccupancyGrid"))
            assert info.attachment is not None and info.attachment.sequence_number == 1
            np.testing.assert_array_equal(grid_msg.data, np.ascontiguousarray(got.T).reshape(-1))
            assert grid_msg.info.resolution == pytest.approx(0.05) and grid_msg.header.frame_id == "map"
            markers = got_msgs["/aisdf/surfels"][-1][0].markers
            assert len(markers) == len(smap) + 1 and markers[0].action == 3 and {m.type for m in markers[1:]} == {1}
            mesh = got_msgs["/aisdf/mesh"][-1][0]
            assert mesh.type == 11 and len(mesh.points) > 300 and len(mesh.points) % 3 == 0
            # The ESDF slice: one point per observed column, its clearance as the intensity.
            cloud = []
            listener.create_subscription("/aisdf/esdf_pointcloud", "sensor_msgs/msg/PointCloud2",
                                         lambda m, i: cloud.append(m), rz.QoS(depth=1), any_hash=False)
            time.sleep(0.5)
            out.version = None  # as if the map moved on: the grid and the slice go out again
            out.tick()
            wait_for(lambda: cloud, 10, what="the ESDF slice")
            assert cloud[-1].width == observed.sum() and [f.name for f in cloud[-1].fields] == ["x", "y", "z",
                                                                                                 "intensity"]

            # The distance window service: the box's grid, as the query service answers it.
            interfaces.register_interfaces(listener.typestore)
            client = listener.create_client("/aisdf/get_distance_window", interfaces.GET_DISTANCE_WINDOW)
            assert client.wait_for_service(10)
            Req = listener.typestore.types[interfaces.request_type(interfaces.GET_DISTANCE_WINDOW)]
            P = listener.typestore.types["geometry_msgs/msg/Point"]
            V = listener.typestore.types["geometry_msgs/msg/Vector3"]
            c = np.asarray(smap.surfels["center"]).mean(0)
            rep = client.call(Req(aabb_min_m=P(x=c[0], y=c[1], z=c[2]), aabb_size_m=V(x=0.4, y=0.3, z=0.2),
                                  voxel_size_m=0.1, gradient=True), timeout=30)
            assert rep.success, rep.message
            dims = [(d.label, d.size) for d in rep.esdf_and_gradients.layout.dim]
            assert dims == [("x", 5), ("y", 4), ("z", 3), ("channel", 4)] and rep.map_version == 1
            # ROS's layout: dim[i].stride is the product of the sizes from i on
            assert [d.stride for d in rep.esdf_and_gradients.layout.dim] == [240, 48, 12, 4]
            # a float32 voxel size of 0.05 still gives every sample of a 4 m edge (81)
            line = client.call(Req(aabb_min_m=P(x=c[0], y=c[1], z=c[2]), aabb_size_m=V(x=4.0, y=0.0, z=0.0),
                                   voxel_size_m=0.05, gradient=False), timeout=30)
            assert line.success and [d.size for d in line.esdf_and_gradients.layout.dim] == [81, 1, 1]
            arr = np.asarray(rep.esdf_and_gradients.data).reshape(5, 4, 3, 4)
            with SdfClient(NS, st.client_zenoh) as cl:
                ref = cl.box(c, [0.4, 0.3, 0.2], 0.1, gradient=True)
            # (the same box up to the service's float32 voxel size)
            np.testing.assert_allclose(arr[..., 0], ref.grid("sdf"), atol=1e-5)
            np.testing.assert_allclose(arr[..., 1:], ref.grid("gradient"), atol=1e-4)
            assert np.linalg.norm(arr[..., 1:], axis=-1).mean() > 0.5
            bad = client.call(Req(aabb_min_m=P(x=0.0, y=0.0, z=0.0), aabb_size_m=V(x=1.0, y=1.0, z=1.0), voxel_size_m=0.0,
                                  gradient=False), timeout=30)
            assert not bad.success and "bad_request" in bad.message
            # No mapper: save_map says so; the node goes on.
            trig = listener.create_client("/aisdf/save_map", interfaces.TRIGGER)
            assert trig.wait_for_service(10)
            r = trig.call(listener.typestore.types[interfaces.request_type(interfaces.TRIGGER)](), timeout=90)
            assert not r.success and "mapper" in r.message
            assert client.call(Req(aabb_min_m=P(x=c[0], y=c[1], z=c[2]), aabb_size_m=V(x=0.0, y=0.0, z=0.0),
                                   voxel_size_m=0.1, gradient=False),
                               timeout=30).success
            services.close()
            out.close()
        finally:
            for n in (listener, node):
                if n is not None:
                    n.close()
            for x in (ros2, ros, sess, s):
                x.close()





def test_aisdf_ros2_runs_as_a_process_and_stops_cleanly(tmp_path):
    """``aisdf ros2`` as users start it: its node, topics and services appear in the ROS graph
    (before any map exists), and SIGTERM stops it with exit code 0."""
    import signal
    import subprocess
    import sys

    from aisdf.stack import endpoint, free_port

    port = free_port()
    with Stack(services=("query",), namespace=NS, ports={"query": port}) as st:
        p = subprocess.Popen([sys.executable, "-m", "aisdf.cli", "ros2", "--namespace", NS, "--no-multicast-scouting",
                              "--connect", endpoint(port), "--ros-connect", endpoint(port), "--map-dir",
                              str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            with rz.open_ros_session([st.endpoints[0]]) as ros:
                def graph():
                    return {(e.kind, e.topic) for e in rz.discover(ros, 0, 1.0) if e.node_name == "aisdf"}

                wait_for(lambda: len(graph()) >= 8, 60, period=1.0, what="the aisdf node's entities")
                g = graph()
            assert {(rz.PUBLISHER, "/aisdf/occupancy_grid"), (rz.PUBLISHER, "/aisdf/esdf_pointcloud"),
                    (rz.PUBLISHER, "/aisdf/surfels"), (rz.PUBLISHER, "/aisdf/mesh"),
                    (rz.SERVICE, "/aisdf/get_distance_window"), (rz.SERVICE, "/aisdf/save_map"),
                    (rz.SERVICE, "/aisdf/load_map"), (rz.NODE, None)} <= g
            p.send_signal(signal.SIGTERM)
            assert p.wait(30) == 0, p.stdout.read()
        finally:
            if p.poll() is None:
                p.kill()
                p.wait(5)


def test_the_grid_follows_the_submaps_that_changed_and_the_bake_catching_up():
    """Change tracking without the services (a fake session and node, the tiles' sampling
    recorded): tiles are sampled again where a changed submap's box reaches; a grid sampled while
    the bake trailed the index is sampled again once the bake catches up (never stale for good);
    a new epoch starts over."""
    from aisdf.submaps.grid import SubmapGrid

    class Pub:
        def __init__(self):
            self.msgs = []

        def publish(self, m):
            self.msgs.append(m)

    class FakeNode:
        typestore = rz.open_typestore("jazzy")

        def create_publisher(self, *a, **k):
            return Pub()

    class FakeSession:
        def declare_subscriber(self, *a, **k):
            return type("Decl", (), {"undeclare": lambda self: None})()

    out = MapOutputs(Ros2OutputsConfig(namespace=NS), FakeSession(), FakeNode())
    sampled: list = []

    def sample(t):
        sampled.append(t)
        return slices.Slice(np.zeros((64, 64), bool), np.ones((64, 64), bool))

    out.sample_tile = sample
    out.surfel_map = protocol.SurfelMap(1, 0.0, np.array([0, 0, 1.0]), np.zeros((0, 3)), room())
    grid = SubmapGrid(np.eye(3), np.zeros(3), 2.0, 3.0, 0.5).to_msg()

    def index(version, versions, epoch=1):
        return protocol.SubmapIndex(version, 0.0, grid, {k: {"version": v, "step": 1} for k, v in versions.items()},
                                    epoch)

    out.index = index(6, {"0_0_0": 6, "2_0_0": 6})
    assert out.refresh_grid(0.0, (1, 5))  # the bake trails the index: every tile, from the older bake
    every = set(sampled)
    assert len(every) == 6 and out.counts["grids"] == 1
    sampled.clear()
    assert out.refresh_grid(1.0, (1, 6))  # caught up: its submaps' tiles again
    assert set(sampled) == {(0, -1), (0, 0), (-1, -1), (-1, 0), (1, -1), (1, 0)} & every and sampled
    sampled.clear()
    assert not out.refresh_grid(2.0, (1, 6)) and not sampled  # nothing changed
    out.index = index(7, {"0_0_0": 6, "2_0_0": 7})
    assert out.refresh_grid(3.0, (1, 7))
    assert set(sampled) == {(1, -1), (1, 0)}  # only where submap 2_0_0's box (grown) reaches
    sampled.clear()
    out.index = index(8, {"0_0_0": 6, "2_0_0": 7}, epoch=2)
    assert out.refresh_grid(4.0, (2, 8)) and set(sampled) == every  # a new epoch: everything
    sampled.clear()
    out.index = index(9, {"0_0_0": 9, "2_0_0": 7}, epoch=2)
    assert out.refresh_grid(40.0, (2, 9)) and set(sampled) == every  # the periodic refresh (30 s)
    # Surfels that reached the node before the bake holds them (1.19's surfel version of the
    # bake): the tiles sampled then are sampled again once the bake holds them.
    sampled.clear()
    out.surfel_map = protocol.SurfelMap(2, 0.0, np.array([0, 0, 1.0]), np.zeros((0, 3)), room())
    out.index = index(10, {"0_0_0": 10, "2_0_0": 7}, epoch=2)
    assert out.refresh_grid(41.0, (2, 10, 1)) and sampled  # the bake still holds surfel map 1
    first = set(sampled)
    sampled.clear()
    assert out.refresh_grid(42.0, (2, 10, 2)) and set(sampled) == first
    sampled.clear()
    assert not out.refresh_grid(43.0, (2, 10, 2)) and not sampled
