"""``aisdf bench rosbag``: the same 7-Scenes frames mapped from a rosbag2 .mcap, a rosbag2
.db3 and a ROS 1 .bag give the same map as from the folder format.

    aisdf bench rosbag [--frames 250] [--out runs/bench-rosbag]

1. Writes the first ``--frames`` RedKitchen frames ($AISDF_DATA/7scenes-redkitchen) into three
   recordings with ``aisdf.ros.record.write_bag`` (the full TF tree map -> odom -> base_link ->
   camera_link -> camera_depth_optical_frame, odom -> base_link at 50 Hz not aligned with the
   images plus one sample at each image's stamp, map frame z-up by the folder's
   gravity-direction.txt): rosbag2 sqlite3 with 16UC1 depth, rosbag2 MCAP with PNG
   CompressedImage depth, ROS 1 with 32FC1 depth. These hold the folder's poses exactly, so the
   three rows test the readers. One more MCAP recording has the 50 Hz samples only: every pose
   is then interpolated across the image's stamp (off by up to the bound printed), as on a
   robot whose odometry does not sample the camera's instants; its row shows what that does.
2. Reads each back with ``aisdf.ros.bag.RosbagSource`` (topics and frames discovered, the TF
   check run) and maps it in-process: the frontend's keyframe selector and
   ``MappingPipeline`` (AiSDF, same preset, seed and steps per keyframe as the folder run).
   The recordings' poses are in the map frame; they are mapped after moving them back to the
   folder's world frame by the known T_map_world of step 1, so that every run builds its map in
   one frame (the network's input box is axis-aligned, so a rotated world is a different
   training problem). With ``--map-frame-row``, one more run maps the MCAP recording as
   recorded, in its map frame, scored at the same points moved into the map frame.
3. Scores every map on the same points against the fused reference (TSDF fusion of all 250
   frames, ``aisdf.bench.scenes``: reference, not truth) and prints keyframes, SDF error and
   the ratio to the folder run; writes ``rosbag.json`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from ..ros import record as rf

ENCODINGS = {"sqlite3": "16UC1", "mcap": "png", "ros1": "32FC1"}
LABELS = {"sqlite3": "rosbag2 .db3 (16UC1)", "mcap": "rosbag2 .mcap (PNG)", "ros1": "ROS 1 .bag (32FC1)"}


class InWorld:
    """A source with its poses moved by ``T`` (map -> folder world)."""

    def __init__(self, src, T):
        self.src, self.T = src, T

    def __len__(self):
        return len(self.src)

    def frame(self, i):
        f = self.src.frame(i)
        return dict(f, T_WC=self.T @ f["T_WC"])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="aisdf bench rosbag", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=250, help="RedKitchen frames (of 250)")
    p.add_argument("--out", default="runs/bench-rosbag", help="recordings, cache and rosbag.json")
    p.add_argument("--data", help="shared data folder (default $AISDF_DATA or ../shared/data)")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--width", type=int, default=64, help="network width")
    p.add_argument("--steps-first", type=int, default=50, help="training steps after the first keyframe")
    p.add_argument("--steps-per-keyframe", type=int, default=15, help="training steps after every other keyframe")
    p.add_argument("--eval-points", type=int, default=50_000)
    p.add_argument("--reference-voxel", type=float, default=0.02, help="fused reference voxel (m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--keep-bags", action="store_true", help="keep the recordings in --out/bags")
    p.add_argument("--map-frame-row", action="store_true", help="also map the .mcap in its own map frame")
    a = p.parse_args(argv)

    import torch

    from .evaluation import EvalSet
    from .methods import ComputeClock, make_runner, run_stream
    from .scenes import make_scene
    from ..datasets import data_root
    from ..ros.bag import RosbagSource
    from ..ros.check import check_source

    torch.set_num_threads(a.threads)
    data = Path(a.data) if a.data else data_root()
    out = Path(a.out)
    (out / "cache").mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    scene = make_scene("7scenes-redkitchen", {"reference_voxel": a.reference_voxel, "max_frames": a.frames,
                                              "cache_dir": str(out / "cache")}, data)
    root = Path(scene.info["path"])
    T_mw = rf.sevenscenes_alignment(root)
    T_wm = np.linalg.inv(T_mw)
    n = len(scene.frames)
    print(f"7-Scenes RedKitchen: {n} frames; {scene.gt_label} ({time.perf_counter() - t:.0f} s)")

    bags = out / "bags"
    shutil.rmtree(bags, ignore_errors=True)
    bags.mkdir(parents=True)
    streams = {"folder": (scene.frames, None)}
    rows: dict[str, dict] = {"folder": {"label": "folder (7-Scenes PNG + pose.txt)"}}
    sources = []
    recordings = [(fmt, fmt, enc, True) for fmt, enc in ENCODINGS.items()] + [("mcap 50 Hz", "mcap", "png", False)]
    for name, fmt, enc, at_images in recordings:
        t = time.perf_counter()
        wb = rf.write_bag(rf.path_for(bags, fmt, name.replace(" ", "_")), scene.frames, fmt, encoding=enc,
                          T_map_world=T_mw, tf_at_images=at_images)
        tw = time.perf_counter() - t
        size = sum(f.stat().st_size for f in ([wb.path] if wb.path.is_file() else wb.path.rglob("*")))
        t = time.perf_counter()
        src = RosbagSource(wb.path)
        verdict = check_source(src)
        sources.append(src)
        et, er = rf.interpolation_bound(wb)
        dev = np.linalg.norm(src.poses()[:, :3, 3] - np.stack(wb.T_WC)[:, :3, 3], axis=1)  # camera positions
        label = LABELS[fmt] + ("" if at_images else ", TF at 50 Hz only")
        rows[name] = {"label": label, "bag_mb": round(size / 2**20, 1), "write_s": round(tw, 1),
                     "open_s": round(time.perf_counter() - t, 2), "placed": len(src), "skipped": src.counts["skipped"],
                     "tf_check": "passed" if verdict.ok else "FAILED",
                     "pose_dev_mm_max": round(1e3 * float(max(dev)), 3),
                     "pose_bound_mm_max": round(1e3 * float(et.max()), 3)}
        print(f"{label}: {rows[name]}")
        if len(src) != n or not verdict.ok:
            raise SystemExit(f"{wb.path}: {src.summary()}; {verdict}")
        streams[name] = (InWorld(src, T_wm), None)
    if a.map_frame_row:
        streams["mcap, map frame"] = (sources[1], T_mw)  # as recorded; scored at points moved into the map frame
        rows["mcap, map frame"] = {"label": "rosbag2 .mcap, mapped in its map frame"}

    training = {"seed": a.seed, "network": {"width": a.width}, "steps_first_frame": a.steps_first,
                "steps_per_keyframe": a.steps_per_keyframe}
    es = None
    for name, (stream, T_query) in streams.items():
        t = time.perf_counter()
        runner = make_runner("aisdf", scene, ComputeClock(), a.preset, training)
        seen = run_stream(stream, [runner], "iterations", [n - 1], lambda *_: None)
        if es is None:  # the folder run's frames give the evaluation points (every 5th frame)
            es = EvalSet(scene, seen, a.eval_points, np.random.default_rng(a.seed))

        def query(pts, grad, r=runner, T=T_query):
            if T is None:
                return r.query("implicit", pts, grad)
            f, g = r.query("implicit", pts @ T[:3, :3].T + T[:3, 3], grad)
            return f, (None if g is None else g @ T[:3, :3])  # gradients back into the folder's frame

        score = es.score(query)
        pos = {fid: i for i, fid in enumerate(runner.seen_ids)}  # frame ids differ (folder: names; bags: topic order)
        rows[name].update(keyframes=runner.keyframes, keyframe_ids=[pos[k] for k in runner.keyframe_ids],
                          steps=runner.steps,
                          sdf_error_cm=round(score["sdf_error_cm"], 3),
                          gradient_cosine_distance=round(score["gradient_cosine_distance"], 4),
                          map_s=round(time.perf_counter() - t, 1))
        print(f"{name}: {runner.keyframes} keyframes, {runner.steps} steps, SDF error {score['sdf_error_cm']:.3f} cm "
              f"({rows[name]['map_s']:.0f} s)")
    for s in sources:
        s.close()
    if not a.keep_bags:
        shutil.rmtree(bags, ignore_errors=True)

    ref = rows["folder"]
    print(f"\n{n} frames, {es and len(es)} evaluation points, preset {a.preset}, width {a.width}, "
          f"{a.steps_first} + {a.steps_per_keyframe} steps per keyframe, seed {a.seed}\n")
    print("| source | keyframes | same keyframes as folder | SDF error (cm) | vs folder | TF check "
          "| pose dev. max (mm) |")
    print("|---|---|---|---|---|---|---|")
    ok = True
    for name, r in rows.items():
        same = r["keyframe_ids"] == ref["keyframe_ids"]  # stream positions of the keyframes
        ratio = r["sdf_error_cm"] / ref["sdf_error_cm"]
        r["ratio_to_folder"] = round(ratio, 4)
        r["same_keyframes"] = same
        if name in ENCODINGS:
            ok &= same and abs(ratio - 1) <= 0.05
        dev = f"{r['pose_dev_mm_max']:.3f} (bound {r['pose_bound_mm_max']:.3f})" if "pose_dev_mm_max" in r else "-"
        print(f"| {r['label']} | {r['keyframes']} | {'yes' if same else 'NO'} | {r['sdf_error_cm']:.3f} | "
              f"{ratio:.3f} | {r.get('tf_check', '-')} | {dev} |")
    print(f"\ndone when (three formats: same keyframes, SDF error within 5% of the folder's): "
          f"{'MET' if ok else 'NOT MET'}")
    (out / "rosbag.json").write_text(json.dumps({"args": vars(a), "rows": rows, "criterion_met": ok}, indent=1,
                                                default=str))


if __name__ == "__main__":
    main()
