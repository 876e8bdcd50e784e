"""``aisdf``: the umbrella command (``demo``, ``view``, ``map``, ``bench``)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from . import __version__


def _demo(args) -> None:
    from .demo import run

    s = run(duration=args.duration, out=args.out, building=args.building, seed=args.seed, preset=args.preset)
    if args.max_error_cm is not None and s.get("sdf_error_cm", 1e9) > args.max_error_cm:
        raise SystemExit(f"SDF error {s.get('sdf_error_cm')} cm is above --max-error-cm {args.max_error_cm}")


def _view(args) -> None:
    from .viewer import main as view_main

    view_main(args)


def _bench_query(args) -> None:
    from .bench.query import report, run

    res = run(out=args.out, sizes=args.sizes, repeats=args.repeats, threads=args.threads, bake_threads=args.bake_threads,
              train_steps=args.train_steps, planners=args.planners, planner_s=args.planner_s, lag_s=args.lag_s,
              n_eval=args.eval_points, mapper=args.mapper, beside_mapper=args.beside_mapper, peer=args.peer)
    print(report(res))


def _bench_scaling(args) -> None:
    from .bench.scaling import main as scaling_main

    scaling_main(args)


def _bench(args) -> None:
    from .bench.suite import main as suite_main

    suite_main(args)


# Benchmarks with their own options: name, module (with main(argv)), what it measures.
TOOLS = [
    ("served", "aisdf.bench.served", "what planners get from the real services over Zenoh while the map grows"),
    ("load", "aisdf.bench.load", "8 planners x 10,000 points with gradients while the mapper trains beside them"),
    ("bake", "aisdf.bench.bake", "the query service's incremental bake against a full bake as a submap map grows"),
    ("rosbag", "aisdf.bench.rosbag", "7-Scenes frames mapped from .mcap, .db3 and ROS 1 recordings against the folder"),
    ("ros2-live", "aisdf.bench.ros2_live", "the live ROS 2 source against the protocol-v1 frontend, real processes"),
    ("parked", "aisdf.bench.parked", "a parked robot's keyframes and memory, and a walk's keyframes, in-process"),
    ("change", "aisdf.bench.change", "a cart moved away, a person crossing, drifting poses corrected, a parked "
     "robot: what the served map says, real processes"),
    ("ros2-out", "aisdf.bench.ros2_out", "what aisdf ros2 publishes (occupancy grid) while a building is walked"),
    ("device", "aisdf.bench.device", "the query engine and both mappers on a GPU against the CPU"),
    ("rooms", "aisdf.bench.rooms", "an Atlanta room at unseen seeds from 20 keyframes: the served answer with and "
     "without the layout prior against 2 and 5 cm voxel maps"),
    ("replicas", "aisdf.bench.replicas", "8 planners x 10,000 points against 1 and 2 query replicas, and one killed "
     "(protocol 1.12), real processes"),
    ("cluster", "aisdf.bench.cluster", "the floor walked by two robots into 1, 2 and 3 mapper shards, one killed, a "
     "fourth joining (protocol 1.14), real processes"),
]


def main(argv: list[str] | None = None) -> None:
    from .mapper import MAPPER_KINDS

    p = argparse.ArgumentParser(prog="aisdf", description="AiSDF: online Atlanta-world neural SDF mapping service.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    p.add_argument("--log-level", default="WARNING", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    sub = p.add_subparsers(dest="cmd", required=True)

    d = sub.add_parser("demo", help="run frontend, mapper and query on the synthetic building, on loopback",
                       description="Starts the three services as processes on loopback, maps the built-in synthetic "
                       "building, shows live progress and the SDF error against ground truth, runs a planner "
                       "example, and writes a mesh, a summary and a rerun recording (.rrd).")
    d.add_argument("--duration", type=float, default=180.0, help="seconds to run (default 180)")
    d.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    d.add_argument("--building", default="office",
                   help="synthetic building (default office; floor: the multi-room floor, --duration 270 walks "
                   "all of it)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--preset", default="auto", choices=["auto", "paper", "cpu"])
    d.add_argument("--max-error-cm", type=float, help="exit non-zero if the final SDF error is above this")
    d.set_defaults(fn=_demo)

    v = sub.add_parser("view", help="live rerun view of a running stack (keyframes, surfels, Atlanta frame, mesh)",
                       description="Connects to a running stack (the services' Zenoh flags and namespace) and shows "
                       "in rerun, live: keyframes (depth, camera frustum, path), the surfel map coloured by Atlanta "
                       "direction, the Atlanta frame and the mesh refreshed every --mesh-period seconds. Spawns the "
                       "rerun viewer; --save FILE.rrd records to a file instead. Needs the extra aisdf[viewer].")
    from .viewer import add_arguments as _view_arguments

    _view_arguments(v)
    v.set_defaults(fn=_view)

    m = sub.add_parser("map", help="save, load and export the map of a running stack (aisdf map save|load|export)",
                       description="Map files of a running stack: `save DIR`, `load DIR`, `export --mesh/--surfels`.")
    from .mapcli import add_arguments as _map_arguments

    _map_arguments(m)

    r2 = sub.add_parser("ros2", help="the map for ROS 2 over rmw_zenoh: occupancy grid, ESDF slice, markers, "
                        "services (`aisdf ros2 --help`: its options)", add_help=False, prefix_chars="+")
    r2.add_argument("argv", nargs=argparse.REMAINDER)
    r2.set_defaults(fn=lambda a: sys.exit(importlib.import_module("aisdf.ros.outputs_main").cli(a.argv)))

    b = sub.add_parser("bench", help="benchmarks: `aisdf bench` = the paper's tables; `aisdf bench query`",
                       description="Without a subcommand: the paper's Tables I-III side by side on the same frames "
                       "(Voxblox-like TSDF/ESDF map, iSDF, AiSDF without and with the explicit map), with error over "
                       "time, SDF slices, meshes and the resolved configuration in a results folder. "
                       "`--quick` is the CI-sized profile.")
    from .bench.suite import add_arguments as _bench_arguments

    _bench_arguments(b)
    bsub = b.add_subparsers(dest="bench_cmd")
    q = bsub.add_parser("query", help="query/sdf on the demo building's map: the baked field beside the network",
                        description="Trains (or reuses from --out) the demo building's map, then measures the bake "
                        "(time, memory), its accuracy against the network and the truth on the demo's evaluation "
                        "points, latency in-process and over Zenoh (baked and network, with and without "
                        "gradients), the lag behind 1 Hz weights, and concurrent planners. Prints the tables; "
                        "writes query.json.")
    q.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    q.add_argument("--repeats", type=int, default=20)
    q.add_argument("--threads", type=int, help="torch threads per evaluation, in the service and in-process "
                   "(default 1, the service's)")
    q.add_argument("--bake-threads", type=int, default=2, help="threads evaluating the network while baking")
    q.add_argument("--mapper", choices=list(MAPPER_KINDS), default="submaps",
                   help="the map's mapper: a network per submap with measured points (the service's default; "
                   "fused answers are protocol 1.4's) or one network (with its measured points too, protocol 1.5)")
    q.add_argument("--train-steps", type=int, help="training steps of the demo map (default 1200 with submaps, "
                   "900 with one network: about what the demo's mapper makes in 180 s)")
    q.add_argument("--planners", type=int, default=8)
    q.add_argument("--planner-s", type=float, default=60.0, help="seconds of the concurrent-planners run")
    q.add_argument("--no-peer", dest="peer", action="store_false",
                   help="skip the voxel map beside it (5 cm and 2 cm: accuracy, lookup, update, memory)")
    q.add_argument("--no-mapper", dest="beside_mapper", action="store_false",
                   help="the concurrent planners without a mapper training beside them (the map above, published "
                   "once); by default the mapper trains the office walk on this machine meanwhile (aisdf bench load)")
    q.add_argument("--lag-s", type=float, default=30.0, help="seconds of the 1 Hz lag run")
    q.add_argument("--eval-points", type=int, default=200_000)
    q.add_argument("--out", default="runs/bench-query", help="results and the cached map (default runs/bench-query)")
    q.set_defaults(fn=_bench_query)
    sc = bsub.add_parser("scaling", help="one room to a floor: one network vs submaps",
                         description="Walks the office and the floor at one keyframe a second of wall time (frames "
                         "rendered up front, the mapper stepping in between), then trains 60 s more; per mapper: "
                         "step time, mapper memory, bytes published per second, whole-map SDF error at the end of "
                         "the walk and 60 s later, each floor room's error just after its visit and at the end, "
                         "and the scaling criteria. Prints the tables; writes scaling.json and scaling.md.")
    from .bench.scaling import add_arguments as _scaling_arguments

    _scaling_arguments(sc)
    sc.set_defaults(fn=_bench_scaling)
    for name, module, text in TOOLS:
        t = bsub.add_parser(name, help=text, add_help=False, prefix_chars="+",
                            description=f"{text} (`aisdf bench {name} --help`: its options)")
        t.add_argument("argv", nargs=argparse.REMAINDER)
        t.set_defaults(fn=lambda a, module=module: importlib.import_module(module).main(a.argv))
    b.set_defaults(fn=_bench)

    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    args.fn(args)


if __name__ == "__main__":
    main()
