"""``aisdf demo``: the whole stack on the built-in synthetic building, on loopback.

Starts frontend, mapper and query as separate processes, shows live progress (frames
sent, keyframes, training steps, map version, SDF error against the synthetic ground
truth), runs a small planner example, and writes a mesh, a summary and a rerun
recording at the end. Ctrl-C stops everything cleanly.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import keys, protocol, transport
from .client import SdfClient
from .collision import chomp_cost
from .stack import Stack, wait_for

log = logging.getLogger("aisdf.demo")


class NullRecorder:
    """Records nothing: rerun-sdk (the ``aisdf[viewer]`` extra) is not installed."""

    def keyframe(self, kf) -> None: ...

    def mesh(self, m) -> None: ...

    def surfels(self, s) -> None: ...

    def close(self) -> None: ...


def open_recorder(path: Path):
    try:
        return Recorder(path)
    except ImportError:
        log.warning("rerun-sdk is not installed (pip install 'aisdf[viewer]'): no recording in %s", path)
        return NullRecorder()


class Recorder:
    """The rerun recording: keyframes' depth and camera poses, the mesh as it grows."""

    def __init__(self, path: Path):
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream("aisdf_demo")
        self.rec.save(str(path))
        self.t0 = time.monotonic()
        self.n = 0

    def _time(self) -> None:
        self.rec.set_time("wall", duration=time.monotonic() - self.t0)

    def keyframe(self, kf: protocol.Keyframe) -> None:
        rr = self.rr
        self._time()
        H, W = kf.depth.shape
        self.rec.log("world/camera", rr.Transform3D(translation=kf.T_WC[:3, 3], mat3x3=kf.T_WC[:3, :3]))
        self.rec.log("world/camera/image", rr.Pinhole(image_from_camera=kf.K, width=W, height=H))
        self.rec.log("world/camera/image/depth", rr.DepthImage(kf.depth_m(), meter=1.0))
        self.rec.log(f"world/keyframes/{kf.frame_id}", rr.Points3D([kf.T_WC[:3, 3]], radii=0.03))
        self.n += 1

    def mesh(self, m: protocol.MeshReply) -> None:
        self._time()
        self.rec.log("world/mesh", self.rr.Mesh3D(vertex_positions=m.vertices, triangle_indices=m.faces))

    def surfels(self, s) -> None:
        if s is None or len(s) == 0:
            return
        self._time()
        c = s.corners()
        strips = [np.concatenate([q, q[:1]]) for q in c]
        self.rec.log("world/surfels", self.rr.LineStrips3D(strips))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect() if hasattr(self.rec, "disconnect") else None


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
        preset: str = "auto", n_eval: int = 20_000, quiet: bool = False) -> dict:
    from .synthetic import SyntheticSequence

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fps = 30.0
    stream_s = max(10.0, 0.75 * duration)  # the camera path ends before the demo does
    n_frames = int(stream_s * fps)
    seq = SyntheticSequence(building=building, n_frames=n_frames, fps=fps, seed=seed)
    ns = "aisdf/demo"
    stack = Stack(namespace=ns, log_dir=out / "logs", args={
        "frontend": ["--building", building, "--set", f"seed={seed}", "--set", f"n_frames={n_frames}",
                     "--set", "linger=true"],
        "mapper": ["--preset", preset],
        "query": [],
    })
    stop = threading.Event()
    prev = signal.signal(signal.SIGINT, lambda *_: stop.set())
    rng = np.random.default_rng(seed)
    history, summary = [], {}
    recorder = open_recorder(out / "demo.rrd")
    t0 = time.monotonic()
    tty = sys.stdout.isatty()
    if not quiet:
        print(f"AiSDF demo: frontend, mapper and query on loopback, synthetic '{building}' building, "
              f"{duration:.0f} s; logs in {out / 'logs'}")
    try:
        stack.start(["query", "mapper"])
        with SdfClient(ns, zenoh=stack.client_zenoh, timeout=30.0) as client:
            session = client._session
            kf_sub = session.declare_subscriber(
                keys.key(ns, keys.KEYFRAMES),
                lambda s: recorder.keyframe(protocol.Keyframe.from_msg(protocol.unpack(s.payload.to_bytes()))))
            wait_for(lambda: transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0), 60, what="the mapper")
            stack.start(["frontend"])
            t0 = time.monotonic()
            last_eval = last_mesh = 0.0
            while not stop.is_set() and time.monotonic() - t0 < duration:
                stop.wait(1.0)
                for name, p in stack.procs.items():
                    if p.poll() is not None:
                        raise RuntimeError(f"{name} exited with {p.returncode}; see {out / 'logs' / (name + '.log')}")
                el = time.monotonic() - t0
                fi = transport.get_latest(session, keys.key(ns, "info/frontend"), 1.0) or {}
                mi = transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0) or {}
                qi = transport.get_latest(session, keys.key(ns, "info/query"), 1.0) or {}
                row = {"t": round(el, 1), "frames": fi.get("frames", 0), "keyframes": fi.get("keyframes", 0),
                       "steps": mi.get("steps", 0), "map_version": mi.get("version", 0),
                       "baked_version": qi.get("baked_version"), "answer_lag_s": (qi.get("lag") or {}).get("behind_s")}
                if row["map_version"] and el - last_eval >= 10:
                    pts = eval_points_from(seq, row["frames"], n_eval, rng)
                    r = client.query(pts)
                    row["sdf_error_cm"] = round(100 * float(np.mean(np.abs(r.sdf - seq.gt_sdf(pts)))), 2)
                    last_eval = el
                if row["map_version"] and el - last_mesh >= 30:
                    try:
                        recorder.mesh(client.mesh(0.08))
                        recorder.surfels(client.surfels(1.0))
                    except (protocol.ProtocolError, TimeoutError) as e:
                        log.info("mesh not ready: %s", e)
                    last_mesh = el
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
            summary = finish(client, seq, out, recorder, rng, history, time.monotonic() - t0, quiet)
            kf_sub.undeclare()
    finally:
        signal.signal(signal.SIGINT, prev)
        stack.stop()
        recorder.close()
    return summary


