"""``aisdf bench``: the paper's Tables I-III, side by side on the same frames.

    aisdf bench --quick --out results/quick
    aisdf bench --scenes atlanta replica-office 7scenes-redkitchen --out results/$(date +%F)
    aisdf bench --mode realtime --scenes atlanta --methods voxel-5cm isdf aisdf
    aisdf bench --scenes manhattan atlanta stairs --seeds 0 1 2 --out results/seeds

For every scene (and seed) the stream is replayed once through every model in lockstep
(``methods.run_stream``); at checkpoints over sequence time every method is scored on the
same points (``evaluation.EvalSet``; at the end also split by whether each point's nearest
true surface was observed, Table Ib, and on the synthetic buildings by whether it is near
furniture, Table I's near-furniture rows and Table Ic); at the end the folder gets
table1/1b/1c/2/3 .md/.json, error_over_time_<scene>.png, sdf_slice_<scene>.png, meshes/<scene>/<method>.ply,
results.json (everything measured) and config.json (the resolved configuration,
versions, machine).
"""

from __future__ import annotations

import logging
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .. import __version__
from . import figures
from .evaluation import EvalSet
from .methods import ABLATION, LABELS, METHODS, MODELS, ComputeClock, atlanta_available, checkpoint_indices, \
    make_runner, run_stream
from .profiles import BenchConfig, resolve
from .progress import Progress
from .report import write_json, write_tables
from .scenes import SYNTHETIC, make_scene

log = logging.getLogger("aisdf.bench")

MODE_NOTES = {
    "iterations": "every model sees every frame; networks train iSDF's schedule on the service's keyframes",
    "realtime": "iSDF's replay: the next frame is the newest one the model's compute clock has passed",
}


