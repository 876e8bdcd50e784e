"""``aisdf bench ros2-out``: what a ROS 2 navigation stack gets from ``aisdf ros2`` while a
building is walked.

The query service and the mapper run as processes over Zenoh on loopback, with their
defaults; a building's walk (``--scene``, ``--keyframes`` at one per ``--period-s``) is
published as a frontend sends it, then the mapper trains ``--after-s`` more. The ROS 2 node
(:class:`aisdf.ros.outputs.MapOutputs`, defaults: 5 cm cells, band 0.1-1.0 m above the floor,
robot radius 0.2 m) runs in this process on its own sessions and ticks at 1 Hz. Every
``--every-s`` the last grid is scored against the grid the building's true SDF gives at the
same samples, on the cells the service says were observed: cells agreeing, true obstacle
cells marked (100), free cells marked as obstacles. Also: each tick's duration, tiles
sampled, the grid's size and the message's bytes.

Prints and writes ``ros2_out.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np

from .. import keys, transport
from ..stack import Stack, wait_for
from .load import Feeder

NS = "aisdf/bench-ros2out"


def score(out, seq) -> dict | None:
    """The node's last grid against the true geometry's at the same samples (observed cells)."""
    from ..ros import slices

    if out.last_grid is None or not out.tiles:
        return None
    cfg = out.cfg
    lo, hi = np.array(min(out.tiles)), np.array(max(out.tiles))
    # the grid published covers the surfel extent's tiles; score the tiles sampled
    obstacle, observed, origin = out.assemble(lo, hi)
    levels = slices.band_levels(cfg.band, cfg.resolution)
    nx, ny = obstacle.shape
    g = np.stack(np.meshgrid(origin[0] + cfg.resolution * np.arange(nx), origin[1] + cfg.resolution * np.arange(ny),
                             levels, indexing="ij"), -1).reshape(-1, 3)
    gt = seq.gt_sdf(out.ground.to_world(g)).reshape(nx, ny, len(levels))
    truth, _ = slices.occupancy((gt < cfg.resolution).any(-1), observed, cfg.resolution, cfg.robot_radius)
    got, _ = slices.occupancy(obstacle, observed, cfg.resolution, cfg.robot_radius)
    t_occ, g_occ = (truth == 100) & observed, (got == 100) & observed
    t_free = (truth == 0) & observed
    return {"cells": int(nx * ny), "observed": int(observed.sum()),
            "agree": float((got == truth)[observed].mean()) if observed.any() else None,
            "obstacles_found": float((g_occ & t_occ).sum() / max(1, t_occ.sum())),
            "free_marked_occupied": float((g_occ & t_free).sum() / max(1, t_free.sum()))}


def run(args, say=print) -> dict:
    from ..ros import rmw_zenoh as rz
    from ..ros.outputs import MapOutputs, Ros2OutputsConfig
    from .scaling_config import resolve
    from .scaling_walk import scene_frames

    seq, frames, _ = scene_frames(args.scene, resolve("full", keyframes=args.keyframes, H=120, W=160, seed=args.seed))
    res: dict = {"scene": args.scene, "keyframes": len(frames), "seed": args.seed, "ticks": [], "scores": []}
    with Stack(services=("query", "mapper"), namespace=NS, args={"mapper": ["--preset", args.preset]},
               log_dir=Path(args.out) / "logs") as st:
        sess = transport.open_session(st.client_zenoh)
        ros = rz.open_ros_session([st.endpoints[0]])
        node = rz.Node(ros, "aisdf")
        out = MapOutputs(Ros2OutputsConfig(namespace=NS, zenoh=st.client_zenoh), sess, node)
        try:
            wait_for(lambda: transport.get_latest(sess, keys.key(NS, "info/mapper"), 1.0), 60, what="the mapper")
            stop = threading.Event()
            mesher = threading.Thread(target=out.mesh_loop, args=(stop,), daemon=True)
            mesher.start()  # as aisdf ros2 runs it
            with Feeder(sess, NS, frames, args.period_s) as feed:
                t0 = time.monotonic()
                end = t0 + len(frames) * args.period_s + args.after_s
                next_score = t0 + args.every_s
                while time.monotonic() < end:
                    tick0 = time.monotonic()
                    tiles0, grids0 = out.counts["tiles"], out.counts["grids"]
                    out.tick(tick0, mesh=False)
                    dt = time.monotonic() - tick0
                    res["ticks"].append({"t": round(tick0 - t0, 2), "s": round(dt, 4),
                                         "tiles": out.counts["tiles"] - tiles0,
                                         "grid": out.counts["grids"] - grids0,
                                         "grid_s": round(out.took.get("grid", 0.0), 3) if out.counts["grids"] > grids0
                                         else None})
                    if time.monotonic() >= next_score:
                        sc = score(out, seq)
                        if sc is not None:
                            sc.update({"t": round(time.monotonic() - t0, 1), "keyframes_sent": feed.sent,
                                       "map_version": out.version[1] if out.version else None})
                            res["scores"].append(sc)
                            say(f"  t {sc['t']:5.0f} s, keyframe {feed.sent:3d}: {sc['observed']:7,d} observed cells, "
                                f"{100 * sc['agree']:.1f} % agree, true obstacles found {100 * sc['obstacles_found']:.1f} %, "
                                f"free cells marked occupied {100 * sc['free_marked_occupied']:.1f} %")
                        next_score += args.every_s
                    time.sleep(max(0.0, 1.0 - (time.monotonic() - tick0)))
            stop.set()
            mesher.join(90)
            grid = out.last_grid
            res["grid_shape"] = None if grid is None else list(grid.shape)
            res["counts"] = dict(out.counts)
            res["mesh_s"] = [round(x, 3) for x in out.mesh_times]
        finally:
            out.close()
            node.close()
            ros.close()
            sess.close()
    return res


def report(res: dict) -> str:
    ticks = [t for t in res["ticks"] if t["grid"]]
    dur = np.array([t["grid_s"] for t in ticks]) if ticks else np.zeros(1)
    mesh = np.array(res.get("mesh_s") or [0.0])
    tiles = np.array([t["tiles"] for t in ticks]) if ticks else np.zeros(1)
    last = res["scores"][-1] if res["scores"] else {}
    lines = [f"ROS 2 outputs while the {res['scene']} walk ({res['keyframes']} keyframes, seed {res['seed']}) is mapped:",
             f"  grids published: {res['counts']['grids']} of {len(res['ticks'])} ticks (1 Hz; the others: no change)",
             f"  a grid (sampling what changed, publishing grid and slice): p50 {np.percentile(dur, 50):.2f} s, "
             f"p95 {np.percentile(dur, 95):.2f} s, max {dur.max():.2f} s; tiles sampled p50 "
             f"{np.percentile(tiles, 50):.0f}, max {tiles.max():.0f} (64 x 64 cells each); the grid "
             f"{res.get('grid_shape')} cells",
             f"  meshes: {len(res.get('mesh_s') or [])} (every 30 s while the map changes, on their own thread): p50 {np.percentile(mesh, 50):.2f} s, max {mesh.max():.2f} s",
             f"  the last grid against the true geometry's: {100 * last.get('agree', float('nan')):.1f} % of "
             f"{last.get('observed', 0):,} observed cells agree; true obstacles found "
             f"{100 * last.get('obstacles_found', float('nan')):.1f} %; free cells marked occupied "
             f"{100 * last.get('free_marked_occupied', float('nan')):.1f} %"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf bench ros2-out", description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="office", help="built-in building (default office; floor: the floor)")
    p.add_argument("--keyframes", type=int, default=120, help="keyframes of the walk (default 120)")
    p.add_argument("--period-s", type=float, default=1.0, help="seconds between keyframes (default 1)")
    p.add_argument("--after-s", type=float, default=60.0, help="seconds after the walk (default 60)")
    p.add_argument("--every-s", type=float, default=20.0, help="seconds between scores (default 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--preset", default="cpu", choices=["auto", "paper", "cpu"])
    p.add_argument("--out", default="runs/bench-ros2-out")
    a = p.parse_args(argv)
    Path(a.out).mkdir(parents=True, exist_ok=True)
    res = run(a)
    text = report(res)
    print(text)
    (Path(a.out) / "ros2_out.json").write_text(json.dumps(res, indent=1))
    (Path(a.out) / "ros2_out.md").write_text(text + "\n")
