"""``aisdf bench served``: what planners get from the real services while the map grows.

The query service and the mapper run as processes over Zenoh on loopback (``aisdf.stack``),
on this machine, with their default settings (the mapper's ``--preset``, by default
``cpu``). A synthetic building (the office, the floor) is walked: its keyframes, rendered up
front, are published on ``keyframes`` one per ``--period-s`` (1 s) of wall time, as a
frontend sends them; after the walk the mapper trains ``--tail-s`` (60 s) more. Meanwhile:

* every ``--planner-period-s`` (0.5 s) a planner asks 1,000 points (``fused``, the default
  answer): the answer lag is the time since a map newer than the one the reply is of
  arrived (a subscriber on ``map/index`` and ``map/weights`` beside the planner; 0 when the
  reply is of the newest map), with the reply's ``map_age_s`` (protocol 1.7);
* at the walk's end and every ``--sample-s`` (10 s) after it, the whole map's evaluation
  points (along the rays of every keyframe, as ``aisdf bench scaling`` draws them) are asked
  twice of the service, ``exact`` (the newest map's network, surfels and measured points)
  then ``fused`` as planners get it (again while a newer map arrived between the two), and
  both are scored against the exact SDF:
  ``served / exact`` is what the bake and its lag cost planners;
* the query service reports its bakes (``info/query``: evaluations of the newest bake) and
  its memory (resident set, from /proc) is read.

Prints a table per scene and writes ``served.json`` in ``--out``. Figures depend on the
machine's load: the mapper, the bake and the planners share its cores, as on a robot.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np

from .. import keys, protocol, transport
from ..client import MapArrivals, SdfClient
from ..keyframes import keyframe_message
from ..stack import Stack, wait_for


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _mb(x: float | None) -> float | None:
    return None if x is None else round(x, 1)


def _pcts(xs: list[float]) -> dict:
    if not xs:
        return {"n": 0}
    a = np.asarray(xs, np.float64)
    return {"n": len(a), "p50": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "max": round(float(a.max()), 3), "mean": round(float(a.mean()), 3)}


def walk_scene(name: str, args, out: Path, say) -> dict:
    from .scaling_config import resolve
    from .scaling_walk import scene_frames, whole_scorer

    # The walk and the evaluation points of ``aisdf bench scaling`` with the same settings.
    cfg = resolve("full", keyframes=args.keyframes, H=args.height, W=args.width, seed=args.seed,
                  n_points=args.n_points)
    seq, frames, _ = scene_frames(name, cfg)
    n = len(frames)
    scorer = whole_scorer(seq, frames, cfg)
    pts, gt = scorer.points, scorer.gt
    planner_pts = pts[np.random.default_rng(1).choice(len(pts), min(1000, len(pts)), replace=False)]
    ns = f"aisdf/bench-served-{name}"
    mapper_args = ["--preset", args.preset] + (["--mapper", args.mapper] if args.mapper else [])
    rec: dict = {"scene": name, "keyframes": n, "eval_points": len(pts), "samples": [], "planner": {}}
    query_args = [x for kv in args.query_set for x in ("--set", kv)]
    with Stack(services=("query", "mapper"), namespace=ns, args={"mapper": mapper_args, "query": query_args},
               log_dir=out / "logs" / name) as st, SdfClient(ns, zenoh=st.client_zenoh, timeout=60.0) as client:
        session = client._session
        qpid = st.procs["query"].pid
        wait_for(lambda: transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0), 60, what="the mapper")
        # (the planner asks from its first moment: a query service not up yet would not answer)
        wait_for(lambda: transport.get_latest(session, keys.key(ns, "info/query"), 1.0), 60, what="the query service")
        rss0 = rss_mb(qpid)
        versions, stop = MapArrivals(session, ns), threading.Event()
        lags, ages, errors, rss, took = [], [], [], [], []
        bakes: dict[int, int] = {}

        def poll_mapper():
            while not stop.is_set():
                qi = transport.get_latest(session, keys.key(ns, "info/query"), 1.0) or {}
                last = qi.get("last_bake") or {}
                if last.get("version") is not None and last.get("evaluations") is not None:
                    bakes[int(last["version"])] = int(last["evaluations"])
                m = rss_mb(qpid)
                if m is not None:
                    rss.append(m)
                stop.wait(0.25)

        def planner():
            while not stop.is_set():
                t = time.monotonic()
                try:
                    r = client.query(planner_pts)
                    took.append(1e3 * (time.monotonic() - t))
                    lags.append(versions.lag(r.map_version, t))  # versions that had arrived when it was asked
                    if r.map_age_s is not None:
                        ages.append(r.map_age_s)
                except protocol.ProtocolError as e:
                    if e.code != "no_map":
                        errors.append(e.code)
                except TimeoutError:  # no reply: an error the planner sees (the thread goes on)
                    errors.append("timeout")
                stop.wait(max(0.0, args.planner_period_s - (time.monotonic() - t)))

        threads = [threading.Thread(target=poll_mapper, daemon=True), threading.Thread(target=planner, daemon=True)]
        for th in threads:
            th.start()

        def sample(label: str, t_rel: float) -> dict:
            # The two answers of one map: a new one may arrive between them (on a loaded machine a
            # map a second), so ask again; the served one is asked first, so that it is never of a
            # newer map than the exact one beside it.
            for _ in range(10):
                served = client.query(pts)
                exact = client.query(pts, exact=True)
                if served.map_version == exact.map_version:
                    break
            s = {"at": label, "t_s": round(t_rel, 1), "served_cm": round(100 * float(np.mean(np.abs(served.sdf - gt))), 3),
                 "exact_cm": round(100 * float(np.mean(np.abs(exact.sdf - gt))), 3),
                 "served_version": served.map_version, "exact_version": exact.map_version,
                 "served_age_s": served.map_age_s}
            s["ratio"] = round(s["served_cm"] / s["exact_cm"], 3) if s["exact_cm"] else None
            say(f"  {name} {label}: served {s['served_cm']:.2f} cm (v{s['served_version']}), newest map exact "
                f"{s['exact_cm']:.2f} cm (v{s['exact_version']}), ratio {s['ratio']}")
            rec["samples"].append(s)
            return s

        t0 = time.monotonic()
        key = keys.key(ns, keys.KEYFRAMES)
        try:
            for i, f in enumerate(frames):
                wait = t0 + i * args.period_s - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                transport.put(session, key, keyframe_message(f, "bench", "u2").to_msg())
                if i % 20 == 0:
                    say(f"  {name}: keyframe {i + 1}/{n}, {time.monotonic() - t0:.0f} s")
            walk_end = time.monotonic()
            wait_for(lambda: versions.first, 60, what="a map")  # (its arrival is recorded by the subscriber)
            sample("end of the walk", walk_end - t0)
            # Every due moment is sampled, even one a slow sample before it overran (on a loaded
            # machine one sample can take longer than the spacing); t_s says when it was taken.
            for k in range(1, int(args.tail_s / args.sample_s + 1e-9) + 1):
                time.sleep(max(0.0, walk_end + k * args.sample_s - time.monotonic()))
                sample(f"+{k * args.sample_s:g} s", time.monotonic() - t0)
        finally:
            stop.set()
            for th in threads:
                th.join(5)
            versions.close()
        mi = transport.get_latest(session, keys.key(ns, "info/mapper"), 1.0) or {}
        rec.update({"mapper_keyframes": mi.get("keyframes"), "mapper_steps": mi.get("steps"),
                    "answer_lag_s": _pcts(lags), "map_age_s": _pcts(ages), "planner_errors": errors,
                    "planner_ms": _pcts(took),
                    "bake_evaluations": _pcts([float(v) for v in bakes.values()]), "bakes": len(bakes),
                    "query_rss_mb": {"start": _mb(rss0), "max": _mb(max(rss) if rss else None),
                                     "end": _mb(rss[-1] if rss else None)}})
    return rec


def report(res: dict) -> str:
    lines = [f"Served answers while the map grows: {res['keyframes']} keyframes, one per {res['period_s']:g} s, then "
             f"{res['tail_s']:g} s; the query service and the mapper (preset {res['preset']}, mapper "
             f"{res['mapper'] or 'default'}{'; query ' + ', '.join(res['query_set']) if res['query_set'] else ''}) on this "
             f"machine over Zenoh; {res['date']}.", ""]
    for rec in res["scenes"]:
        lines += [f"{rec['scene']}: {rec['eval_points']:,} points, {rec['mapper_keyframes']} keyframes in the map, "
                  f"{rec['mapper_steps']} training steps", "",
                  "| moment | served (cm) | newest map, exact (cm) | served / exact | served version / newest |",
                  "|---|---:|---:|---:|---|"]
        for s in rec["samples"]:
            lines.append(f"| {s['at']} | {s['served_cm']:.2f} | {s['exact_cm']:.2f} | {s['ratio']} | "
                         f"{s['served_version']} / {s['exact_version']} |")
        lag, age, ev, rss = rec["answer_lag_s"], rec["map_age_s"], rec["bake_evaluations"], rec["query_rss_mb"]
        ms = rec["planner_ms"]
        worst = max((s["ratio"] or 0) for s in rec["samples"]) if rec["samples"] else None
        lines += ["", "| figure | value |", "|---|---:|",
                  f"| worst served / exact | {worst} |",
                  f"| answer lag p50 / p95 / max (s), {lag.get('n', 0)} requests | "
                  f"{lag.get('p50', '-')} / {lag.get('p95', '-')} / {lag.get('max', '-')} |",
                  f"| map_age_s p50 / p95 / max (s) | {age.get('p50', '-')} / {age.get('p95', '-')} / "
                  f"{age.get('max', '-')} |",
                  f"| planner's 1,000 points: latency p50 / p95 / max (ms) | {ms.get('p50', '-')} / "
                  f"{ms.get('p95', '-')} / {ms.get('max', '-')} |",
                  f"| bakes seen; network evaluations per bake p50 / max | {rec['bakes']}; {ev.get('p50', '-')} / "
                  f"{ev.get('max', '-')} |",
                  f"| query service memory start / max / end (MB) | {rss['start']} / {rss['max']} / {rss['end']} |",
                  f"| planner errors (not no_map) | {len(rec['planner_errors'])} |", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf bench served", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["office", "floor"])
    p.add_argument("--keyframes", type=int, default=200)
    p.add_argument("--period-s", type=float, default=1.0)
    p.add_argument("--tail-s", type=float, default=60.0)
    p.add_argument("--sample-s", type=float, default=10.0)
    p.add_argument("--planner-period-s", type=float, default=0.5)
    p.add_argument("--n-points", type=int, default=50_000, help="whole-map evaluation points per sample")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--mapper", choices=["submaps", "single"], help="the mapper (default: the service's, submaps)")
    p.add_argument("--query-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a query service setting (its --set), e.g. fresh_s=0; repeatable")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/bench-served")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    say = lambda s: print(s, flush=True)  # noqa: E731
    res = {"date": time.strftime("%Y-%m-%d"), "keyframes": a.keyframes, "period_s": a.period_s, "tail_s": a.tail_s,
           "preset": a.preset, "mapper": a.mapper, "query_set": a.query_set, "scenes": []}
    t = time.time()
    for name in a.scenes:
        say(f"{name}: {a.keyframes} keyframes, one per {a.period_s:g} s, then {a.tail_s:g} s")
        res["scenes"].append(walk_scene(name, a, out, say))
    res["wall_s"] = round(time.time() - t, 1)
    (out / "served.json").write_text(json.dumps(res, indent=1))
    md = report(res)
    (out / "served.md").write_text(md + "\n")
    print(md)
    print(f"results in {out / 'served.json'} ({res['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