def finish(client, seq, out: Path, recorder, rng, history, elapsed, quiet) -> dict:
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
    summary = {"elapsed_s": round(elapsed, 1), "frames": frames_seen, "history": history,
               "answer_lag_s": {"max": max(lags), "mean": round(float(np.mean(lags)), 3)} if lags else None,
               "sdf_error_cm": errs["fused"], "sdf_error_implicit_cm": errs["implicit"],
               "sdf_error_fused_network_cm": errs["fused_exact"], "answered_baked": errs["fused_baked"],
               "answered_version": errs["fused_version"], "newest_version": errs["fused_exact_version"],
               "eval_points": len(pts), "planner": planner_example(client, seq)}
    try:
        m = client.mesh(0.05)
        recorder.mesh(m)
        import trimesh

        trimesh.Trimesh(m.vertices, m.faces, process=False).export(out / "mesh.ply")
        summary["mesh"] = {"vertices": len(m.vertices), "faces": len(m.faces), "path": str(out / "mesh.ply")}
    except (protocol.ProtocolError, TimeoutError) as e:
        summary["mesh"] = {"error": str(e)}
    s = client.surfels(2.0)
    recorder.surfels(s)
    summary["surfels"] = 0 if s is None else len(s)
    summary["recording"] = str(out / "demo.rrd")
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
            print(f"answers trailed the newest weights by {summary['answer_lag_s']['mean']:.2f} s on average, "
                  f"{summary['answer_lag_s']['max']:.2f} s at most (the bake of each new map)")
        print(f"wrote {out / 'summary.json'}, {out / 'demo.rrd'}")
    return summary
