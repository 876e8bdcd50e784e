"""``aisdf bench rooms``: a room the defaults never saw, mapped from a few keyframes, against
the voxel map a team would otherwise run on the same frames and points.

Each run is a built-in Atlanta room (``--building``, at building seeds the benchmark's
defaults do not use: 1, 2, 3) walked with ``--keyframes`` frames of noisy depth at
``--size``, spread over its whole walk (one frame a second of it). The same frames go to
AiSDF's model as the mapper trains it (``aisdf.bench.methods``: the service's keyframe
selector, iSDF's schedule of 200 steps after the first keyframe and 60 after each later
one) and to the voxel maps (``aisdf.bench.voxel``: open3d's TSDF at 2 and 5 cm, free space
carved, scipy's Euclidean distance transform). Every method answers the same points,
``--points`` along the frames' rays as iSDF evaluates (``aisdf.metrics.eval_points``):

* ``served``: the query service's default answer with the layout prior (protocol 1.13);
* ``served, no prior``: the same without it (1.12's answer);
* the voxel maps' trilinear lookup.

Printed per seed and as the mean over seeds: mean SDF error (cm) on all points, on the
points whose nearest true surface no frame measured (``evaluation.observed_mask``) and
near furniture (``evaluation.near_furniture_mask``), and the served answer's ratio to the
2 cm voxel map's.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

METHODS = ("served", "served-noprior", "voxel-2cm", "voxel-5cm")
LABELS = {"served": "AiSDF served", "served-noprior": "AiSDF served, no prior", "voxel-2cm": "voxel map 2 cm",
          "voxel-5cm": "voxel map 5 cm"}


def run_one(building: str, seed: int, keyframes: int, H: int, W: int, n_points: int, preset: str,
            schedule_scale: float, say=print) -> dict:
    from .evaluation import labelled_building, near_furniture_mask, observed_mask
    from .methods import ComputeClock, make_runner, run_stream
    from .scenes import make_scene
    from .. import metrics

    scene = make_scene(building, {"n_frames": keyframes, "H": H, "W": W, "fps": 1.0, "scene_seed": seed})
    training = {"seed": 0, "steps_first_frame": max(1, round(200 * schedule_scale)),
                "steps_per_keyframe": max(1, round(60 * schedule_scale))}
    runners = {m: make_runner(m, scene, ComputeClock(), preset, training) for m in ("aisdf", "voxel-2cm", "voxel-5cm")}
    out: dict = {"building": building, "seed": seed}

    def at_end(i: int, t: float, seen: list[dict]) -> None:
        if i != len(scene) - 1:
            return
        p = metrics.eval_points(seen, n_points=n_points, every=1, rng=np.random.default_rng([seed, i]),
                                far_margin=scene.far_margin)
        gt = np.asarray(scene.gt_sdf(p), np.float64)
        keep = np.isfinite(gt)
        p, gt = p[keep], gt[keep]
        masks = {"all": np.ones(len(p), bool), "unobserved": ~observed_mask(scene, seen, p, gt)}
        b = labelled_building(scene)
        if b is not None:
            masks["near furniture"] = near_furniture_mask(b, p)
        a = runners["aisdf"]
        answers = {"served": a.query("served", p, False)[0], "served-noprior": a.query("served-noprior", p, False)[0],
                   "voxel-2cm": runners["voxel-2cm"].query("voxel", p, False)[0],
                   "voxel-5cm": runners["voxel-5cm"].query("voxel", p, False)[0]}
        out["points"] = int(len(p))
        out["shares"] = {k: round(float(m.mean()), 4) for k, m in masks.items()}
        out["error_cm"] = {m: {k: round(100 * float(np.abs(f - gt)[mk].mean()), 3) if mk.any() else None
                               for k, mk in masks.items()} for m, f in answers.items()}
        lay = a.layout()
        out["predicted_points"] = 0 if lay is None else int(len(lay))
        out["keyframes"], out["steps"] = a.keyframes, a.steps

    t = time.perf_counter()
    run_stream(scene.frames, list(runners.values()), "iterations", [len(scene) - 1], at_end, None)
    out["wall_s"] = round(time.perf_counter() - t, 1)
    e = out["error_cm"]
    say(f"{building} seed {seed}: {out['keyframes']} keyframes, {out['steps']} steps, {out['points']} points, "
        f"{out['predicted_points']} predicted layout points, {out['wall_s']:.0f} s")
    for m in METHODS:
        say(f"  {LABELS[m]:<24} " + "  ".join(f"{k} {v:.2f}" for k, v in e[m].items() if v is not None))
    return out


def table(runs: list[dict]) -> str:
    """Mean over runs of each method's error, and the served answer's ratio to the 2 cm voxel map's."""
    splits = [k for k in runs[0]["error_cm"]["served"] if all(r["error_cm"]["served"].get(k) is not None
                                                            for r in runs)]
    mean = {m: {k: float(np.mean([r["error_cm"][m][k] for r in runs])) for k in splits} for m in METHODS}
    lines = ["| method | " + " | ".join(f"{k} (cm)" for k in splits) + " |",
             "|---|" + "---|" * len(splits)]
    for m in METHODS:
        lines.append(f"| {LABELS[m]} | " + " | ".join(f"{mean[m][k]:.2f}" for k in splits) + " |")
    lines.append("| served / voxel 2 cm | " + " | ".join(
        f"{mean['served'][k] / mean['voxel-2cm'][k]:.2f}x" for k in splits) + " |")
    lines.append("| served / no prior | " + " | ".join(
        f"{mean['served'][k] / mean['served-noprior'][k]:.2f}x" for k in splits) + " |")
    shares = {k: float(np.mean([r["shares"][k] for r in runs])) for k in splits}
    lines.append("| share of points | " + " | ".join(f"{100 * shares[k]:.1f} %" for k in splits) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="aisdf bench rooms", description=__doc__.split("\n\n")[0])
    p.add_argument("--building", default="atlanta", help="a built-in building (aisdf.synthetic.buildings)")
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="building seeds (the defaults use 0)")
    p.add_argument("--keyframes", type=int, default=20)
    p.add_argument("--size", default="240x320", help="HxW of the depth images")
    p.add_argument("--points", type=int, default=20_000)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--schedule-scale", type=float, default=1.0, help="times iSDF's 200 / 60 steps")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args(argv)
    H, W = (int(x) for x in args.size.lower().split("x"))
    import torch

    torch.set_num_threads(2)
    runs = [run_one(args.building, s, args.keyframes, H, W, args.points, args.preset, args.schedule_scale)
            for s in args.seeds]
    md = table(runs)
    print(f"\n{args.building}, {args.keyframes} keyframes at {W}x{H}, seeds {args.seeds}, mean:\n\n{md}")
    res = {"runs": runs, "table": md, "args": vars(args)}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    return res


if __name__ == "__main__":
    main()
