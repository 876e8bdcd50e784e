"""``aisdf bench cluster``: the built-in floor walked by two robots into 1, 2 and 3 mapper
shards (protocol 1.14) and one query service (``--replicas 2``: two, protocol 1.12), real
processes over Zenoh on loopback, on this machine; then 3 shards with one killed with SIGKILL
mid-walk, and a fourth joining.

Each run starts the query service and the mappers (``--cluster``, ids ``c1`` .. ``cN``),
waits until every mapper sees all members, then two front ends walk the floor's ``--frames``
frames at ``--fps`` (robot1 the first half, robot2 the second), holding every keyframe until
its owners have it. At the walk's end (every keyframe acknowledged) and ``--settle`` seconds
later it measures the whole floor's error: the query service's default answer (``source``
fused) against the exact SDF at points sampled along the walk's rays (``eval_points``).

Prints, and writes to ``cluster.json`` in ``--out``: per run, per mapper its training steps
and the submaps it owns (trains); keyframes the front ends had acknowledged against those in
the map (the union of the mappers' keyframes; acknowledged but absent = lost); the error at
the walk's end and at +``--settle`` s. The kill run (3 mappers; half-way through the walk the
one that has published the most submaps, at least ``--kill-after``, killed): seconds until every submap it had published is published
by a survivor, acknowledged keyframes lost, the error at +``--settle`` s; then ``c4`` starts and
the seconds until it publishes a submap of its own. On a 2-core machine 3 mappers share the
cores with the query service and the front ends: each trains fewer steps than one alone.
``--threads auto`` (the default) gives each mapper process ``cores // mappers`` torch threads
(at least 1), as co-located shards should be configured (``torch_threads``).
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from .. import keys, protocol, transport
from ..stack import Stack, wait_for

NS = "aisdf/bench-cluster"


def mapper_infos(s, ns: str) -> dict[str, dict]:
    out = {}
    for r in s.get(keys.key(ns, "info/mapper"), payload=protocol.pack({"keys": True}), timeout=5.0,
                   consolidation=zenoh.ConsolidationMode.NONE):
        if r.ok is not None:
            m = protocol.unpack(transport.payload_bytes(r.ok.payload))
            out[m["cluster"]["id"]] = m
    return out


def front_infos(s, ns: str) -> list[dict]:
    out = []
    for r in s.get(keys.key(ns, "info/frontend"), timeout=5.0, consolidation=zenoh.ConsolidationMode.NONE):
        if r.ok is not None:
            out.append(protocol.unpack(transport.payload_bytes(r.ok.payload)))
    return out


def served_error(opts, ns: str, pts: np.ndarray, gt: np.ndarray) -> float | None:
    from ..client import SdfClient

    try:
        with SdfClient(ns, zenoh=opts, timeout=60.0) as c:
            rep = c.query(pts)
    except (protocol.ProtocolError, TimeoutError):
        return None
    return float(np.abs(np.asarray(rep.sdf, np.float64) - gt).mean())


def run_one(n: int, args, pts, gt, kill: bool = False, join: bool = False, log_dir: Path | None = None) -> dict:
    ns = f"{NS}/{n}{'k' if kill else ''}"
    threads = mapper_threads(args.threads, n)
    mapper = ["--preset", "cpu", "--cluster", "--set", f"training.network.width={args.width}", "--set",
              f"cluster.region_cells={args.region_cells}", "--set", "log_level=INFO",
              *(["--set", f"torch_threads={threads}"] if threads else [])]
    names = ["mapper"] + [f"mapper{i}" for i in range(2, n + 1 + int(join))]
    ids = {name: f"c{i + 1}" for i, name in enumerate(names)}
    half = args.frames // 2
    front = ["--set", "building=floor", "--set", f"n_frames={args.frames}", "--set", f"fps={args.fps}",
             "--set", "width=80", "--set", "height=60", "--set", "linger=true", "--set", "hold_max=2000"]
    queries = ["query"] + [f"query{i}" for i in range(2, args.replicas + 1)]
    st = Stack(services=[*queries, *names, "frontend", "frontend2"], namespace=ns,
               args={**{k: mapper + ["--mapper-id", v] for k, v in ids.items()},
                     "frontend": front + ["--set", "sensor=robot1", "--set", f"max_frames={half}"],
                     "frontend2": front + ["--set", "sensor=robot2", "--set", f"start={half}"]},
               log_dir=log_dir / ns.replace("/", "_") if log_dir else None)
    pubs: list[tuple[float, str, str]] = []
    lock = threading.Lock()

    def on_submap(sample):
        m = protocol.unpack(transport.payload_bytes(sample.payload))
        with lock:
            pubs.append((time.monotonic(), m["submap"]["id"], m["submap"].get("mapper", "")))

    out: dict = {"mappers": n, "kill": kill, "torch_threads": threads, "query_replicas": args.replicas}
    try:
        st.start(only=[*queries, *names[:n]])
        with transport.open_session(st.client_zenoh) as s:
            sub = s.declare_subscriber(keys.key(ns, keys.MAP_SUBMAPS) + "/*", on_submap)
            wait_for(lambda: (lambda i: len(i) == n and all(len(v["cluster"]["members"]) == n for v in i.values()))(
                mapper_infos(s, ns)), 120, what="every member")
            t0 = time.monotonic()
            st.start(only=["frontend", "frontend2"])
            if kill:  # half-way through the walk: the mapper that has published the most submaps
                wait_for(lambda: (lambda f: len(f) == 2 and sum(x["frames"] for x in f) >= args.frames // 2)(
                    front_infos(s, ns)), 900, 1.0, what="half the walk")

                def victim():
                    with lock:
                        counts = {}
                        for _, sid, m in pubs:
                            counts.setdefault(m, set()).add(sid)
                    best = max(counts, key=lambda m: (len(counts[m]), m), default=None)
                    return best if best and len(counts[best]) >= args.kill_after else None

                dead = wait_for(victim, 300, what="a mapper with submaps to kill")
                t_kill = time.monotonic()
                st.procs[next(k for k, v in ids.items() if v == dead)].kill()
                with lock:
                    owned = {p[1] for p in pubs if p[2] == dead}
                out.update(killed=dead, killed_at_s=round(t_kill - t0, 1), killed_submaps=len(owned))

                def back():
                    with lock:
                        later = {p[1]: p[0] for p in sorted(pubs, reverse=True) if p[0] > t_kill and p[2] != dead}
                    return all(c in later for c in owned) and max(later[c] for c in owned) - t_kill

                try:
                    out["served_again_s"] = round(wait_for(back, 300, 0.1, what="its submaps again"), 1)
                except TimeoutError:
                    out["served_again_s"] = None
            wait_for(lambda: (lambda f: len(f) == 2 and all(x["done"] and x["pending"] == 0 for x in f))(
                front_infos(s, ns)), 3600, 1.0, what="the walk's keyframes acknowledged")
            out["walk_s"] = round(time.monotonic() - t0, 1)
            fronts = front_infos(s, ns)
            out["error_end_cm"] = _cm(served_error(st.client_zenoh, ns, pts, gt))
            time.sleep(args.settle)
            out["error_settled_cm"] = _cm(served_error(st.client_zenoh, ns, pts, gt))
            infos = mapper_infos(s, ns)
            held = set().union(*({tuple(k) for k in i["keys"]} for i in infos.values())) if infos else set()
            acked = sum(f["acked"] for f in fronts)
            out.update(acked=acked, keyframes=sum(f["keyframes"] for f in fronts),
                       rejected=sum(f["rejected"] for f in fronts), in_map=len(held), lost=max(0, acked - len(held)))
            out["per_mapper"] = {k: {"steps": v["steps"], "owned_submaps": v["stats"].get("submaps", 0),
                                     "owned_regions": len(v["cluster"]["owned"]), "keyframes": v["keyframes"]}
                                 for k, v in sorted(infos.items())}
            if join:
                t_join = time.monotonic()
                st.start(only=[names[-1]])
                try:
                    wait_for(lambda: any(p[2] == ids[names[-1]] and p[0] > t_join for p in pubs), 120, 0.1,
                             what="the joiner's share")
                    out["joiner_owns_s"] = round(time.monotonic() - t_join, 1)
                except TimeoutError:
                    out["joiner_owns_s"] = None
            sub.undeclare()
    finally:
        st.stop()
    return out


def mapper_threads(spec: str, n: int) -> int | None:
    """torch threads per mapper process: ``auto`` splits this machine's cores between the ``n``
    mappers (at least 1 each), ``default`` leaves torch's default (every core, each), a number."""
    if spec == "default":
        return None
    if spec == "auto":
        return max(1, (os.cpu_count() or 1) // n)
    return int(spec)


def _cm(x):
    return None if x is None else round(100 * x, 2)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="aisdf bench cluster", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=300, help="frames of the floor's walk (default 300)")
    p.add_argument("--fps", type=float, default=3.0, help="the walk's frame rate (default 3: 100 s)")
    p.add_argument("--settle", type=float, default=60.0, help="seconds after the walk for the second error")
    p.add_argument("--width", type=int, default=64, help="network width (default 64)")
    p.add_argument("--region-cells", type=int, default=1, help="cells per region side (default 1)")
    p.add_argument("--kill-after", type=int, default=2, help="submaps the killed mapper has published at least")
    p.add_argument("--runs", default="1,2,3,kill", help="comma-separated: 1, 2, 3 mappers, kill (3 with one killed, "
                   "then a fourth joins)")
    p.add_argument("--replicas", type=int, default=1, choices=(1, 2), help="query services (replicas, protocol 1.12) "
                   "answering the planner's error queries (default 1)")
    p.add_argument("--threads", default="auto", help="torch threads per mapper: auto (the cores split between "
                   "the mappers: co-located shards should not each take every core), default (torch's), or N")
    p.add_argument("--out", default="runs/bench-cluster", help="results (cluster.json) and the services' logs")
    a = p.parse_args(argv)
    from ..metrics import eval_points
    from ..synthetic import SyntheticSequence

    seq = SyntheticSequence(building="floor", n_frames=a.frames, H=60, W=80, fps=a.fps, noise=True, seed=0)
    pts = eval_points([seq.frame(i) for i in range(0, a.frames, 5)], n_points=6000, every=1,
                      rng=np.random.default_rng(0), far_margin=0.1)
    gt = seq.gt_sdf(pts)
    out_dir = Path(a.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = {"date": time.strftime("%Y-%m-%d %H:%M"), "args": vars(a), "runs": []}
    for r in a.runs.split(","):
        r = r.strip()
        res = run_one(3, a, pts, gt, kill=True, join=True, log_dir=out_dir) if r == "kill" else \
            run_one(int(r), a, pts, gt, log_dir=out_dir)
        results["runs"].append(res)
        print(json.dumps(res), flush=True)
        (out_dir / "cluster.json").write_text(json.dumps(results, indent=1))
    print(report(results["runs"]))
    return results


def report(runs: list[dict]) -> str:
    lines = ["mappers | walk s | error end / +settle cm | acked / in map (lost) | per mapper: steps, submaps owned",
             "---|---|---|---|---"]
    for r in runs:
        per = "; ".join(f"{k} {v['steps']}, {v['owned_submaps']}" for k, v in r.get("per_mapper", {}).items())
        name = f"{r['mappers']}" + (" (one killed)" if r["kill"] else "") + \
            (f", {r['torch_threads']} thread{'s' * (r['torch_threads'] != 1)} each" if r.get("torch_threads") else "") + \
            (f", {r['query_replicas']} query replicas" if r.get("query_replicas", 1) > 1 else "")
        lines.append(f"{name} | {r.get('walk_s')} | {r.get('error_end_cm')} / {r.get('error_settled_cm')} | "
                     f"{r.get('acked')} / {r.get('in_map')} ({r.get('lost')}) | {per}")
    for r in runs:
        if r["kill"]:
            lines.append(f"kill: {r.get('killed')} killed {r.get('killed_at_s')} s into the walk with {r.get('killed_submaps')} "
                         f"submaps; served again after {r.get('served_again_s')} s; {r.get('lost')} acknowledged "
                         f"keyframes lost; a fourth mapper published its share after {r.get('joiner_owns_s')} s")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
