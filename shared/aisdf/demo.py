"""``aisdf demo``: the whole stack on the built-in synthetic building, on loopback.

Starts frontend, mapper and query as separate processes, shows live progress (frames
sent, keyframes, training steps, map version, SDF error against the synthetic ground
truth), runs a small planner example, and writes a mesh and a summary at the end. The
live viewer (``aisdf view --save``, a fourth process; needs the ``aisdf[viewer]`` extra)
records the run as it goes. Ctrl-C or SIGTERM (``timeout``, ``kill``, a supervisor) stops
everything cleanly: the services run in sessions of their own, so they would otherwise be
left running; the final evaluation and mesh are written if a map had been published.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import keys, protocol, transport
from .client import MapArrivals, SdfClient
from .collision import chomp_cost
from .config import PARENT_ENV
from .stack import Stack, endpoint, free_port, wait_for

log = logging.getLogger("aisdf.demo")


def rerun_installed() -> bool:
    try:
        import rerun  # noqa: F401
    except ImportError:
        return False
    return True


def start_viewer(stack: Stack, port: int, path: Path, log_dir: Path, mesh_period_s: float,
                 mesh_resolution: float) -> subprocess.Popen:
    """``aisdf view --save path`` as a process on the stack's loopback endpoints (it listens on ``port``,
    which the frontend connects to, so the viewer sees every keyframe from the first)."""
    cmd = [sys.executable, "-m", "aisdf.cli", "view", "--save", str(path), "--namespace", stack.namespace,
           "--no-multicast-scouting", "--listen", endpoint(port), "--mesh-period", str(mesh_period_s),
           "--mesh-resolution", str(mesh_resolution)]
    for e in stack.endpoints:
        cmd += ["--connect", e]
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / "viewer.log", "w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())})


def stop_viewer(p: subprocess.Popen | None, timeout: float = 30.0) -> int | None:
    """SIGTERM: the viewer records what it has queued, flushes the recording and closes its session."""
    if p is None:
        return None
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("the viewer did not stop within %.0f s; killed (the recording may be cut short)", timeout)
            p.kill()
            p.wait(5)
    return p.returncode


def viewer_up(session, namespace: str) -> bool:
    for reply in session.liveliness().get(keys.status_key(namespace, "viewer", "*"), timeout=1.0):
        if reply.ok is not None:
            return True
    return False


def answer_lag(client, seq, row: dict, published, rng) -> dict:
    """A planner's request of 1,000 points now: how far its answer trails the newest map
    (seconds since a map newer than the reply's arrived, ``published``: a
    ``client.MapArrivals`` subscriber; 0 when the reply is of the newest), and the
    reply's ``map_age_s`` (protocol 1.7)."""
    now = time.monotonic()
    r = client.query(eval_points_from(seq, row["frames"], 1000, rng))
    return {"answer_version": r.map_version, "answer_lag_s": round(published.lag(r.map_version, now), 3),
            "map_age_s": r.map_age_s}


def eval_points_from(seq, n_frames_seen: int, n_points: int, rng) -> np.ndarray:
    from .metrics import eval_points

    frames = [seq.frame(i) for i in range(0, max(1, min(n_frames_seen, len(seq))), 5)]
    return eval_points(frames, n_points=n_points, every=1, rng=rng, far_margin=0.1)


