"""``aisdf bench query``: the baked field beside the network, in one run, on the demo
building's map.

1. The map: the demo's synthetic ``office`` building, camera path and keyframe selection,
   trained in-process with the ``cpu`` preset for ``--train-steps`` steps (the demo's
   mapper makes about as many in its 180 s; ``query_map.py``); cached in ``--out`` so a rerun skips it. By
   default the mapper the service runs by default (``--mapper submaps``: a network per
   submap, with measured points, so ``fused`` answers are protocol 1.4's); ``--mapper
   single``: one network (the bench's map before 2026-12-03; with its measured points since
   protocol 1.5, 1.3's fused answer before).
2. The bake: wall time and memory (the baked arrays, and the process's peak resident
   memory growth during the bake, measured in a fresh process).
3. Accuracy on the demo's 200,000 evaluation points (along seen rays, iSDF's protocol):
   baked vs network (mean and 99th percentile difference, gradient cosine distance added)
   and each against the exact SDF.
4. Latency and throughput: in-process and over Zenoh (a real ``aisdf-query`` process on
   loopback), baked and network, 1k/10k/100k points, with and without gradients; and baked
   with each point's distance to unknown space (protocol 1.6's ``unknown``).
5. Lag: weights published at the demo's snapshot rate (1 Hz); how far the answering map
   trails the newest weights, sampled at 10 Hz.
6. Concurrent planners: 8 planners sending 10,000-point requests with gradients back to
   back for ``--planner-s`` seconds: latency percentiles, requests lost, busy replies, the
   query service's memory. By default with the mapper training the office walk beside them
   (``aisdf bench load``: its own services); ``--no-mapper``: the quiet case, the map
   above published once.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .. import keys, query_messages, transport
from ..client import SdfClient
from ..stack import Stack, wait_for
from .load import concurrent_planners, planners_beside_mapper
from .load import report as load_report
from .query_map import demo_map, engine_of, versioned

NS = "aisdf/bench"


# ----------------------------------------------------------------------------- helpers


def _pcts(ts) -> dict:
    a = 1e3 * np.asarray(ts, float)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
            "p99": float(np.percentile(a, 99)), "n": len(a)}


def _time(fn, repeats: int) -> list[float]:
    fn()  # warm-up
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def _cos_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    return 1.0 - np.sum(a * b, 1) / np.maximum(na * nb, 1e-12)


_BAKE_PROBE = r"""
import json, resource, sys, time
import torch
torch.set_num_threads(1)
from aisdf import protocol
from aisdf.bench.query_map import engine_of, warm
m = protocol.unpack(open(sys.argv[1], "rb").read())
e = engine_of(m, int(sys.argv[2]))
warm(e)
from aisdf.baked import bake, BakeConfig
import numpy as np
from aisdf.observed import ObservedGrid
occ = np.zeros((8, 8, 8), bool); occ[2:6, 2:6, 2:6] = True
bake(lambda p: (p[:, 0].copy(), np.tile([1.0, 0, 0], (len(p), 1)).astype("float32")), ObservedGrid(np.zeros(3), 0.1, occ))
e._baked = None
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
b = e.bake_now()
wall = time.perf_counter() - t
rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"wall_s": wall, "peak_growth_mb": (rss1 - rss0) / 1024, "field_mb": b.field.nbytes / 1e6,
                  **b.field.stats}))
