"""``aisdf bench ros2-live``: the live ROS 2 source against the protocol-v1 frontend, on the
same synthetic frames.

    aisdf bench ros2-live                                  # 300 frames, office, 160x120
    aisdf bench ros2-live --n-frames 900 --train-s 90

Both paths run at once (``--sequential``: one after the other) as real processes over real
Zenoh on loopback (explicit endpoints, multicast scouting off), each with its own
``aisdf-mapper``:

* **protocol v1**: ``aisdf-frontend`` (the built-in synthetic source) -> ``keyframes``;
* **ROS 2**: ``python -m aisdf.ros.replay`` (a ROS 2 robot after rmw_zenoh's design: depth
  Image + CameraInfo, ``/tf`` map->odom->base_link, ``/tf_static`` base_link->camera_link->
  optical frame, transient local) on a ROS-side Zenoh router (``aisdf-router``), and
  ``aisdf-frontend --source ros2 --ros-connect <router>`` -> ``keyframes``.

A tap on each AiSDF network records the keyframes the mapper receives. It prints: whether the
two paths selected the same keyframes and how far apart their arrays are; the live mappers'
SDF error (their network after the stream plus ``--train-s`` seconds, and the mean over maps
taken every 3 s in the second half of that time, evaluated on iSDF-protocol points against
the building's exact SDF; timing-dependent: a live mapper trains as fast as the machine lets
it, and a map's error swings between snapshots); and the same-training error (each path's keyframes trained in-process
with the same seed and step schedule), the fair comparison; the ROS 2 path is expected within
1.1x of protocol v1's error.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from .. import keys, protocol, transport
from ..config import PARENT_ENV
from ..stack import Stack, endpoint, free_port, wait_for

MAPPER_ARGS = ["--preset", "cpu"]


def router_command(port: int) -> list[str]:
    return [sys.executable, "-c", "from aisdf.ops import router_cli; router_cli()", "--listen", endpoint(port),
            "--no-multicast-scouting", "--namespace", "ros"]


def replay_command(port: int, n_frames: int, width: int, height: int, building: str = "office", seed: int = 0,
                   extra: list[str] | None = None) -> list[str]:
    return [sys.executable, "-m", "aisdf.ros.replay", "--connect", endpoint(port), "--building", building,
            "--seed", str(seed), "--n-frames", str(n_frames), "--width", str(width), "--height", str(height),
            *(extra or [])]


def popen(cmd: list[str], log_path: Path | None):
    out = open(log_path, "w") if log_path else subprocess.DEVNULL  # noqa: SIM115 - closed by the caller
    # the router (a service) stops if this process dies (aisdf.config.service_setup)
    env = {"OMP_NUM_THREADS": "1", **os.environ, "PYTHONUNBUFFERED": "1", PARENT_ENV: str(os.getpid())}
    return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True), out


def stop_proc(p, out) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    if out not in (None, subprocess.DEVNULL):
        out.close()


class KeyframeTap:
    """Records every keyframe put on ``<ns>/keyframes`` (a resent one once)."""

    def __init__(self, session, namespace: str):
        self.keyframes: dict[int, protocol.Keyframe] = {}
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(keys.key(namespace, keys.KEYFRAMES), self._on)

    def _on(self, sample) -> None:
        kf = protocol.Keyframe.from_msg(protocol.unpack(transport.payload_bytes(sample.payload)))
        with self.lock:
            self.keyframes.setdefault(kf.frame_id, kf)

    def sorted(self) -> list[protocol.Keyframe]:
        with self.lock:
            return [self.keyframes[k] for k in sorted(self.keyframes)]

    def close(self) -> None:
        self.sub.undeclare()


def settled(session, ns: str):
    fi = transport.get_latest(session, keys.key(ns, "info/frontend"), 2.0)
    mi = transport.get_latest(session, keys.key(ns, "info/mapper"), 2.0)
    if fi and mi and fi.get("done") and fi.get("pending") == 0 and mi.get("pending", 0) == 0:
        return fi, mi
    return None


def run_path(kind: str, n_frames: int, width: int, height: int, train_s: float = 0.0, building: str = "office",
             seed: int = 0, mapper_args: list[str] | None = None, log_dir: Path | None = None,
             garbage_after: int | None = None, timeout: float = 180.0, sample_s: float = 3.0) -> dict:
    """One path (``synthetic``: protocol v1 frontend; ``ros2``: replay robot + ros2 source) with
    its own mapper. Returns the keyframes the tap saw, the frontend's and mapper's info, the
    mapper's latest weight snapshot after ``train_s`` more seconds, and the snapshots taken
    every ``sample_s`` in the second half of that time (the last one included)."""
    ns = f"aisdf/ros2cmp/{kind}"
    common = ["--set", f"building={building}", "--set", f"seed={seed}", "--set", "linger=true",
              "--set", "resend_period_s=2"]
    if kind == "synthetic":
        fargs = common + ["--set", f"n_frames={n_frames}", "--set", f"width={width}", "--set", f"height={height}"]
    else:
        ros_port = free_port()
        fargs = common + ["--source", "ros2", "--ros-connect", endpoint(ros_port), "--ros-idle-timeout", "3"]
    st = Stack(services=("mapper", "frontend"), namespace=ns, log_dir=log_dir,
               args={"mapper": list(mapper_args or MAPPER_ARGS), "frontend": fargs})
    procs = []
    if log_dir:
        log_dir.mkdir(parents=True, exist_ok=True)
    try:
        if kind == "ros2":
            procs.append(popen(router_command(ros_port), log_dir / "ros-router.log" if log_dir else None))
        st.start(["mapper"])
        with transport.open_session(st.client_zenoh) as s:
            tap = KeyframeTap(s, ns)
            try:
                wait_for(lambda: transport.get_latest(s, keys.key(ns, "info/mapper"), 1.0), 90, what="the mapper")
                st.start(["frontend"])
                wait_for(lambda: transport.get_latest(s, keys.key(ns, "info/frontend"), 1.0), 90,
                         what="the frontend")
                t0 = time.monotonic()
                if kind == "ros2":
                    extra = ["--wait-subscriber", "30"]
                    if garbage_after:
                        extra += ["--garbage-after", str(garbage_after)]
                    procs.append(popen(replay_command(ros_port, n_frames, width, height, building, seed, extra),
                                       log_dir / "replay.log" if log_dir else None))
                fi, mi = wait_for(lambda: settled(s, ns), timeout, period=0.5, what=f"the {kind} path to finish")
                stream_s = time.monotonic() - t0
                snaps = []  # the map every sample_s during the second half of the training time
                end = time.monotonic() + train_s
                while time.monotonic() < end:
                    time.sleep(min(sample_s, max(0.0, end - time.monotonic())))
                    if end - time.monotonic() < train_s / 2:
                        snap = transport.get_latest(s, keys.key(ns, keys.MAP_WEIGHTS), 5.0)
                        if snap:
                            snaps.append(protocol.WeightSnapshot.from_msg(snap))
                mi = transport.get_latest(s, keys.key(ns, "info/mapper"), 2.0)
                snap = transport.get_latest(s, keys.key(ns, keys.MAP_WEIGHTS), 5.0)
                weights = protocol.WeightSnapshot.from_msg(snap) if snap else None
                return {"keyframes": tap.sorted(), "frontend": fi, "mapper": mi, "stream_s": stream_s,
                        "weights": weights, "snapshots": snaps + ([weights] if weights else [])}
            finally:
                tap.close()
    finally:
        st.stop()
        for p, out in reversed(procs):
            stop_proc(p, out)


def reference_keyframes(n_frames: int, width: int, height: int, building: str = "office", seed: int = 0) -> list:
    """The protocol-v1 frontend's keyframes for the synthetic source, in-process (no Zenoh):
    what ``aisdf-frontend`` sends with these settings and its defaults (30 fps, noise on,
    the default keyframe selection, ``f4`` depth, sensor ``depth``)."""
    from ..keyframes import KeyframeConfig, KeyframeSelector, keyframe_message
    from ..synthetic import SyntheticSequence

    seq = SyntheticSequence(building=building, n_frames=n_frames, H=height, W=width, fps=30.0, noise=True, seed=seed)
    sel = KeyframeSelector(KeyframeConfig())
    out: list = []
    for i in range(len(seq)):
        f = seq.frame(i)
        if sel.is_keyframe(float(f["stamp"]), f["depth"], f["K"], f["T_WC"]):
            out.append(keyframe_message(f))
    return out


def compare_keyframes(a: list, b: list) -> dict:
    """Same frame ids? Largest differences of depth, K, T_WC, and of the stamps' spacing."""
    ids_a, ids_b = [k.frame_id for k in a], [k.frame_id for k in b]
    out = {"ids_a": ids_a, "ids_b": ids_b, "same_ids": ids_a == ids_b}
    if out["same_ids"] and a:
        out["depth"] = max(float(np.nanmax(np.abs(x.depth_m() - y.depth_m()))) for x, y in zip(a, b))
        out["K"] = max(float(np.abs(x.K - y.K).max()) for x, y in zip(a, b))
        out["T_WC"] = max(float(np.abs(x.T_WC - y.T_WC).max()) for x, y in zip(a, b))
        sa = np.array([k.stamp for k in a]) - a[0].stamp
        sb = np.array([k.stamp for k in b]) - b[0].stamp
        out["stamp"] = float(np.abs(sa - sb).max())
    return out


