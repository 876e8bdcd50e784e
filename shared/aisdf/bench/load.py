"""``aisdf bench load``: planners hammering the query service while the mapper trains beside it.

The query service and the mapper run as processes over Zenoh on loopback, on this machine,
with their default settings (the mapper's ``--preset``, by default ``cpu``). The office is
walked at one keyframe per ``--period-s`` (1 s), its keyframes rendered up front and
published as a frontend sends them; the mapper trains and publishes its submaps, and the
query service bakes them, while ``--planners`` (8) planner threads in one client process
each send ``--points`` (10,000) point requests with gradients back to back for
``--seconds`` (60 s), starting ``--warmup-s`` (20 s) into the walk, once a map is served.

Prints, and writes to ``load.json`` in ``--out``: requests sent / answered / busy / errors /
lost (no reply), latency percentiles, points per second, the query service's resident
memory at the planners' start, its maximum and its end (growth = maximum - start), its
bakes and the mapper's steps in the meantime. ``aisdf bench query`` runs the same case
(``--no-mapper`` there for the quiet one, the map published once and not changing).
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
from ..keyframes import keyframe_message
from ..stack import Stack, wait_for
from .served import rss_mb

NS = "aisdf/bench-load"


def _pcts_ms(ts) -> dict:
    a = 1e3 * np.asarray(ts, float)
    return {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max()), "n": len(a)}


def concurrent_planners(client: SdfClient, pts, planners: int, seconds: float,
                        n_points: int = 10_000, gradient: bool = True) -> dict:
    """``planners`` threads, each sending ``n_points``-point requests back to back, drawn from
    ``pts`` (an array, or a function returning the array to draw from now)."""
    lat: list[float] = []
    counts = {"sent": 0, "answered": 0, "busy": 0, "errors": 0, "timeouts": 0}
    lock = threading.Lock()
    stop = time.monotonic() + seconds

    def planner(i: int):
        rng = np.random.default_rng(100 + i)
        while time.monotonic() < stop:
            pool = pts() if callable(pts) else pts
            q = pool[rng.integers(0, len(pool), n_points)].astype(np.float32)
            t = time.perf_counter()
            try:
                client.query(q, gradient=gradient)
                kind = "answered"
            except protocol.ProtocolError as e:
                kind = "busy" if e.code == "busy" else "errors"
            except TimeoutError:
                kind = "timeouts"
            dt = time.perf_counter() - t
            with lock:
                counts["sent"] += 1
                counts[kind] += 1
                if kind == "answered":
                    lat.append(dt)

    ths = [threading.Thread(target=planner, args=(i,)) for i in range(planners)]
    t0 = time.perf_counter()
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    wall = time.perf_counter() - t0
    return {"planners": planners, "seconds": round(wall, 1), "points_per_request": n_points, "gradient": gradient,
            **counts, "lost": counts["sent"] - counts["answered"] - counts["busy"] - counts["errors"],
            "latency_ms": _pcts_ms(lat) if lat else None, "points_per_s": counts["answered"] * n_points / wall}


class Feeder:
    """Publishes keyframes on ``keyframes`` one per ``period_s`` of wall time, from a thread."""

    def __init__(self, session, ns: str, frames: list[dict], period_s: float):
        self.session, self.key, self.frames, self.period_s = session, keys.key(ns, keys.KEYFRAMES), frames, period_s
        self.sent, self.stop = 0, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        t0 = time.monotonic()
        for i, f in enumerate(self.frames):
            if self.stop.wait(max(0.0, t0 + i * self.period_s - time.monotonic())):
                return
            transport.put(self.session, self.key, keyframe_message(f, "bench", "u2").to_msg())
            self.sent = i + 1

    def __enter__(self) -> "Feeder":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(5)


def walk_frames(scene: str = "office", keyframes: int = 200, seed: int = 0, per_frame: int = 250):
    """The walk of ``aisdf bench scaling`` / ``served`` (its keyframes) and points along its
    rays, ``per_frame`` of each keyframe's, in the keyframes' order."""
    from ..metrics import eval_points
    from .scaling_config import resolve
    from .scaling_walk import scene_frames

    seq, frames, _ = scene_frames(scene, resolve("full", keyframes=keyframes, H=120, W=160, seed=seed))
    return frames, eval_points(frames, n_points=per_frame * len(frames), every=1, rng=np.random.default_rng([seed, 7]))


def planners_beside_mapper(planners: int = 8, seconds: float = 60.0, n_points: int = 10_000, scene: str = "office",
                           keyframes: int = 200, period_s: float = 1.0, warmup_s: float = 20.0, preset: str = "cpu",
                           query_set: list[str] | None = None, mapper_set: list[str] | None = None,
                           mapper: bool = True, log_dir: str | Path | None = None, say=print) -> dict:
    """With ``mapper`` False, the quiet case: the walk and the mapper stop at the warm-up's
    end, and the planners start once the query service has baked the last map."""
    per_frame = 250
    frames, pts = walk_frames(scene, keyframes, per_frame=per_frame)
    query_args = [x for kv in (query_set or []) for x in ("--set", kv)]
    mapper_args = ["--preset", preset] + [x for kv in (mapper_set or []) for x in ("--set", kv)]
    with Stack(services=("query", "mapper"), namespace=NS, args={"mapper": mapper_args, "query": query_args},
               log_dir=log_dir) as st, SdfClient(NS, zenoh=st.client_zenoh, timeout=60.0) as client:
        s = client._session
        qpid = st.procs["query"].pid
        wait_for(lambda: transport.get_latest(s, keys.key(NS, "info/mapper"), 1.0), 60, what="the mapper")
        with Feeder(s, NS, frames, period_s) as feed:
            t0 = time.monotonic()

            def served():
                try:
                    client.query(pts[:10])
                    return True
                except (protocol.ProtocolError, TimeoutError):  # no map yet; no query service up yet
                    return False

            wait_for(served, 120, period=0.5, what="a served map")
            time.sleep(max(0.0, t0 + warmup_s - time.monotonic()))
            if not mapper:
                feed.stop.set()
                st.stop_one("mapper")

                def baked():
                    lag = (transport.get_latest(s, keys.key(NS, "info/query"), 1.0) or {}).get("lag") or {}
                    return lag.get("bake_versions", 1) == 0

                wait_for(baked, 120, period=1.0, what="the last map's bake")
            say(f"  {planners} planners x {seconds:.0f} s of {n_points:,}-point requests with gradients, "
                f"keyframe {feed.sent}/{len(frames)} of the {scene} walk" + ("" if mapper else ", the mapper stopped"))
            qi0 = transport.get_latest(s, keys.key(NS, "info/query"), 1.0) or {}
            mi0 = transport.get_latest(s, keys.key(NS, "info/mapper"), 1.0) or {}
            rss, stop = [rss_mb(qpid)], threading.Event()

            def poll():
                while not stop.wait(0.25):
                    m = rss_mb(qpid)
                    if m is not None:
                        rss.append(m)

            poller = threading.Thread(target=poll, daemon=True)
            poller.start()
            try:
                # planners ask about the space seen so far: points along the rays of the keyframes sent
                res = concurrent_planners(client, lambda: pts[:max(1, feed.sent) * per_frame], planners, seconds,
                                          n_points)
            finally:
                stop.set()
                poller.join(5)
            kf_end = feed.sent
        qi = transport.get_latest(s, keys.key(NS, "info/query"), 1.0) or {}
        mi = transport.get_latest(s, keys.key(NS, "info/mapper"), 1.0) or {}
    rss = [x for x in rss if x is not None]
    res.update({
        "scene": scene, "mapper": mapper, "mapper_preset": preset, "query_set": query_set or [], "mapper_set": mapper_set or [],
        "keyframes_published": kf_end, "keyframes_total": len(frames),
        "mapper_steps": (mi.get("steps") or 0) - (mi0.get("steps") or 0),
        "mapper_keyframes": mi.get("keyframes"),
        "bakes": (qi.get("bakes") or 0) - (qi0.get("bakes") or 0), "last_bake": qi.get("last_bake"),
        "service": {k: (qi.get(k) or 0) - (qi0.get(k) or 0) for k in ("answered", "errors", "busy", "held")},
        "query_rss_mb": {"start": rss[0] if rss else None, "max": max(rss) if rss else None,
                         "end": rss[-1] if rss else None,
                         "growth": (max(rss) - rss[0]) if rss else None},
    })
    return res


def report(res: dict) -> str:
    lat = res["latency_ms"] or {k: float("nan") for k in ("p50", "p95", "p99", "max")}
    m = res.get("query_rss_mb") or {}
    beside = ("no mapper: one map, published once" if "mapper" not in res else f"the mapper (preset {res['mapper_preset']}) training the {res['scene']} walk beside it, keyframes "
              f"{res['keyframes_published']}/{res['keyframes_total']} published by the end, "
              f"{res['mapper_steps']} training steps and {res['bakes']} bakes during the run"
              if res["mapper"] else f"the mapper stopped after {res['keyframes_published']} keyframes of "
              f"the {res['scene']} walk: the map does not change")
    lines = [f"| {res['planners']} planners x {res['seconds']:.0f} s, {res['points_per_request']:,}-point requests "
             f"with gradients; {beside} | value |", "|---|---:|",
             f"| requests sent / answered / busy / errors / timeouts | {res['sent']} / {res['answered']} / "
             f"{res['busy']} / {res['errors']} / {res['timeouts']} |",
             f"| lost (no reply) | {res['lost']} |",
             *([f"| answered by a bake trailing by more than fresh_s while requests waited (planners first) | "
                f"{res['service']['held']} |"] if "held" in (res.get("service") or {}) else []),
             f"| latency p50 / p95 / p99 / max (ms) | {lat['p50']:.1f} / {lat['p95']:.1f} / {lat['p99']:.1f} / "
             f"{lat.get('max', float('nan')):.1f} |",
             f"| points answered per second | {res['points_per_s']:,.0f} |"]
    if m:
        lines.append(f"| query service memory start / max / end (MB); growth | {m['start']:.0f} / {m['max']:.0f} / "
                     f"{m['end']:.0f}; {m['growth']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="aisdf bench load", description=__doc__.split("\n\n")[0])
    p.add_argument("--planners", type=int, default=8)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--points", type=int, default=10_000, help="points per request")
    p.add_argument("--scene", default="office")
    p.add_argument("--keyframes", type=int, default=200)
    p.add_argument("--period-s", type=float, default=1.0)
    p.add_argument("--warmup-s", type=float, default=20.0, help="seconds into the walk the planners start")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--query-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a query service setting (its --set); repeatable")
    p.add_argument("--mapper-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a mapper setting (its --set), e.g. nice=0; repeatable")
    p.add_argument("--no-mapper", dest="mapper", action="store_false",
                   help="the quiet case: the walk and the mapper stop after the warm-up, the map no longer changes")
    p.add_argument("--out", default="runs/bench-load")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = planners_beside_mapper(a.planners, a.seconds, a.points, a.scene, a.keyframes, a.period_s, a.warmup_s,
                                 a.preset, a.query_set, a.mapper_set, a.mapper, log_dir=out / "logs", say=lambda s: print(s, flush=True))
    res["date"] = time.strftime("%Y-%m-%d")
    (out / "load.json").write_text(json.dumps(res, indent=1))
    print(report(res))


if __name__ == "__main__":
    main()
