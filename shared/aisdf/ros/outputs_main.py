"""``aisdf ros2``: the ROS 2 node of :mod:`aisdf.ros.outputs` (topics) and
:mod:`aisdf.ros.outputs_services` (services) as a process: its sessions, its settings from a
file, the environment and the command line, and a clean stop on SIGINT/SIGTERM."""

from __future__ import annotations

import threading

from .. import transport
from . import rmw_zenoh as rz
from .outputs import MapOutputs, Ros2OutputsConfig, log
from .outputs_services import MapServices


def main(cfg: Ros2OutputsConfig, stop: threading.Event | None = None) -> None:
    stop = stop or threading.Event()
    with transport.open_session(cfg.zenoh) as session, \
            rz.open_ros_session(cfg.ros_connect, str(cfg.ros_zenoh_config) if cfg.ros_zenoh_config else None) as ros:
        node = rz.Node(ros, cfg.node_name, cfg.ros_namespace, cfg.domain_id, cfg.distro)
        out = MapOutputs(cfg, session, node)
        services = MapServices(cfg, session, node)
        log.info("ROS 2 node %s%s up on domain %d (%s); map frame %s", cfg.ros_namespace.rstrip("/") + "/",
                 cfg.node_name, cfg.domain_id, cfg.distro, cfg.frame_id)
        try:
            out.run(stop)
        finally:
            out.close()
            services.close()
            node.close()


def cli(argv: list[str] | None = None) -> int:
    import argparse

    from ..config import add_common_args, config_from_args, service_setup

    p = argparse.ArgumentParser(prog="aisdf ros2", description="the map for ROS 2 over rmw_zenoh: occupancy grid, "
                                "ESDF slice, surfel markers and mesh topics; distance window, save and load services")
    add_common_args(p)
    r = p.add_argument_group("ROS 2 side (any field with --set)")
    r.add_argument("--ros-connect", action="append", metavar="ENDPOINT",
                   help=f"Zenoh router of the ROS 2 network (default {rz.DEFAULT_ROUTER}, rmw_zenoh's)")
    r.add_argument("--ros-zenoh-config", metavar="FILE", help="Zenoh session file for the ROS side")
    r.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default $ROS_DOMAIN_ID or 0)")
    r.add_argument("--distro", help="humble, jazzy (default), ...: message definitions and type hashes")
    r.add_argument("--node-name", help="the node's name (default aisdf): topics /<name>/occupancy_grid, ...")
    r.add_argument("--ros-namespace", help="the node's namespace (default /)")
    r.add_argument("--frame-id", help="the fixed frame of the keyframes' poses (default map)")
    r.add_argument("--resolution", type=float, help="grid cell, metres (default 0.05)")
    r.add_argument("--band", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="heights above the floor sliced, metres (default 0.1 1.0)")
    r.add_argument("--robot-radius", type=float, help="occupied where the clearance is below it (default 0.2)")
    r.add_argument("--rate", type=float, help="grid refreshes per second (default 1)")
    r.add_argument("--map-dir", help="where /aisdf/save_map writes and /aisdf/load_map reads (default maps)")
    a = p.parse_args(argv)
    cfg = config_from_args(Ros2OutputsConfig, a, {
        "ros_connect": a.ros_connect, "ros_zenoh_config": a.ros_zenoh_config, "domain_id": a.domain_id,
        "distro": a.distro, "node_name": a.node_name, "ros_namespace": a.ros_namespace, "frame_id": a.frame_id,
        "resolution": a.resolution, "band": a.band, "robot_radius": a.robot_radius, "rate_hz": a.rate,
        "map_dir": a.map_dir})
    stop = service_setup(cfg, "ros2")
    main(cfg, stop)
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