def _versions() -> dict:
    import importlib.metadata as md

    out = {"aisdf": __version__, "python": platform.python_version()}
    for pkg in ("torch", "numpy", "scipy", "open3d", "trimesh", "scikit-image", "matplotlib"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out


def _machine() -> dict:
    import os

    import torch

    cuda = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    cpu = platform.processor() or platform.machine()
    info = {"platform": platform.platform(), "cpu": cpu, "cpu_count": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "cuda": cuda}
    info["summary"] = f"{cuda or cpu}, {os.cpu_count()} CPU cores, torch threads {info['torch_threads']}"
    return info


def _git() -> dict:
    root = Path(__file__).resolve().parents[3]
    try:
        rev = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain"], capture_output=True, text=True,
                               timeout=5)
        return {"commit": rev.stdout.strip() or None, "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None}


def _check_methods(cfg: BenchConfig) -> tuple[list[str], dict[str, str]]:
    """Methods that can run, and why the others cannot (the Atlanta module missing)."""
    unknown = [m for m in cfg.methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    why = atlanta_available()
    if why is None:
        return list(cfg.methods), {}
    keep = [m for m in cfg.methods if not MODELS[METHODS[m][0]].atlanta]
    dropped = {m: f"the Atlanta module does not import ({why})" for m in cfg.methods if m not in keep}
    for m, w in dropped.items():
        log.warning("method %s left out: %s", m, w)
    return keep, dropped


def _models_for(scene: str, methods: list[str], cfg: BenchConfig, atlanta_ok: bool) -> list[str]:
    models = list(dict.fromkeys(METHODS[m][0] for m in methods))
    if scene in cfg.ablation and atlanta_ok:
        models += [m for _, m in ABLATION if m not in models]
    return models


def run(cfg: BenchConfig, timer=time.perf_counter) -> dict:
    """Run the benchmark described by ``cfg``; write everything under ``cfg.out``; return the
    results (see ``report``'s docstring). ``timer``: the compute clock's time source."""
    import torch

    from ..datasets import data_root

    t_start = time.time()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    methods, dropped = _check_methods(cfg)
    atlanta_ok = atlanta_available() is None
    needs_data = any(name not in SYNTHETIC for name in cfg.scenes)
    data = Path(cfg.data) if cfg.data else (data_root() if needs_data else None)
    scenes = {name: make_scene(name, cfg.opts_for(name), data) for name in cfg.scenes}
    results: dict = {"mode": cfg.mode, "mode_note": MODE_NOTES[cfg.mode], "profile": cfg.profile, "methods": methods,
                     "unavailable": dropped, "n_points": cfg.n_points, "seeds": cfg.seed_list, "machine": _machine(),
                     "scenes": {}}
    config: dict = {"command": sys.argv, "config": cfg.model_dump(mode="json"), "versions": _versions(),
                    "machine": results["machine"], "git": _git(), "unavailable": dropped,
                    "method_labels": {m: LABELS[m] for m in methods}, "scenes": {}, "models": {}}
    seeds = cfg.seed_list
    total = sum(len(s) for s in scenes.values()) * len(seeds)
    with Progress(total, enabled=cfg.progress) as bar:
        for name, scene in scenes.items():
            config["scenes"][name] = scene.describe()
            entry = {"ground_truth": scene.gt_label, "gt_kind": scene.gt_kind, "frames": len(scene), "runs": []}
            results["scenes"][name] = entry
            for seed in seeds:
                bar.set_description(f"{name} seed {seed}")
                run_ = _run_scene(cfg, scene, methods, _models_for(name, methods, cfg, atlanta_ok), seed, timer, bar,
                                  out, artefacts=cfg.artefacts and seed == seeds[0], config=config)
                entry["runs"].append(run_)
    config["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    config["wall_s"] = round(time.time() - t_start, 1)
    results["wall_s"] = config["wall_s"]
    write_json(out / "config.json", config)
    write_json(out / "results.json", results)
    md = write_tables(out, results)
    if cfg.progress:
        print(md["table1"])
        print(f"results in {out} ({config['wall_s']:.0f} s)")
    return results


def _run_scene(cfg: BenchConfig, scene, methods, models, seed, timer, bar, out: Path, artefacts: bool,
               config: dict) -> dict:
    runners = {m: make_runner(m, scene, ComputeClock(timer, cfg.slowdown), cfg.preset, cfg.training_for(seed),
                              cfg.keyframes) for m in models}
    for m, r in runners.items():
        if hasattr(r, "pipe"):
            config["models"].setdefault(m, {"training": r.pipe.trainer.cfg.model_dump(mode="json"),
                                            "describe": r.pipe.describe()})
    n = len(scene)
    cps = checkpoint_indices(n, cfg.checkpoints)
    record: dict = {"seed": seed, "final": {}, "ablation": {}, "over_time": [], "models": {}}

    def on_checkpoint(i: int, t: float, seen: list[dict]) -> None:
        final = i == n - 1
        n_pts = cfg.n_points if final else min(cfg.n_points, cfg.n_points_checkpoint)
        es = EvalSet(scene, seen, n_pts, np.random.default_rng([seed, i]), split=final)
        row = {}
        for m in methods:
            model, view = METHODS[m]
            row[m] = es.score(lambda p, g, r=runners[model], v=view: r.query(v, p, g))
        record["over_time"].append({"frame": i, "t": round(t, 3), "methods": row})
        if final:
            record["final"] = row
            if scene.name in cfg.ablation:
                implicit = {METHODS[m][0]: row[m] for m in row if METHODS[m][1] == "implicit"}
                for _, model in ABLATION:
                    if model in runners:
                        record["ablation"][model] = implicit.get(model) or es.score(
                            lambda p, g, r=runners[model]: r.query("implicit", p, g))

    seen = run_stream(scene.frames, list(runners.values()), cfg.mode, cps, on_checkpoint, bar)
    record["models"] = {m: r.summary(scene.up) for m, r in runners.items()}
    if artefacts:
        _artefacts(cfg, scene, methods, runners, seen, record, out)
    return record


def _artefacts(cfg: BenchConfig, scene, methods, runners, seen, record, out: Path) -> None:
    name = scene.name
    labels = {m: LABELS[m] for m in methods}
    figures.plot_over_time(out / f"error_over_time_{name}.png", name, record["over_time"], labels, scene.gt_label)
    grid, extent, info = figures.slice_plane(scene.up, seen, cfg.slice_res, cfg.slice_height)
    pts = grid.reshape(-1, 3)
    gt_title = "reference, not truth" if scene.is_reference else "ground truth"
    fields = {gt_title: np.asarray(scene.gt_sdf(pts), np.float64).reshape(grid.shape[:2])}
    for m in methods:
        model, view = METHODS[m]
        fields[labels[m]] = runners[model].query(view, pts, False)[0].reshape(grid.shape[:2])
    figures.plot_slices(out / f"sdf_slice_{name}.png", name, fields, extent, info, scene.up_source)
    record["slice"] = info
    mdir = out / "meshes" / name
    mdir.mkdir(parents=True, exist_ok=True)
    meshes = {}
    for m in methods:
        model, view = METHODS[m]
        r = runners[model]
        if view == "voxel":
            V, F = r.map.mesh()
        else:
            V, F = figures.marching_cubes_mesh(lambda p, r=r, v=view: r.query(v, p, False)[0], scene.bounds,
                                               cfg.mesh_res)
        figures.write_mesh(mdir / f"{m}.ply", V, F)
        meshes[m] = {"path": str(mdir / f"{m}.ply"), "faces": int(len(F))}
    if "aisdf" in runners and (s := runners["aisdf"].surfels()) is not None:
        figures.write_mesh(mdir / "aisdf_surfels.ply", *figures.surfel_mesh(s))
        meshes["aisdf_surfels"] = {"path": str(mdir / "aisdf_surfels.ply"), "surfels": len(s)}
    if scene.gt_kind == "exact":  # the synthetic building's own surfaces
        gm = scene.frames.scene.mesh()
        figures.write_mesh(mdir / "ground_truth.ply", gm.vertices, gm.faces)
    record["meshes"] = meshes


# ------------------------------------------------------------------ command line


def add_arguments(p) -> None:
    """The suite's options on the ``aisdf bench`` parser."""
    from .profiles import PROFILES
    from .scenes import SCENES

    p.add_argument("--profile", choices=list(PROFILES), help="quick (CI), standard (CPU, default), paper (GPU)")
    p.add_argument("--quick", action="store_true", help="the quick profile (one small synthetic scene, ~2 min)")
    p.add_argument("--scenes", nargs="+", choices=list(SCENES), help="scenes (default: the profile's)")
    p.add_argument("--methods", nargs="+", choices=list(METHODS), help="Table I columns (default: voxel maps at "
                   "5 and 2 cm, iSDF, AiSDF w/o and w. explicit map, AiSDF served exact and baked; voxblox: the "
                   "paper's 5.5 cm)")
    p.add_argument("--ablation", nargs="*", help="scenes that also get Table II's models (none: no Table II)")
    p.add_argument("--mode", choices=["iterations", "realtime"], help="equal iterations (default) or real-time replay")
    p.add_argument("--seeds", type=int, nargs="+", help="one number N: seeds 0..N-1; several: those seeds "
                   "(e.g. --seeds 0 1 2); tables give mean ± standard deviation")
    p.add_argument("--out", help="results folder (default results/<date>-<time>)")
    p.add_argument("--data", help="shared data folder (default: AISDF_DATA, else ../shared/data)")
    p.add_argument("--cache", dest="cache_dir", help="cache for ground-truth grids and reference meshes "
                   "(default ~/.cache/aisdf/bench)")
    p.add_argument("--preset", choices=["cpu", "paper", "auto"], help="training preset")
    p.add_argument("--schedule-scale", type=float, help="iterations mode: times iSDF's 200/60 steps")
    p.add_argument("--frames", type=int, help="use only the first N frames of every scene")
    p.add_argument("--n-points", type=int, help="evaluation points at the end (iSDF: 200000)")
    p.add_argument("--checkpoints", type=int, help="evaluations over sequence time")
    p.add_argument("--threads", type=int, help="torch threads")
    p.add_argument("--slowdown", type=float, help="realtime mode: multiply compute time (emulate a slower machine)")
    p.add_argument("--no-artefacts", action="store_true", help="tables and config only (no meshes, no figures)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar and no table printout")


def config_from_args(args) -> BenchConfig:
    g = lambda k: getattr(args, k, None)  # noqa: E731
    profile = "quick" if g("quick") else (g("profile") or "standard")
    out = g("out") or f"results/{time.strftime('%Y-%m-%d-%H%M%S')}"
    cache = g("cache_dir") or str(Path.home() / ".cache" / "aisdf" / "bench")
    over = {k: g(k) for k in ("scenes", "methods", "ablation", "mode", "seeds", "data", "preset", "schedule_scale",
                              "frames", "n_points", "checkpoints", "threads", "slowdown")}
    if isinstance(over["seeds"], list) and len(over["seeds"]) == 1:
        over["seeds"] = over["seeds"][0]  # a count, as before
    over.update(out=out, cache_dir=cache)
    if g("no_artefacts"):
        over["artefacts"] = False
    if g("no_progress"):
        over["progress"] = False
    cfg = resolve(profile, **over)
    if g("ablation") is None:  # the profile's ablation scenes among those run, else the first scene
        cfg.ablation = [s for s in cfg.ablation if s in cfg.scenes] or cfg.scenes[:1]
    return cfg


def main(args) -> None:
    run(config_from_args(args))