def planner_example(client: SdfClient, seq, epsilon: float = 1.0) -> dict:
    """A candidate straight path between two camera positions: collision cost along it."""
    a, b = seq.poses[0][:3, 3], seq.poses[len(seq) // 2][:3, 3]
    path = a + np.linspace(0, 1, 200)[:, None] * (b - a)
    r = client.query(path, gradient=True, collision_epsilon=epsilon)
    gt = seq.gt_sdf(path)
    return {"points": len(path), "epsilon": epsilon, "cost": float(r.collision.sum()),
            "cost_truth": float(chomp_cost(gt, epsilon).sum()), "min_clearance": float(r.sdf.min()),
            "min_clearance_truth": float(gt.min()), "map_version": r.map_version}


def run(duration: float = 180.0, out: str | Path = "runs/demo", building: str = "office", seed: int = 0,
        preset: str = "auto", n_eval: int = 20_000, quiet: bool = False, mesh_period_s: float = 15.0,
        mesh_resolution: float = 0.1) -> dict:
    """The demo. The recording's meshes (``mesh_period_s``, ``mesh_resolution``) cost the query
    service about what the demo's own meshes did before the viewer (0.08 m every 30 s)."""
    from .synthetic import SyntheticSequence

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fps = 30.0
    stream_s = max(10.0, 0.75 * duration)  # the camera path ends before the demo does
    n_frames = int(stream_s * fps)
    seq = SyntheticSequence(building=building, n_frames=n_frames, fps=fps, seed=seed)
    ns = "aisdf/demo"
    recording = out / "demo.rrd" if rerun_installed() else None
    if recording is None:
        log.warning("rerun-sdk is not installed (pip install 'aisdf[viewer]'): no recording in %s", out / "demo.rrd")
    viewer_port = free_port()
    stack = Stack(namespace=ns, log_dir=out / "logs", args={
        "frontend": ["--building", building, "--set", f"seed={seed}", "--set", f"n_frames={n_frames}",
                     "--set", "linger=true"] + (["--connect", endpoint(viewer_port)] if recording else []),
        "mapper": ["--preset", preset],
        "query": [],
    })
    viewer = None
    stop = threading.Event()
    prev = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    rng = np.random.default_rng(seed)
    history, summary = [], {}
    t0 = time.monotonic()
    tty = sys.stdout.isatty()
    if not quiet:
        print(f"AiSDF demo: frontend, mapper and query on loopback, synthetic '{building}' building, "
              f"{duration:.0f} s; logs in {out / 'logs'}")
    try:
        stack.start(["query", "mapper"])
        if recording:  # `aisdf view --save`, the live viewer, records the run
            viewer = start_viewer(stack, viewer_port, recording, out / "logs", mesh_period_s, mesh_resolution)
        with SdfClient(ns, zenoh=stack.client_zenoh, timeout=30.0) as client:
            session = client._session
            wait_for(lambda: stop.is_set() or transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0), 60,
                     what="the mapper")
            if viewer is not None:
                wait_for(lambda: stop.is_set() or viewer.poll() is not None or viewer_up(session, ns), 60,
                         what="the viewer")
            if not stop.is_set():
                stack.start(["frontend"])
            t0 = time.monotonic()
            last_eval = 0.0
            published = MapArrivals(session, ns)  # when each map version arrived
            while not stop.is_set() and time.monotonic() - t0 < duration:
                stop.wait(1.0)
                for name, p in stack.procs.items():
                    if p.poll() is not None:
                        raise RuntimeError(f"{name} exited with {p.returncode}; see {out / 'logs' / (name + '.log')}")
                if viewer is not None and viewer.poll() is not None and recording is not None:
                    log.warning("the viewer exited with %s (see %s): the recording stops there", viewer.returncode,
                                out / "logs" / "viewer.log")
                    recording = None
                el = time.monotonic() - t0
                fi = transport.get_latest(session, keys.key(ns, "info/frontend"), 1.0) or {}
                mi = transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0) or {}
                qi = transport.get_latest(session, keys.key(ns, "info/query"), 1.0) or {}
                row = {"t": round(el, 1), "frames": fi.get("frames", 0), "keyframes": fi.get("keyframes", 0),
                       "steps": mi.get("steps", 0), "map_version": mi.get("version", 0),
                       "baked_version": qi.get("baked_version"),
                       "bake_lag_s": (qi.get("lag") or {}).get("bake_behind_s")}
                if row["map_version"]:
                    row.update(answer_lag(client, seq, row, published, rng))
                if row["map_version"] and el - last_eval >= 10:
                    pts = eval_points_from(seq, row["frames"], n_eval, rng)
                    r = client.query(pts)
                    row["sdf_error_cm"] = round(100 * float(np.mean(np.abs(r.sdf - seq.gt_sdf(pts)))), 2)
                    last_eval = el
                history.append(row)
                if not quiet and (tty or "sdf_error_cm" in row):
                    err = f"{row['sdf_error_cm']:6.2f} cm" if "sdf_error_cm" in row else "   ...   "
                    line = (f"[{el:5.0f}/{duration:.0f} s] frames {row['frames']:5d}  keyframes {row['keyframes']:4d}  "
                            f"steps {row['steps']:6d}  map v{row['map_version']:<5d} baked v{row['baked_version'] or 0:<5d} "
                            f"SDF error {err}")
                    # On a terminal one line is redrawn; in a log, a line per evaluation.
                    sys.stdout.write(f"\r{line}" if tty else f"{line}\n")
                    sys.stdout.flush()
            if not quiet and tty:
                print()
            # The recording covers the live run; the final evaluation and mesh do not wait behind its meshes.
            if stop_viewer(viewer) not in (None, 0):
                log.warning("the viewer exited with %s; see %s", viewer.returncode, out / "logs" / "viewer.log")
            if any(h["map_version"] for h in history):
                summary = finish(client, seq, out, recording, rng, history, time.monotonic() - t0, quiet)
            elif not quiet:
                print("stopped before the mapper published a map: no evaluation")
    finally:
        for sig, handler in prev.items():
            signal.signal(sig, handler)
        stop_viewer(viewer)
        stack.stop()
    if summary and not quiet:
        print(f"wrote {out / 'summary.json'}" + (f", {summary['recording']}" if summary.get("recording") else ""))
    return summary


