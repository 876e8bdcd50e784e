"""``aisdf bench device``: a check for a machine with a GPU (it runs on the CPU too):

    aisdf bench device [--map runs/bench-query/map-submaps.msgpack] [--steps 300] [--profile] [--out DIR]

1. The query engine with ``device="auto"`` (CUDA where there is one) against the engine on the
   CPU, on the same map (``aisdf bench query``'s cached demo map, which that command writes):
   exact answers and gradients, baked answers, protocol 1.6's distances to unknown space, each
   engine's error against the exact SDF, the bake's time on each, 10,000-point latencies.
2. Both mappers (submaps, one network) training with preset ``auto`` (the paper's on CUDA) on
   30 keyframes of the office: time per step and the network's error after ``--steps`` steps.
3. With ``--profile``: where 100 steps of each mapper spend their time (cProfile, top 22).

Prints one JSON (also ``device_check.json`` in ``--out``). On a GPU machine without this
project's installed environment: ``PYTHONPATH=shared python -m aisdf.bench.device``.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import time
from pathlib import Path

import numpy as np
import torch

from .. import protocol, query_messages
from ..demo import eval_points_from
from ..synthetic import SyntheticSequence


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _median_ms(fn, n: int = 10) -> float:
    fn()
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return round(1e3 * float(np.median(ts)), 2)


def engines(map_path: Path, n_eval: int) -> dict:
    from ..query.engine import QueryEngine

    m = protocol.unpack(map_path.read_bytes())
    seq = SyntheticSequence(building="office", n_frames=int(m.get("n_frames", 4050)), fps=30.0, seed=0)
    pts = eval_points_from(seq, len(seq), n_eval, np.random.default_rng(0))
    gt = seq.gt_sdf(pts)

    def engine(dev):
        e = QueryEngine(device=dev, bake_threads=2)
        for k, msg in m["messages"]:
            e.take(k, msg)
        return e

    out: dict = {}
    eg, ec = engine("auto"), engine("cpu")
    out["engine_device"] = str(eg.device)
    R = query_messages.SdfRequest
    rg, rc = (e.answer_sdf(R(pts, gradient=True, exact=True)) for e in (eg, ec))
    d = np.abs(rg.sdf - rc.sdf)
    out["exact_auto_vs_cpu"] = {"mean_cm": 100 * float(d.mean()), "max_cm": 100 * float(d.max()),
                                "grad_max": float(np.abs(rg.gradient - rc.gradient).max())}
    for name, e in (("auto", eg), ("cpu", ec)):
        t = time.perf_counter()
        e.bake_now()
        out[f"bake_{name}_s"] = round(time.perf_counter() - t, 2)
    bg, bc = (e.answer_sdf(R(pts, gradient=True)) for e in (eg, ec))
    d = np.abs(bg.sdf - bc.sdf)
    out["baked_auto_vs_cpu"] = {"mean_cm": 100 * float(d.mean()), "max_cm": 100 * float(d.max()),
                                "baked": bool(bg.baked and bc.baked)}
    out["error_vs_truth_cm"] = {f"{n}_{k}": 100 * float(np.abs(r.sdf - gt).mean())
                                for n, k, r in (("auto", "exact", rg), ("cpu", "exact", rc), ("auto", "baked", bg),
                                                ("cpu", "baked", bc))}
    out["unknown_equal"] = bool(np.array_equal(eg.answer_sdf(R(pts, unknown=True)).unknown,
                                               ec.answer_sdf(R(pts, unknown=True)).unknown))
    q = pts[:10000]
    out["latency_10k_ms_auto"] = {"baked_grad": _median_ms(lambda: eg.answer_sdf(R(q, gradient=True))),
                                  "exact_grad": _median_ms(lambda: eg.answer_sdf(R(q, gradient=True, exact=True))),
                                  "baked_unknown": _median_ms(lambda: eg.answer_sdf(R(q, unknown=True)))}
    return out


def mappers(steps: int, profile: bool) -> dict:
    from ..mapper import MAPPER_KINDS
    from ..mapper.factory import make_mapper

    seq = SyntheticSequence(building="office", n_frames=600, seed=0)
    frames = [seq.frame(i) for i in range(0, 600, 20)]
    pts = eval_points_from(seq, 600, 20000, np.random.default_rng(1))
    gt = seq.gt_sdf(pts)
    out: dict = {}
    for kind in MAPPER_KINDS:
        pipe = make_mapper(kind, "auto")
        t = time.perf_counter()
        for f in frames:
            pipe.add_keyframe(protocol.Keyframe(f["frame_id"], f["stamp"], np.asarray(f["depth"], np.float32), f["K"],
                                                f["T_WC"]))
        t_add = time.perf_counter() - t
        _sync()
        t = time.perf_counter()
        while pipe.steps < steps:
            pipe.step()
        _sync()
        dt = time.perf_counter() - t
        rec = {"keyframes": int(pipe.n_keyframes), "add_s": round(t_add, 2), "steps": int(pipe.steps),
               "step_ms": round(1e3 * dt / max(pipe.steps, 1), 1),
               "implicit_error_cm": round(100 * float(np.abs(np.asarray(pipe.sdf(pts), np.float64) - gt).mean()), 2),
               "describe": pipe.describe()}
        if profile:
            pr = cProfile.Profile()
            pr.enable()
            for _ in range(100):
                pipe.step()
            _sync()
            pr.disable()
            sio = io.StringIO()
            pstats.Stats(pr, stream=sio).sort_stats("tottime").print_stats(22)
            rec["profile"] = [line for line in sio.getvalue().splitlines() if line.strip()]
        out[kind] = rec
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="aisdf bench device", description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, default=Path("runs") / "bench-query" / "map-submaps.msgpack",
                    help="a map aisdf bench query cached (its map-submaps.msgpack)")
    ap.add_argument("--eval-points", type=int, default=50_000)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    res = {"cuda": torch.cuda.is_available(), "torch": torch.__version__,
           "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    if a.map.exists():
        res["query"] = engines(a.map, a.eval_points)
    else:
        res["query"] = f"no map at {a.map}: run aisdf bench query first (it caches one there)"
    res["mappers"] = mappers(a.steps, a.profile)
    text = json.dumps(res, indent=1)
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "device_check.json").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
