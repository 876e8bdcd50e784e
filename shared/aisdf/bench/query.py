"""``aisdf bench query``: throughput and latency of ``query/sdf`` over Zenoh (a real query
service process on loopback) beside evaluating the same network in-process, for
batches of 1k, 10k and 100k points. Prints a markdown table with the ratio."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from .. import keys, protocol, transport
from ..client import SdfClient
from ..mapping.presets import training_config
from ..network import SDFNetwork, model_spec, state_to_numpy
from ..stack import Stack, wait_for


def _snapshot(preset: str) -> protocol.WeightSnapshot:
    cfg = training_config(preset)
    torch.manual_seed(0)
    net = SDFNetwork(cfg.network)
    spec = model_spec(net)
    spec["bounds"] = [[-4.0, -4.0, -1.0], [4.0, 4.0, 3.0]]
    return protocol.WeightSnapshot(1, 0, time.time(), spec, state_to_numpy(net))


def _time(fn, repeats: int) -> list[float]:
    fn()  # warm-up
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def run(sizes=(1_000, 10_000, 100_000), repeats: int = 20, preset: str = "auto", gradient: bool = False,
        out: str | Path | None = None, threads: int | None = None, log_dir: str | None = None) -> list[dict]:
    from aisdf_query.engine import QueryEngine

    if threads:
        torch.set_num_threads(threads)
    snap = _snapshot(preset)
    rng = np.random.default_rng(0)
    rows = []
    qargs = ["--set", f"torch_threads={threads}"] if threads else []
    with Stack(services=("query",), namespace="aisdf/bench", args={"query": qargs}, log_dir=log_dir) as stack:
        with SdfClient("aisdf/bench", zenoh=stack.client_zenoh, timeout=60.0) as client:
            key = keys.key("aisdf/bench", keys.MAP_WEIGHTS)

            def ready():
                transport.put(client._session, key, snap.to_msg())
                try:
                    return client.query(np.zeros((1, 3))).map_version == 1
                except (protocol.ProtocolError, TimeoutError):
                    return False

            wait_for(ready, 60, period=0.5, what="the query service to load the map")
            engine = QueryEngine(device="auto")
            engine.set_weights(snap)
            for n in sizes:
                pts = rng.uniform(-3, 3, size=(n, 3)).astype(np.float32)
                req = protocol.SdfRequest(pts, gradient)
                reps = max(3, repeats if n <= 10_000 else repeats // 4)
                t_local = _time(lambda: engine.answer_sdf(req), reps)
                t_zenoh = _time(lambda: client.query(pts, gradient=gradient), reps)
                # Same answers both ways (the wire carries float32).
                assert np.allclose(client.query(pts[:100]).sdf, engine.answer_sdf(protocol.SdfRequest(pts[:100])).sdf,
                                   atol=1e-5)
                row = {"points": n, "gradient": gradient, "repeats": reps,
                       "inproc_ms_p50": 1e3 * float(np.median(t_local)),
                       "zenoh_ms_p50": 1e3 * float(np.median(t_zenoh)),
                       "zenoh_ms_p95": 1e3 * float(np.percentile(t_zenoh, 95)),
                       "inproc_pts_per_s": n / float(np.median(t_local)),
                       "zenoh_pts_per_s": n / float(np.median(t_zenoh))}
                row["ratio"] = row["zenoh_pts_per_s"] / row["inproc_pts_per_s"]
                rows.append(row)
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps({"preset": preset, "model": snap.model, "rows": rows}, indent=2))
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| points | gradient | in-process p50 (ms) | Zenoh p50 (ms) | Zenoh p95 (ms) | in-process (pts/s) "
             "| Zenoh (pts/s) | ratio |", "|---:|:---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['points']:,} | {'yes' if r['gradient'] else 'no'} | {r['inproc_ms_p50']:.1f} | "
                     f"{r['zenoh_ms_p50']:.1f} | {r['zenoh_ms_p95']:.1f} | {r['inproc_pts_per_s']:,.0f} | "
                     f"{r['zenoh_pts_per_s']:,.0f} | {r['ratio']:.2f} |")
    return "\n".join(lines)