def finish(client, seq, out: Path, recording: Path | None, rng, history, elapsed, quiet) -> dict:
    frames_seen = max([h["frames"] for h in history] + [1])
    pts = eval_points_from(seq, frames_seen, 200_000, rng)
    gt = seq.gt_sdf(pts)
    errs = {}
    for name, src, exact in (("fused", "fused", False), ("fused_exact", "fused", True), ("implicit", "implicit", True)):
        r = client.query(pts, source=src, exact=exact)
        errs[name] = round(100 * float(np.mean(np.abs(r.sdf - gt))), 2)
        errs[name + "_baked"] = r.baked
        errs[name + "_version"] = r.map_version
    lags = [h["answer_lag_s"] for h in history if h.get("answer_lag_s") is not None]
    bake_lags = [h["bake_lag_s"] for h in history if h.get("bake_lag_s") is not None]
    summary = {"elapsed_s": round(elapsed, 1), "frames": frames_seen, "history": history,
               "answer_lag_s": {"max": max(lags), "mean": round(float(np.mean(lags)), 3)} if lags else None,
               "bake_lag_s": {"max": max(bake_lags), "mean": round(float(np.mean(bake_lags)), 3)} if bake_lags else None,
               "sdf_error_cm": errs["fused"], "sdf_error_implicit_cm": errs["implicit"],
               "sdf_error_fused_network_cm": errs["fused_exact"], "answered_baked": errs["fused_baked"],
               "answered_version": errs["fused_version"], "newest_version": errs["fused_exact_version"],
               "eval_points": len(pts), "planner": planner_example(client, seq)}
    try:
        # Generous: on a busy machine the query service may still be computing the viewer's last mesh.
        m = client.mesh(0.05, timeout=180.0)
        import trimesh

        trimesh.Trimesh(m.vertices, m.faces, process=False).export(out / "mesh.ply")
        summary["mesh"] = {"vertices": len(m.vertices), "faces": len(m.faces), "path": str(out / "mesh.ply")}
    except (protocol.ProtocolError, TimeoutError) as e:
        summary["mesh"] = {"error": str(e)}
    s = client.surfel_map(2.0)
    summary["surfels"] = 0 if s is None else len(s)
    summary["recording"] = str(recording) if recording else None
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if not quiet:
        p = summary["planner"]
        print(f"SDF error (iSDF protocol, {len(pts)} points along seen rays): {errs['fused']:.2f} cm fused "
              f"({'baked field' if errs['fused_baked'] else 'network'}, map v{errs['fused_version']}; "
              f"{errs['fused_exact']:.2f} cm fused from the network of the newest map v{errs['fused_exact_version']}), "
              f"{errs['implicit']:.2f} cm network alone")
        print(f"planner: path of {p['points']} points, collision cost {p['cost']:.2f} (truth {p['cost_truth']:.2f}), "
              f"min clearance {p['min_clearance']:.2f} m (truth {p['min_clearance_truth']:.2f} m)")
        print(f"surfels: {summary['surfels']}; mesh: {summary['mesh']}")
        if summary["answer_lag_s"]:
            bl = summary["bake_lag_s"] or {"mean": float("nan"), "max": float("nan")}
            print(f"answers trailed the newest weights by {summary['answer_lag_s']['mean']:.2f} s on average, "
                  f"{summary['answer_lag_s']['max']:.2f} s at most (a planner's request every second; the bake "
                  f"trailed by {bl['mean']:.2f} s on average, {bl['max']:.2f} s at most)")
    return summary
