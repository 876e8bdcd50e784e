"""``aisdf bench change``: what the served map says when the world changes.

The frontend, the mapper (``--preset``, cpu by default) and the query service run as
processes over Zenoh on loopback (``aisdf.stack``); the frontend streams a changing synthetic
scene (``aisdf.synthetic.changes``: ``--set change=cart|person|drift``) at the sensor's rate,
and this process asks the query service what planners get (``fused``, the default answer).
The keyframes the frontend selects are known here by running the same selection on the
same frames; a keyframe counts as in the map once the frontend has it acknowledged.

* ``cart``: a cart (0.8 x 0.6 x 1.0 m) stands in the office during the walk's first pass,
  and is gone for its second pass over the same path. Two thirds into the pause between
  the passes (``--pause-s``, 30 s): the share of a 5 cm lattice inside its box answered
  occupied (served sdf < 5 cm; target >= 80 %; the lattice's points within 10 cm of the
  floor are left out: they are that near a surface with or without the cart). After the
  last keyframe that saw its space empty is in the map: that share every second for
  ``--watch-s`` (30 s), and the time until it is <= 5 % (target <= 10 s);
  also every second from the first keyframe that saw its space empty, and that time from it.
  The rest of the room's mean |served - truth| (points along the first pass's keyframe rays,
  as ``metrics.eval_points`` draws them, more than 0.3 m from the cart and where the cart is
  not the nearest surface, so the truth there is the same with and without it) at the pause
  and at the end of the watch (target: <= 1.1x).
* ``person``: someone (0.35 x 0.5 x 1.75 m) crosses the view during the first pass. 10 s
  after the last keyframe that saw the swept volume empty: the most negative served - truth
  over a 5 cm lattice of that volume (target >= -0.20 m) and the share answered occupied
  (points more than 10 cm from the floor).
* ``drift``: the walk with poses drifting to 20 cm and 2 degrees; at its end the true poses
  of its keyframes are sent as corrections (``aisdf.poses.send_corrections``), and
  ``--after-s`` (60 s) later the whole map's mean error is set against the same walk mapped
  with the true poses from the start (a second run; target <= 1.2x); and the served sdf
  along lines crossing walls (1 cm apart, from 1 m in front to 10 cm behind): the surfaces
  it meets up to 3 cm behind the wall, stretches below 2 cm apart by more than 5 cm
  (target: one per line, one surface not two), its value at the wall and its zero crossings.
* ``parked``: ``aisdf bench parked`` (in its own process): the keyframes a robot parked for
  ``--parked-frames`` frames keeps, and its memory growth.

``--only cart,person`` runs a subset; ``--quick`` is a smoke run (300-frame passes, short
waits, 200 parked frames). Prints every figure with its target and yes/no; writes
``change.json`` and ``change.md`` in ``--out``. The mapper is measured as it is: nothing is
tuned here.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..keyframes import KeyframeSelector
from ..metrics import eval_points
from .change_report import report
from .change_run import (CLEAR_M, NEAR_CART_M, OCCUPIED_M, PARTS, Run, _frontend_args, _say, _stream_s,
                         commit, crossings, rays_through, select_keyframes, still_box, surfaces, wall_lines)


def cart(args, out: Path) -> dict:
    from ..synthetic.changes import ChangingSequence

    seq = ChangingSequence(args.building, "cart", n_frames=args.frames, seed=args.seed, pause_s=args.pause_s)
    n, removed = seq.pass_frames, seq.removed_at
    _say(f"cart: {seq.cart.size.tolist()} m at {np.round(seq.cart.center, 2).tolist()} (canonical); "
         f"{len(seq)} frames: pass 1 [0, {n}), pause, pass 2 from {removed}; selecting keyframes here")
    ids, kept = select_keyframes(seq)
    empty = [i for i in ids if i >= removed and rays_through(seq, kept[i], seq.true_poses[i], seq.cart) >= 30]
    seen = [i for i in ids if i < n and rays_through(seq, kept[i], seq.true_poses[i], seq.cart, -0.05) >= 30]
    last_empty = empty[-1] if empty else ids[-1]
    before_removal = sum(1 for i in ids if i < removed)
    at = n + (2 * seq.pause_frames) // 3  # the standing cart is measured two thirds into the pause
    before_at = sum(1 for i in ids if i < at)  # pass 1's keyframes and the pause's first (max_interval_s)
    _say(f"cart: {len(ids)} keyframes ({before_removal} before the removal); {len(seen)} of pass 1 see the cart, "
         f"{len(empty)} of pass 2 see its space empty, the last is frame {last_empty}")
    # The cart's lattice, less its points within ``CLEAR_M`` of another surface (the floor under
    # it): those are within 5 cm of a surface with or without the cart.
    grid = seq.box_points(seq.cart)
    grid = grid[seq.gt_sdf(grid, len(seq) - 1) >= CLEAR_M]
    still = still_box(seq)
    still_grid = seq.box_points(still)
    still_grid = still_grid[seq.scene.room.sdf_grad(seq.scene.to_canon(still_grid))[0] >= CLEAR_M]
    p1 = [kept[i] for i in ids if i < n]
    pts = eval_points(p1, n_points=args.n_points, every=1, rng=0)
    # The rest of the room: more than 0.3 m from the cart, where the cart is not the nearest
    # surface either (its true distance is the same with and without the cart).
    far = seq.cart.sdf(seq.scene.to_canon(pts)) > NEAR_CART_M
    gt_with, gt_without = seq.gt_sdf(pts, 0), seq.gt_sdf(pts, len(seq) - 1)
    rest = far & (np.abs(gt_with - gt_without) < 1e-9)
    pts, gt_with, gt_without = pts[rest], gt_with[rest], gt_without[rest]
    rec: dict = {"building": args.building, "frames": len(seq), "pass_frames": n, "pause_frames": seq.pause_frames,
                 "keyframes": len(ids), "keyframes_seeing_empty": len(empty), "last_empty_frame": last_empty,
                 "grid_points": len(grid), "room_points": len(pts), "watch": []}
    stream = _stream_s(len(seq))
    with Run("cart", _frontend_args("cart", args.frames, args), args, out) as run:
        run.wait_frames(at, stream + 300)
        run.wait_acked(before_at, 600)
        c = run.counts()
        sdf, v = run.sdf(grid)
        room, _ = run.sdf(pts)
        still_sdf, _ = run.sdf(still_grid)
        unk, still_unk = run.sdf_or_unknown(grid), run.sdf_or_unknown(still_grid)
        rec["standing"] = {"t_s": round(time.monotonic() - run.t0, 1), "frame": c.get("frames"), "map_version": v,
                           "occupied": float(np.mean(sdf < OCCUPIED_M)),
                           "sdf_p10_p50_p90_m": np.round(np.percentile(sdf, [10, 50, 90]), 3).tolist(),
                           "room_error_cm": 100 * float(np.mean(np.abs(room - gt_with))),
                           "still_box": np.round(still.size, 3).tolist(),
                           "still_occupied": float(np.mean(still_sdf < OCCUPIED_M)),
                           "occupied_unknown": float(np.mean(unk < OCCUPIED_M)),
                           "still_occupied_unknown": float(np.mean(still_unk < OCCUPIED_M))}
        st = rec["standing"]
        # Pass 2's first keyframe sees the cart's space empty: a figure taken after it is not the
        # standing cart's (the mapper trailed the walk by more than the pause's first two thirds).
        st["before_removal"] = bool(c.get("frames", 0) < removed)
        if not st["before_removal"]:
            _say(f"cart: WARNING: pass 1's keyframes were acknowledged only at frame {c.get('frames')}, after the "
                 f"removal (frame {removed}): this figure may already see pass 2")
        _say(f"cart: standing (frame {c.get('frames')}, map v{v}): {100 * st['occupied']:.1f} % of its volume "
             f"occupied (served sdf p10/p50/p90 {st['sdf_p10_p50_p90_m']} m; a box that never moved, "
             f"{st['still_box']} m: {100 * st['still_occupied']:.1f} %); the rest of the room "
             f"{st['room_error_cm']:.2f} cm")
        # From the first keyframe that saw its space empty to the last one, every second too.
        rec["clearing"] = []
        last_k = ids.index(last_empty) + 1
        if empty:
            t_first = run.wait_acked(ids.index(empty[0]) + 1, stream + 600)
            rec["first_empty_frame"], rec["first_empty_t_s"] = empty[0], round(t_first - run.t0, 1)
            k = 0
            while run.counts().get("acked", 0) < last_k and time.monotonic() - t_first < stream + 600:
                time.sleep(max(0.0, t_first + k - time.monotonic()))
                sdf, v = run.sdf(grid)
                share = float(np.mean(sdf < OCCUPIED_M))
                rec["clearing"].append({"since_first_s": k, "occupied": share, "map_version": v})
                _say(f"cart: +{k} s after the first keyframe that saw it gone (v{v}): {100 * share:.1f} % occupied")
                k += 1
        t_seen = run.wait_acked(last_k, stream + 600)
        rec["seen_empty_t_s"] = round(t_seen - run.t0, 1)
        for k in range(int(args.watch_s) + 1):
            time.sleep(max(0.0, t_seen + k - time.monotonic()))
            sdf, v = run.sdf(grid)
            share = float(np.mean(sdf < OCCUPIED_M))
            rec["watch"].append({"after_s": k, "occupied": share, "map_version": v})
            _say(f"cart: +{k} s after the last keyframe that saw it gone (v{v}): {100 * share:.1f} % occupied")
        room, v = run.sdf(pts)
        rec["after"] = {"t_s": round(time.monotonic() - run.t0, 1), "map_version": v,
                        "room_error_cm": 100 * float(np.mean(np.abs(room - gt_without))),
                        "occupied_unknown": float(np.mean(run.sdf_or_unknown(grid) < OCCUPIED_M))}
        rec["mapper"] = {k: run.mapper_info().get(k) for k in ("keyframes", "steps", "redundant")}
        rec["frontend"] = run.counts()
    low = [w["after_s"] for w in rec["watch"] if w["occupied"] <= 0.05]
    rec["cleared_after_s"] = low[0] if low else None
    early = [w["since_first_s"] for w in rec["clearing"] if w["occupied"] <= 0.05]
    if early:
        rec["cleared_since_first_s"] = early[0]
    elif low and "first_empty_t_s" in rec:
        rec["cleared_since_first_s"] = round(rec["seen_empty_t_s"] - rec["first_empty_t_s"] + low[0], 1)
    else:
        rec["cleared_since_first_s"] = None
    rec["room_ratio"] = rec["after"]["room_error_cm"] / max(rec["standing"]["room_error_cm"], 1e-9)
    return rec


# ---------------------------------------------------------------- the person


def person(args, out: Path) -> dict:
    from ..synthetic.changes import ChangingSequence

    seq = ChangingSequence(args.building, "person", n_frames=args.frames, seed=args.seed, pause_s=args.pause_s)
    walk, sw = seq.person, seq.person.swept
    _say(f"person: crosses frames {walk.first}-{walk.last} of {len(seq)}; swept volume {np.round(sw.size, 2).tolist()} m "
         f"at {np.round(sw.center, 2).tolist()} (canonical); selecting keyframes here")
    ids, kept = select_keyframes(seq)
    during = [i for i in ids if walk.first <= i <= walk.last]
    free = [i for i in ids if i > walk.last and rays_through(seq, kept[i], seq.true_poses[i], sw) >= 30]
    last_free = free[-1] if free else ids[-1]
    _say(f"person: {len(ids)} keyframes, {len(during)} while it crosses, {len(free)} see its swept volume empty "
         f"after it, the last is frame {last_free}")
    grid = seq.box_points(sw)
    truth = seq.gt_sdf(grid)
    clear = truth >= CLEAR_M  # the share occupied leaves out the floor's neighbourhood (as the cart's)
    rec: dict = {"building": args.building, "frames": len(seq), "stretch": [walk.first, walk.last],
                 "keyframes": len(ids), "keyframes_during": len(during), "keyframes_seeing_free": len(free),
                 "last_free_frame": last_free, "grid_points": len(grid)}
    with Run("person", _frontend_args("person", args.frames, args), args, out) as run:
        t_free = run.wait_acked(ids.index(last_free) + 1, _stream_s(len(seq)) + 600)
        time.sleep(max(0.0, t_free + args.person_after_s - time.monotonic()))
        sdf, v = run.sdf(grid)
        diff = sdf - truth
        rec.update({"seen_free_t_s": round(t_free - run.t0, 1), "after_s": args.person_after_s, "map_version": v,
                    "worst_below_m": float(diff.min()), "occupied": float(np.mean(sdf[clear] < OCCUPIED_M)),
                    "below_20cm": float(np.mean(diff < -0.20)),
                    "mapper": {k: run.mapper_info().get(k) for k in ("keyframes", "steps", "redundant")}})
        # where the worst is, and what each part of the answer says there (exact: the newest
        # map's composition, not the bake's; implicit: the networks alone)
        w = int(np.argmin(diff))
        exact = np.asarray(run.client.query(grid[w:w + 1], exact=True).sdf, np.float64)[0]
        implicit = np.asarray(run.client.query(grid[w:w + 1], source="implicit").sdf, np.float64)[0]
        rec["worst"] = {"canonical": np.round(seq.scene.to_canon(grid[w:w + 1])[0], 3).tolist(),
                        "truth_m": float(truth[w]), "served_m": float(sdf[w]), "exact_m": float(exact),
                        "networks_m": float(implicit)}
        rec["worst_below_m_clear"] = float(diff[clear].min()) if clear.any() else None
        _say(f"person: {args.person_after_s:g} s after (v{v}): served - truth down to {diff.min():+.3f} m "
             f"({100 * rec['below_20cm']:.2f} % of it more than 20 cm below; {rec['worst_below_m_clear']:+.3f} m "
             f"{100 * CLEAR_M:.0f} cm or more from the floor); at the worst point {rec['worst']}; "
             f"{100 * rec['occupied']:.1f} % of the swept volume occupied")
    return rec


# ---------------------------------------------------------------- the drift


def drift(args, out: Path) -> dict:
    from ..synthetic.changes import DRIFT_DEG, DRIFT_M, ChangingSequence

    try:
        from ..poses import send_corrections
    except ImportError:
        send_corrections = None
    seq = ChangingSequence(args.building, "drift", n_frames=args.frames, seed=args.seed)
    _say(f"drift: {len(seq)} frames, the sent poses drifting to {DRIFT_M * 100:.0f} cm and {DRIFT_DEG:g} deg; "
         "selecting keyframes here")
    # The depth is the same in both runs; the selection sees the poses each frontend sends.
    sel_d, sel_t = KeyframeSelector(), KeyframeSelector()
    ids_d, ids_t, true_frames = [], [], []
    for i in range(len(seq)):
        f = seq.true_frame(i)
        if sel_t.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
            ids_t.append(i)
            true_frames.append(f)
        if sel_d.is_keyframe(f["stamp"], f["depth"], f["K"], seq.sent_poses[i]):
            ids_d.append(i)
    pts = eval_points(true_frames, n_points=args.n_points, every=1, rng=0)
    gt = seq.gt_sdf(pts)
    lines = wall_lines(seq, true_frames)
    along = np.arange(-0.1, 1.0 + 1e-9, 0.01)[::-1]  # each line's distance in front of the wall (m)
    front_of_wall = along >= -0.03  # surfaces are counted up to 3 cm behind the wall: beyond, nothing was seen
    at_wall = int(np.argmin(np.abs(along)))
    rec: dict = {"building": args.building, "frames": len(seq), "keyframes_drifting": len(ids_d),
                 "keyframes_true": len(ids_t), "points": len(pts), "lines": len(lines),
                 "corrections_available": send_corrections is not None}

    def measure(run: Run, label: str) -> dict:
        sdf, v = run.sdf(pts)
        prof = [run.sdf(line)[0] for line in lines]
        m = {"t_s": round(time.monotonic() - run.t0, 1), "map_version": v,
             "error_cm": 100 * float(np.mean(np.abs(sdf - gt))),
             "surfaces": [surfaces(x[front_of_wall]) for x in prof],
             "at_wall_cm": [round(100 * float(x[at_wall]), 1) for x in prof],
             "crossings": [crossings(x) for x in prof], "profiles_mm": [np.round(1e3 * x).astype(int).tolist()
                                                                         for x in prof]}
        _say(f"drift: {label} (v{v}): mean error {m['error_cm']:.2f} cm; wall profiles: surfaces met "
             f"{m['surfaces']}, served sdf at the wall {m['at_wall_cm']} cm, zero crossings {m['crossings']}")
        return m

    stream = _stream_s(len(seq))
    with Run("drift-true", _frontend_args(None, args.frames, args), args, out) as run:
        t_end = run.wait_acked(len(ids_t), stream + 600)
        rec["true_end"] = measure(run, "true poses, end of the walk")
        time.sleep(max(0.0, t_end + args.after_s - time.monotonic()))
        rec["true_after"] = measure(run, f"true poses, +{args.after_s:g} s")
    with Run("drift", _frontend_args("drift", args.frames, args), args, out) as run:
        t_end = run.wait_acked(len(ids_d), stream + 600)
        rec["drift_end"] = measure(run, "drifting poses, end of the walk")
        t_sent = time.monotonic()
        if send_corrections is not None:
            try:
                reply = send_corrections(run.session, run.ns, "depth", seq.corrections(ids_d), timeout=60.0)
                rec["corrections_reply"] = {k: v for k, v in dict(reply or {}).items()
                                            if isinstance(v, (int, float, str, bool))}
                _say(f"drift: {len(ids_d)} corrections sent, answered in {time.monotonic() - t_sent:.1f} s: "
                     f"{rec['corrections_reply']}")
            except Exception as e:  # noqa: BLE001 - a mapper without 1.11, or one that refuses: said, not hidden
                rec["corrections_available"] = False
                rec["corrections_error"] = f"{type(e).__name__}: {e}"
                _say(f"drift: the corrections were not applied: {rec['corrections_error']}")
        else:
            _say("drift: aisdf.poses.send_corrections is not in this tree: no corrections sent")
        time.sleep(max(0.0, t_sent + args.after_s - time.monotonic()))
        label = "corrected" if rec["corrections_available"] else "not corrected"
        rec["drift_after"] = measure(run, f"drifting poses, {label}, +{args.after_s:g} s")
    rec["ratio"] = rec["drift_after"]["error_cm"] / max(rec["true_after"]["error_cm"], 1e-9)
    return rec


# ---------------------------------------------------------------- the parked robot


def parked(args, out: Path) -> dict:
    cmd = [sys.executable, "-m", "aisdf.bench.parked", "--frames", str(args.parked_frames), "--steps-every", "10",
           "--walk-frames", "0", "--preset", args.preset]
    _say(f"parked: {' '.join(cmd[1:])}")
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **os.environ}
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
    (out / "parked.log").write_text(p.stdout + p.stderr)
    if p.returncode != 0:
        raise RuntimeError(f"aisdf bench parked failed ({p.returncode}): {p.stderr[-500:]}")
    res = json.loads(p.stdout[p.stdout.index("{"):])["parked"]
    _say(f"parked: {res['frames']} frames: {res['end']['keyframes']} keyframes kept ({res['redundant']} redundant), "
         f"process {res['start']['rss_mb']} -> {res['end']['rss_mb']} MB")
    return res


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="aisdf bench change", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", default=",".join(PARTS), help=f"comma-separated subset of {','.join(PARTS)}")
    p.add_argument("--quick", action="store_true", help="a smoke run: 300-frame passes, short waits, 200 parked "
                   "frames")
    p.add_argument("--building", default="office")
    p.add_argument("--frames", type=int, help="frames of one pass of the walk (default 900; --quick 300)")
    p.add_argument("--pause-s", type=float, help="pause between the passes (default 30; --quick 4)")
    p.add_argument("--watch-s", type=float, help="cart: seconds watched after it is seen gone (default 30; "
                   "--quick 8)")
    p.add_argument("--person-after-s", type=float, default=10.0)
    p.add_argument("--after-s", type=float, help="drift: seconds after the corrections (default 60; --quick 10)")
    p.add_argument("--parked-frames", type=int, help="default 3600; --quick 200")
    p.add_argument("--n-points", type=int, default=20_000, help="evaluation points along the keyframes' rays")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--mapper", choices=["submaps", "single"], help="the mapper (default: the service's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/bench-change")
    a = p.parse_args(argv)
    q = a.quick
    for name, full, quick in (("frames", 900, 300), ("pause_s", 30.0, 4.0), ("watch_s", 30.0, 8.0),
                              ("after_s", 60.0, 10.0), ("parked_frames", 3600, 200)):
        if getattr(a, name) is None:
            setattr(a, name, quick if q else full)
    only = [s.strip() for s in a.only.split(",") if s.strip()]
    bad = [s for s in only if s not in PARTS]
    if bad:
        p.error(f"unknown part(s) {bad}; choose from {','.join(PARTS)}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    np.seterr(all="ignore")
    res: dict = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "commit": commit(),
                 "args": {k: v for k, v in vars(a).items()}}
    t = time.time()
    for part in PARTS:
        if part in only:
            res[part] = {"cart": cart, "person": person, "drift": drift, "parked": parked}[part](a, out)
    res["wall_s"] = round(time.time() - t, 1)
    (out / "change.json").write_text(json.dumps(res, indent=1, default=str))
    md = report(res)
    (out / "change.md").write_text(md + "\n")
    print(md)
    print(f"results in {out / 'change.json'}")
    return res


if __name__ == "__main__":
    main()
