"""``aisdf bench replicas``: planners against one and two query replicas (protocol 1.12), and
one of two killed.

The demo building's map (``aisdf bench query``'s, trained in-process with ``--train-steps``
and cached in ``--out``) is put on the namespace as the mapper publishes it; the query
services run as processes over Zenoh on loopback, on this machine, with their default
settings. ``--planners`` (8) threads, each with its own ``SdfClient``, send ``--points``
(10,000) point requests with gradients back to back:

1. for ``--seconds`` (20) against one replica;
2. for ``--seconds`` against two (the second joins, is given the map, bakes it);
3. for ``--kill-s`` (15) seconds after one of the two is killed with SIGKILL, ``--warmup-s``
   (3) into the run.

Prints, and writes to ``replicas.json`` in ``--out``: per run, requests sent, answered, errors
(a protocol error), lost (no answer: a timeout), requests per second, p50/p95 latency of the
answered ones, each replica's ``evaluated`` count over the run, the clients' failovers; for
the kill, the requests that ended in the ``--kill-s`` seconds after it.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np

from .. import keys, protocol, transport
from ..client import SdfClient
from ..metrics import eval_points
from ..replicas import replica_infos
from ..stack import Stack, wait_for
from .query_map import demo_map, versioned

NS = "aisdf/bench-replicas"


def planners(clients: list[SdfClient], pts: np.ndarray, seconds: float, n_points: int) -> list[tuple]:
    """Each client in its own thread, requests back to back for ``seconds``:
    [(start, end, "ok" | "error" | "lost")]."""
    out, lock = [], threading.Lock()
    stop = time.monotonic() + seconds

    def run(i: int, c: SdfClient):
        rng = np.random.default_rng(100 + i)
        while time.monotonic() < stop:
            q = pts[rng.integers(0, len(pts), n_points)]
            t = time.monotonic()
            try:
                c.query(q, gradient=True)
                kind = "ok"
            except protocol.ProtocolError:
                kind = "error"
            except TimeoutError:
                kind = "lost"
            with lock:
                out.append((t, time.monotonic(), kind))

    ths = [threading.Thread(target=run, args=(i, c)) for i, c in enumerate(clients)]
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    return out


def summary(res: list[tuple], wall: float, before: dict, after: dict, failovers: int) -> dict:
    ok = [t1 - t0 for t0, t1, k in res if k == "ok"]
    lat = 1e3 * np.asarray(ok) if ok else np.zeros(1)
    return {"sent": len(res), "answered": len(ok), "errors": sum(k == "error" for _, _, k in res),
            "lost": sum(k == "lost" for _, _, k in res), "seconds": round(wall, 1),
            "requests_per_s": round(len(ok) / wall, 1), "p50_ms": round(float(np.percentile(lat, 50)), 1),
            "p95_ms": round(float(np.percentile(lat, 95)), 1), "failovers": failovers,
            # None: the replica is gone (killed), its count with it
            "evaluated": {r: after[r]["evaluated"] - before.get(r, {}).get("evaluated", 0) if r in after else None
                          for r in sorted(set(before) | set(after))}}


def run(out: Path, n_planners: int = 8, n_points: int = 10_000, seconds: float = 20.0, kill_s: float = 15.0,
        warmup_s: float = 3.0, train_steps: int = 300, say=print) -> dict:
    m = demo_map(out, train_steps, quiet=False)
    seq = m["seq"]
    pts = eval_points([seq.frame(i) for i in range(0, len(seq), 20)], n_points=200_000, every=1,
                      rng=np.random.default_rng(0), far_margin=0.1).astype(np.float32)
    st = Stack(services=("query", "query2"), namespace=NS, log_dir=out / "logs",
               args={"query": ["--replica-id", "r1"], "query2": ["--replica-id", "r2"]})
    st.start(only=["query"])
    clients: list[SdfClient] = []
    res: dict = {"planners": n_planners, "points": n_points, "gradient": True, "train_steps": train_steps}
    try:
        s = transport.open_session(st.client_zenoh)
        try:
            def baked(ids):
                for key, msg in sorted(versioned(m["messages"], 1), key=lambda km: km[0] != keys.MAP_SURFELS):
                    transport.put(s, keys.key(NS, key), msg)
                inf = replica_infos(s, NS)
                return set(inf) == set(ids) and all(i.get("baked_version") == 1 for i in inf.values())

            def settled():
                # a submap map arrives as several messages: the first bake may be of part of it and
                # bakes of the rest follow; measure once no replica has finished a bake for 5 s
                b0 = {r: i.get("bakes") for r, i in replica_infos(s, NS).items()}
                time.sleep(5.0)
                return b0 == {r: i.get("bakes") for r, i in replica_infos(s, NS).items()}

            wait_for(lambda: baked(["r1"]), 300, period=2.0, what="replica r1 to bake the map")
            wait_for(settled, 120, period=0.0, what="r1's bakes to finish")
            clients = [SdfClient(NS, st.client_zenoh, timeout=30.0) for _ in range(n_planners)]
            wait_for(lambda: all(c.replica_ids() == ["r1"] for c in clients), 30, what="the clients to see r1")

            def measure(name: str, secs: float, kill_at: float | None = None) -> dict:
                before, f0 = replica_infos(s, NS), sum(c.failovers for c in clients)
                killer = None
                if kill_at is not None:
                    killer = threading.Timer(kill_at, st.procs["query"].kill)
                    killer.start()
                t0 = time.monotonic()
                r = planners(clients, pts, secs, n_points)
                wall = time.monotonic() - t0
                if killer is not None:
                    killer.join()
                out_ = summary(r, wall, before, replica_infos(s, NS), sum(c.failovers for c in clients) - f0)
                if kill_at is not None:
                    t_kill = t0 + kill_at
                    after = [(a, b, k) for a, b, k in r if b >= t_kill]
                    out_["after_kill"] = {"seconds": kill_s, "requests": len(after),
                                          "answered": sum(k == "ok" for *_, k in after),
                                          "errors": sum(k == "error" for *_, k in after),
                                          "lost": sum(k == "lost" for *_, k in after)}
                say(f"  {name}: {out_}")
                return out_

            say(f"{n_planners} planners x {n_points} points with gradients, {seconds:.0f} s each run")
            res["one"] = measure("one replica", seconds)
            st.start(only=["query2"])
            wait_for(lambda: baked(["r1", "r2"]), 300, period=2.0, what="replica r2 to bake the map")
            wait_for(settled, 120, period=0.0, what="r2's bakes to finish")
            wait_for(lambda: all(c.replica_ids() == ["r1", "r2"] for c in clients), 30, what="the clients to see r2")
            res["two"] = measure("two replicas", seconds)
            res["kill"] = measure("two replicas, r1 killed", warmup_s + kill_s, kill_at=warmup_s)
        finally:
            for c in clients:
                c.close()
            s.close()
    finally:
        st.stop()
    return res


def report(res: dict) -> str:
    rows = [f"{res['planners']} planners x {res['points']:,} points with gradients (demo map, "
            f"{res['train_steps']} training steps)",
            "| run | sent | answered | errors | lost | requests/s | p50 ms | p95 ms | evaluated per replica | failovers |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for key, name in (("one", "1 replica"), ("two", "2 replicas"), ("kill", "2 replicas, r1 killed")):
        r = res[key]
        ev = ", ".join(f"{k} {'killed' if v is None else v}" for k, v in r["evaluated"].items())
        rows.append(f"| {name} | {r['sent']} | {r['answered']} | {r['errors']} | {r['lost']} | "
                    f"{r['requests_per_s']} | {r['p50_ms']} | {r['p95_ms']} | {ev} | {r['failovers']} |")
    k = res["kill"]["after_kill"]
    rows.append(f"after the kill ({k['seconds']:.0f} s): {k['requests']} requests, {k['answered']} answered, "
                f"{k['errors']} errors, {k['lost']} lost")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf bench replicas", description=__doc__.split("\n\n")[0])
    p.add_argument("--planners", type=int, default=8)
    p.add_argument("--points", type=int, default=10_000)
    p.add_argument("--seconds", type=float, default=20.0, help="seconds of each of the first two runs")
    p.add_argument("--kill-s", type=float, default=15.0, help="seconds measured after the kill")
    p.add_argument("--warmup-s", type=float, default=3.0, help="seconds before the kill")
    p.add_argument("--train-steps", type=int, default=300, help="training steps of the demo map (cached in --out)")
    p.add_argument("--out", default="runs/bench-replicas")
    a = p.parse_args(argv)
    out = Path(a.out)
    res = run(out, a.planners, a.points, a.seconds, a.kill_s, a.warmup_s, a.train_steps)
    out.mkdir(parents=True, exist_ok=True)
    (out / "replicas.json").write_text(json.dumps(res, indent=2))
    print(report(res))


if __name__ == "__main__":
    main()