def eval_setup(n_frames: int, width: int, height: int, building: str = "office", seed: int = 0,
               n_points: int = 50_000):
    from ..metrics import eval_points
    from ..synthetic import SyntheticSequence

    seq = SyntheticSequence(building=building, n_frames=n_frames, H=height, W=width, seed=seed)
    frames = [seq.frame(i) for i in range(0, n_frames, 5)]
    pts = eval_points(frames, n_points=n_points, every=1, rng=0, far_margin=0.1)
    return pts, seq.gt_sdf(pts)


def snapshot_error(snap: protocol.WeightSnapshot, pts: np.ndarray, gt: np.ndarray) -> float:
    import torch

    from ..network import build_model, load_numpy_state

    net = build_model(snap.model)
    load_numpy_state(net, snap.state)
    with torch.no_grad():
        pred = net(torch.as_tensor(pts, dtype=torch.float32)).numpy().reshape(-1)
    return float(np.mean(np.abs(pred - gt)))


def trained_error(keyframes: list, pts: np.ndarray, gt: np.ndarray, steps_first: int = 50, steps_per: int = 15,
                  width: int | None = None, seed: int = 0) -> tuple[float, int]:
    """Train in-process on ``keyframes`` (in order) with a fixed schedule and seed; SDF error
    of the network on ``pts`` (metres) and the number of steps."""
    import torch

    from ..mapper.single import MappingPipeline

    torch.set_num_threads(1)
    training = {"seed": seed}
    if width:
        training["network"] = {"width": width}
    pipe = MappingPipeline.from_settings("cpu", training=training)
    for k, kf in enumerate(keyframes):
        pipe.add_keyframe(kf)
        for _ in range(steps_first if k == 0 else steps_per):
            pipe.step()
    return float(np.mean(np.abs(pipe.sdf(pts) - gt))), pipe.steps


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="aisdf bench ros2-live", description=__doc__.split("\n\n")[0])
    p.add_argument("--n-frames", type=int, default=300)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--building", default="office")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train-s", type=float, default=30.0, help="live mappers train this long after the stream")
    p.add_argument("--steps-first", type=int, default=50)
    p.add_argument("--steps-per", type=int, default=15)
    p.add_argument("--log-dir", default="runs/ros2-compare")
    p.add_argument("--sequential", action="store_true", help="one path after the other (default: both at once)")
    p.add_argument("--json", help="also write the figures here")
    a = p.parse_args(argv)
    log_dir = Path(a.log_dir)
    t0 = time.monotonic()
    kinds = ("synthetic", "ros2")
    print(f"[{time.monotonic() - t0:6.1f} s] both paths {'one after the other' if a.sequential else 'at once'}: "
          f"{a.n_frames} frames at {a.width}x{a.height}, then {a.train_s:.0f} s of training", flush=True)

    def one(kind):
        return run_path(kind, a.n_frames, a.width, a.height, a.train_s, a.building, a.seed, log_dir=log_dir / kind)

    if a.sequential:
        res = {k: one(k) for k in kinds}
    else:  # at once: both mappers train under the same load
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as pool:
            futures = {k: pool.submit(one, k) for k in kinds}
            res = {k: f.result() for k, f in futures.items()}
    for kind in kinds:
        r = res[kind]
        print(f"[{time.monotonic() - t0:6.1f} s] {kind}: {len(r['keyframes'])} keyframes to the mapper "
              f"(frontend: {r['frontend']['frames']} frames, {r['frontend']['keyframes']} keyframes, "
              f"{r['frontend']['acked']} acknowledged); mapper: {r['mapper']['keyframes']} keyframes, "
              f"{r['mapper'].get('steps')} steps", flush=True)
        if kind == "ros2":
            print(f"             ROS 2 source: {json.dumps(r['frontend'].get('source'))}", flush=True)
    cmp = compare_keyframes(res["synthetic"]["keyframes"], res["ros2"]["keyframes"])
    print(f"same keyframes: {cmp['same_ids']} ({len(cmp['ids_a'])} vs {len(cmp['ids_b'])}); largest differences: "
          f"depth {cmp.get('depth')} m, K {cmp.get('K')}, T_WC {cmp.get('T_WC')}, stamp spacing {cmp.get('stamp')} s")
    pts, gt = eval_setup(a.n_frames, a.width, a.height, a.building, a.seed)
    live = {k: snapshot_error(res[k]["weights"], pts, gt) if res[k]["weights"] else float("nan") for k in res}
    print(f"live mappers, final map (network, {len(pts)} points): protocol v1 {100 * live['synthetic']:.2f} cm "
          f"({res['synthetic']['weights'].step} steps), ROS 2 {100 * live['ros2']:.2f} cm "
          f"({res['ros2']['weights'].step} steps): ratio {live['ros2'] / live['synthetic']:.3f}")
    # one snapshot's error swings by cm between seconds of training: the mean over the second half
    swing = {k: [snapshot_error(w, pts, gt) for w in res[k]["snapshots"]] for k in res}
    mean = {k: float(np.mean(v)) if v else float("nan") for k, v in swing.items()}
    print("live mappers, mean over the second half of the training time: " + ", ".join(
        f"{name} {100 * mean[k]:.2f} cm ({len(swing[k])} maps, {100 * min(swing[k]):.2f}-{100 * max(swing[k]):.2f}, "
        f"steps {res[k]['snapshots'][0].step}-{res[k]['snapshots'][-1].step})"
        for k, name in (("synthetic", "protocol v1"), ("ros2", "ROS 2")) if swing[k])
        + f": ratio {mean['ros2'] / mean['synthetic']:.3f}")
    same = {}
    for k in res:
        same[k] = trained_error(res[k]["keyframes"], pts, gt, a.steps_first, a.steps_per, seed=a.seed)
    ratio = same["ros2"][0] / same["synthetic"][0]
    verdict = "within" if ratio <= 1.1 else "NOT within"
    print(f"same training ({same['synthetic'][1]} steps, seed {a.seed}): protocol v1 "
          f"{100 * same['synthetic'][0]:.2f} cm, ROS 2 {100 * same['ros2'][0]:.2f} cm: ratio {ratio:.3f} "
          f"({verdict} 1.1x)")
    print(f"[{time.monotonic() - t0:6.1f} s] done")
    if a.json:
        Path(a.json).write_text(json.dumps({"compare": {k: v for k, v in cmp.items() if not k.startswith("ids")},
                                            "n_keyframes": [len(cmp["ids_a"]), len(cmp["ids_b"])],
                                            "live_cm": {k: 100 * v for k, v in live.items()},
                                            "live_mean_cm": {k: 100 * v for k, v in mean.items()},
                                            "same_training_cm": {k: 100 * v[0] for k, v in same.items()},
                                            "steps": same["synthetic"][1]}, indent=2))
    return 0 if cmp["same_ids"] and ratio <= 1.1 else 1


if __name__ == "__main__":
    sys.exit(main())