"""


def bake_probe(map_path: Path, threads: int = 2) -> dict:
    """Bake once in a fresh process: wall time, the field's size and the peak memory growth."""
    r = subprocess.run([sys.executable, "-c", _BAKE_PROBE, str(map_path), str(threads)], capture_output=True,
                       text=True, timeout=600)
    if r.returncode:
        raise RuntimeError(f"bake probe failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- the run


def run(out: str | Path = "runs/bench-query", sizes=(1_000, 10_000, 100_000), repeats: int = 20,
        threads: int | None = None, bake_threads: int = 2, train_steps: int | None = None, planners: int = 8,
        planner_s: float = 60.0, lag_s: float = 30.0, n_eval: int = 200_000, quiet: bool = False,
        log_dir: str | None = None, mapper: str = "submaps", beside_mapper: bool = True, peer: bool = True) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(threads or 1)  # as the service: parallelism from its workers and bake threads
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    say("1/6 the demo building's map")
    m = demo_map(out, train_steps, quiet=quiet, mapper=mapper)
    seq = m.pop("seq")
    res: dict = {"map": {"mapper": mapper, "describe": m["describe"], "keyframes": m["keyframes"],
                         "train_steps": m["steps"]},  # made (at least one a keyframe): can exceed --train-steps
                 "threads": torch.get_num_threads(), "bake_threads": bake_threads}

    say("2/6 bake time and memory (a fresh process)")
    res["bake"] = bake_probe(out / f"map-{mapper}.msgpack", bake_threads)

    say("3/6 accuracy on the demo's evaluation points")
    from ..demo import eval_points_from

    eng = engine_of(m, bake_threads)
    st = eng.state
    res["map"].update(surfels=len(st.surfels) if st.surfels is not None else 0,
                      measured_points=len(st.measured) if st.measured is not None else 0)
    if mapper == "submaps":
        res["map"].update(submaps=len(st.submaps.submaps))
    eng.bake_now()
    rng = np.random.default_rng(0)
    pts = eval_points_from(seq, len(seq), n_eval, rng)
    gt = seq.gt_sdf(pts)
    gt_grad = _gt_gradient(seq, pts)
    b = eng.answer_sdf(query_messages.SdfRequest(pts, gradient=True))
    n = eng.answer_sdf(query_messages.SdfRequest(pts, gradient=True, exact=True))
    assert b.baked and not n.baked
    d = np.abs(b.sdf - n.sdf)
    valid = np.linalg.norm(gt_grad, axis=1) > 0.5
    res["accuracy"] = {
        "points": len(pts), "covered": float(np.mean(eng.baked.field.query(pts, False)[2])),
        "diff_mean_cm": 100 * float(d.mean()), "diff_p99_cm": 100 * float(np.percentile(d, 99)),
        "diff_max_cm": 100 * float(d.max()),
        "grad_cos_baked_vs_network": float(_cos_dist(b.gradient, n.gradient).mean()),
        "grad_cos_network_vs_truth": float(_cos_dist(n.gradient[valid], gt_grad[valid]).mean()),
        "grad_cos_baked_vs_truth": float(_cos_dist(b.gradient[valid], gt_grad[valid]).mean()),
        "sdf_error_network_cm": 100 * float(np.abs(n.sdf - gt).mean()),
        "sdf_error_baked_cm": 100 * float(np.abs(b.sdf - gt).mean()),
    }
    a = res["accuracy"]
    a["grad_cos_added"] = a["grad_cos_baked_vs_truth"] - a["grad_cos_network_vs_truth"]
    if peer:
        from . import query_peer

        res["peer"] = query_peer.run(seq, eng, m["messages"], pts, gt, res["bake"]["wall_s"], say)

    say("4/6 latency: in-process and over Zenoh, baked and network")
    res["latency"] = []
    qargs = ["--set", f"bake_threads={bake_threads}"] + (["--set", f"torch_threads={threads}"] if threads else [])
    with Stack(services=("query",), namespace=NS, args={"query": qargs}, log_dir=log_dir) as stack:
        with SdfClient(NS, zenoh=stack.client_zenoh, timeout=60.0) as client:
            s = client._session
            info_key = keys.key(NS, "info/query")

            def baked_version():
                i = transport.get_latest(s, info_key, 1.0) or {}
                return i.get("baked_version")

            def publish(version: int):
                # the surfels first (the map's first bake then has them), the weights or the submaps, the index
                for key, msg in sorted(versioned(m["messages"], version), key=lambda km: km[0] != keys.MAP_SURFELS):
                    transport.put(s, keys.key(NS, key), msg)

            def ready():
                if baked_version() == 1:
                    return True
                publish(1)  # until the service has subscribed (an older copy is ignored)
                return False

            wait_for(ready, 120, period=1.0, what="the query service to bake the map")
            # A submap map arrives as several messages, each a new map state for the service:
            # the first bake may be of part of it, and bakes of the rest follow. Measure once
            # no bake has finished for 5 s (a bake of this map takes about 1 s).
            bakes = [-1, (transport.get_latest(s, info_key, 1.0) or {}).get("bakes")]

            def settled():
                time.sleep(5.0)
                bakes[:] = [bakes[1], (transport.get_latest(s, info_key, 1.0) or {}).get("bakes")]
                return bakes[0] == bakes[1]

            wait_for(settled, 120, period=0.0, what="the query service's bakes to finish")
            for grad in (False, True):
                for npts in sizes:
                    q = pts[rng.choice(len(pts), npts, replace=False)].astype(np.float32)
                    reps = max(5, repeats if npts <= 10_000 else repeats // 4)
                    row = {"points": npts, "gradient": grad}
                    # 1.6: baked answers with each point's distance to unknown space
                    for name, exact, unknown in (("baked", False, False), ("network", True, False),
                                                 ("baked + unknown", False, True)):
                        req = query_messages.SdfRequest(q, grad, exact=exact, unknown=unknown)
                        t_in = _time(lambda: eng.answer_sdf(req), reps if not exact else max(3, reps // 2))
                        t_z = _time(lambda: client.query(q, gradient=grad, exact=exact, unknown=unknown),
                                    reps if not exact else max(3, reps // 2))
                        r = client.query(q, gradient=grad, exact=exact, unknown=unknown)
                        assert r.baked == (not exact) and (r.unknown is not None) == unknown
                        row[name] = {"inproc": _pcts(t_in), "zenoh": _pcts(t_z),
                                     "inproc_pts_s": npts / float(np.median(t_in)),
                                     "zenoh_pts_s": npts / float(np.median(t_z))}
                    res["latency"].append(row)
                    say(f"  {npts:>7,} pts grad={grad!s:5}: baked zenoh p50 {row['baked']['zenoh']['p50']:.1f} ms, "
                        f"network {row['network']['zenoh']['p50']:.1f} ms")

            say(f"5/6 lag behind the newest weights at 1 Hz for {lag_s:.0f} s")
            lags, versions, bake_lags = [], [], []
            t0 = time.monotonic()
            v = 1
            next_pub = t0
            while time.monotonic() - t0 < lag_s:
                now = time.monotonic()
                if now >= next_pub:
                    v += 1
                    publish(v)
                    next_pub += 1.0
                i = transport.get_latest(s, info_key, 1.0) or {}
                lag = i.get("lag") or {}
                lags.append(float(lag.get("behind_s", 0.0)))
                versions.append(int(lag.get("versions", 0)))
                bake_lags.append(float(lag.get("bake_behind_s", lag.get("behind_s", 0.0))))
                time.sleep(0.1)
            wait_for(lambda: baked_version() == v, 30, what="the last bake")
            info = transport.get_latest(s, info_key, 1.0) or {}
            res["lag"] = {"published": v - 1, "samples": len(lags), "behind_s_p50": float(np.median(lags)),
                          "behind_s_p95": float(np.percentile(lags, 95)), "behind_s_max": float(np.max(lags)),
                          "versions_behind_max": int(np.max(versions)), "bake_behind_s_p50": float(np.median(bake_lags)),
                          "bake_behind_s_p95": float(np.percentile(bake_lags, 95)),
                          "bake_behind_s_max": float(np.max(bake_lags)), "bakes": info.get("bakes"),
                          "last_bake": info.get("last_bake")}

            if not beside_mapper:
                say(f"6/6 {planners} concurrent planners x {planner_s:.0f} s of 10,000-point requests, no mapper")
                res["planners"] = concurrent_planners(client, pts, planners, planner_s)
                info = transport.get_latest(s, info_key, 1.0) or {}
                res["planners"]["service"] = {k: info.get(k) for k in ("answered", "errors", "busy")}
    if beside_mapper:
        say(f"6/6 {planners} concurrent planners x {planner_s:.0f} s of 10,000-point requests, the mapper training "
            "the office walk beside them (aisdf bench load)")
        res["planners"] = planners_beside_mapper(planners, planner_s, log_dir=log_dir, say=say)
    (out / "query.json").write_text(json.dumps(res, indent=2))
    return res


def _gt_gradient(seq, pts: np.ndarray, h: float = 0.01) -> np.ndarray:
    g = np.zeros_like(pts)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[:, k] = (seq.gt_sdf(pts + e) - seq.gt_sdf(pts - e)) / (2 * h)
    return g


# ----------------------------------------------------------------------------- tables


def report(res: dict) -> str:
    b, a, lg, pl = res["bake"], res["accuracy"], res["lag"], res["planners"]
    mp = res["map"]
    n_m = mp.get("measured_points") or 0
    submaps = mp.get("mapper", "single") == "submaps"
    what = (f"{mp.get('submaps')} submaps ({mp.get('describe')}), " if submaps else "one network, ") + \
        f"{mp.get('surfels')} surfels, " + (
            f"{n_m:,} measured points: `fused` is protocol " + ("1.4's answer" if submaps else "1.5's answer (1.4's rule)")
            if n_m else "no measured points: `fused` is protocol 1.3's answer")
    lines = [f"Map: the demo building (office), {mp['keyframes']} keyframes, "
             f"{mp['train_steps']} training steps (cpu preset), {what}; torch threads {res['threads']} per "
             f"evaluation, {res['bake_threads']} bake threads. The lag row: the whole map republished each second "
             f"(a submap map: every submap changed, so every bake is a full one).", "",
             "| bake | value |", "|---|---:|",
             f"| wall time (s) | {b['wall_s']:.2f} |",
             f"| network evaluations | {b['evaluations']:,} |",
             f"| blocks (fine) | {b['blocks']:,} ({b['fine_blocks']:,}) |",
             f"| baked arrays (MB) | {b['field_mb']:.1f} |",
             f"| peak memory growth during the bake (MB) | {b['peak_growth_mb']:.1f} |",
             f"| answering map behind the newest weights at 1 Hz: p50 / p95 / max (s) | "
             f"{lg['behind_s_p50']:.2f} / {lg['behind_s_p95']:.2f} / {lg['behind_s_max']:.2f} |",
             f"| the bake behind the newest weights: p50 / p95 / max (s) | "
             f"{lg['bake_behind_s_p50']:.2f} / {lg['bake_behind_s_p95']:.2f} / {lg['bake_behind_s_max']:.2f} |", "",
             f"| accuracy on {a['points']:,} demo evaluation points | value |", "|---|---:|",
             f"| covered by the bake | {100 * a['covered']:.2f} % |",
             f"| baked vs network: mean abs difference (cm) | {a['diff_mean_cm']:.3f} |",
             f"| baked vs network: 99th percentile (cm) | {a['diff_p99_cm']:.3f} |",
             f"| baked vs network: gradient cosine distance | {a['grad_cos_baked_vs_network']:.4f} |",
             f"| gradient cosine distance to the truth: network / baked (added) | "
             f"{a['grad_cos_network_vs_truth']:.4f} / {a['grad_cos_baked_vs_truth']:.4f} ({a['grad_cos_added']:+.4f}) |",
             f"| SDF error against the truth: network / baked (cm) | "
             f"{a['sdf_error_network_cm']:.3f} / {a['sdf_error_baked_cm']:.3f} |", "",
             "| points | gradient | path | in-process p50 / p99 (ms) | in-process (pts/s) | Zenoh p50 / p95 / p99 (ms) "
             "| Zenoh (pts/s) |", "|---:|:---:|---|---:|---:|---:|---:|"]
    for r in res["latency"]:
        for name in ("baked", "network", "baked + unknown"):
            if name not in r:  # (a run before protocol 1.6)
                continue
            x = r[name]
            lines.append(f"| {r['points']:,} | {'yes' if r['gradient'] else 'no'} | {name} | "
                         f"{x['inproc']['p50']:.2f} / {x['inproc']['p99']:.2f} | {x['inproc_pts_s']:,.0f} | "
                         f"{x['zenoh']['p50']:.2f} / {x['zenoh']['p95']:.2f} / {x['zenoh']['p99']:.2f} | "
                         f"{x['zenoh_pts_s']:,.0f} |")
    if res.get("peer"):
        from .query_peer import report as peer_report

        lines += ["", peer_report(res["peer"])]
    lines += ["", load_report(pl)]
    return "\n".join(lines)
