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

from .. import keys, transport
from ..client import SdfClient
from ..geometry import ray_dirs_C
from ..keyframes import KeyframeSelector
from ..metrics import eval_points
from ..stack import Stack, wait_for

PARTS = ("cart", "person", "drift", "parked")
OCCUPIED_M = 0.05
NEAR_CART_M = 0.3
CLEAR_M = 0.1  # lattice points nearer another surface (the floor) are left out of the shares occupied


def _say(s: str) -> None:
    print(s, flush=True)


def commit() -> str:
    try:
        here = Path(__file__).resolve().parent
        c = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                           timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return (c or "unknown") + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# ---------------------------------------------------------------- the frames, seen from here


def select_keyframes(seq, frames=None) -> tuple[list[int], dict[int, dict]]:
    """The frame ids the frontend's default selection picks from ``seq`` (its frames as the
    frontend gets them), and those frames."""
    sel, ids, kept = KeyframeSelector(), [], {}
    for i in range(len(seq)) if frames is None else frames:
        f = seq.frame(i)
        if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
            ids.append(i)
            kept[i] = f
    return ids, kept


def rays_through(seq, frame: dict, T_WC: np.ndarray, box, shrink: float = 0.05) -> int:
    """How many of the frame's measured rays pass through ``box`` (a ``BoxPlacement``, shrunk
    by ``shrink`` on every side) before their surface: pixels that saw its space empty."""
    depth = np.asarray(frame["depth"], np.float64)
    ok = depth.ravel() > 0
    d_C = ray_dirs_C(frame["K"], *depth.shape).reshape(-1, 3)[ok] * depth.ravel()[ok, None]
    T = seq.scene.T_canon_W @ T_WC
    o = T[:3, 3]
    seg = d_C @ T[:3, :3].T  # camera centre -> surface, canonical
    from ..synthetic.scene import rot_z

    R = rot_z(box.yaw)
    o_l, s_l = (o - box.center) @ R, seg @ R
    h = np.maximum(box.halves - shrink, 1e-3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-h - o_l) / s_l, (h - o_l) / s_l
    t_in = np.nanmax(np.minimum(t1, t2), axis=1)
    t_out = np.nanmin(np.maximum(t1, t2), axis=1)
    return int(np.count_nonzero((t_in < t_out) & (t_out > 0) & (t_in < 1)))


# ---------------------------------------------------------------- the services


class Run:
    """The three services on loopback for one change: query and mapper first, then the
    frontend streaming ``frontend_args``; ``counts()`` is the frontend's info."""

    def __init__(self, name: str, frontend_args: list[str], args, out: Path):
        self.ns = f"aisdf/bench-change-{name}"
        mapper = ["--preset", args.preset] + (["--mapper", args.mapper] if args.mapper else [])
        self.stack = Stack(services=("query", "mapper", "frontend"), namespace=self.ns,
                           args={"mapper": mapper, "frontend": frontend_args + ["--set", "linger=true"]},
                           log_dir=out / "logs" / name)
        self.client: SdfClient | None = None

    def __enter__(self) -> "Run":
        self.stack.start(["query", "mapper"])
        self.client = SdfClient(self.ns, zenoh=self.stack.client_zenoh, timeout=60.0)
        wait_for(lambda: transport.get_latest(self.session, keys.key(self.ns, "info/mapper"), 1.0), 120,
                 what="the mapper")
        self.stack.start(["frontend"])
        self.t0 = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        self.stack.stop()

    @property
    def session(self):
        return self.client._session

    def counts(self) -> dict:
        return transport.get_latest(self.session, keys.key(self.ns, "info/frontend"), 1.0) or {}

    def wait_acked(self, n: int, timeout: float) -> float:
        """Wait until the frontend has ``n`` keyframes acknowledged; the time (monotonic)."""
        wait_for(lambda: self.counts().get("acked", 0) >= n, timeout, period=0.25,
                 what=f"{n} keyframes acknowledged")
        return time.monotonic()

    def wait_frames(self, n: int, timeout: float) -> None:
        wait_for(lambda: self.counts().get("frames", 0) >= n, timeout, period=0.25, what=f"frame {n}")

    def sdf(self, points: np.ndarray) -> tuple[np.ndarray, int]:
        r = self.client.query(points)
        return np.asarray(r.sdf, np.float64), r.map_version

    def sdf_or_unknown(self, points: np.ndarray) -> np.ndarray:
        """min(sdf, distance to unobserved space) (protocol 1.6): the answer of a planner that
        treats unknown space as occupied, as Voxblox users do."""
        r = self.client.query(points, unknown=True)
        return np.minimum(np.asarray(r.sdf, np.float64), np.asarray(r.unknown, np.float64))

    def mapper_info(self) -> dict:
        return transport.get_latest(self.session, keys.key(self.ns, "info/mapper"), 1.0) or {}


def _stream_s(n_frames: int, fps: float = 30.0) -> float:
    return n_frames / fps


def _frontend_args(change: str | None, n: int, args) -> list[str]:
    a = ["--building", args.building, "--set", f"n_frames={n}", "--set", f"seed={args.seed}"]
    if change:
        a += ["--set", f"change={change}", "--set", f"change_pause_s={args.pause_s}"]
    return a


# ---------------------------------------------------------------- the cart


def still_box(seq):
    """The building's box most like the cart that never moves (the office's cabinet, 0.8 x
    0.45 x 1.0 m): the share of it answered occupied is what the cart's can be compared with."""
    from ..synthetic.changes import CART_SIZE, BoxPlacement

    bx = seq.scene.boxes
    k = int(np.argmin(np.abs(2 * bx.halves - np.asarray(CART_SIZE)).sum(axis=1)))
    R = bx.rotations[k]
    return BoxPlacement(bx.centers[k], float(np.arctan2(R[1, 0], R[0, 0])), 2 * bx.halves[k])


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


def wall_lines(seq, frames: list[dict], n_lines: int = 3, front: float = 1.0, behind: float = 0.1):
    """Lines (n, P, 3), 1 cm apart, crossing a room wall along its normal from ``front`` m
    in front of it to ``behind`` m behind it: where a keyframe's middle row first hits a
    wall with no other surface within 0.3 m of the line (keyframes a quarter, half and three
    quarters into the walk)."""
    sc, lines = seq.scene, []
    for q in np.linspace(0.25, 0.75, n_lines):
        start = int(q * (len(frames) - 1))
        for f in frames[start:] + frames[:start]:  # from there on, the first that shows a wall
            line = _wall_line(sc, f, front, behind)
            if line is not None:
                lines.append(line)
                break
    return np.array(lines)


def _wall_line(sc, f: dict, front: float, behind: float) -> np.ndarray | None:
    """The line of ``wall_lines`` in frame ``f`` (None: its middle row shows no such wall)."""
    H, W = f["depth"].shape
    d_C = ray_dirs_C(f["K"], H, W)[H // 2]
    order = np.argsort(np.abs(np.arange(W) - W // 2))
    T = f["T_WC"]
    dirs = d_C[order] @ T[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, nrm = sc.raycast(np.repeat(T[None, :3, 3], len(dirs), 0), dirs, return_normals=True)
    hit = T[:3, 3] + t[:, None] * dirs
    horizontal = np.abs(nrm @ sc.up_W) < 0.05
    ok = np.isfinite(t) & horizontal & (np.abs(sc.room.sdf_grad(sc.to_canon(np.where(np.isfinite(hit), hit, 0)))[0])
                                        < 1e-6)
    s = np.arange(-behind, front + 1e-9, 0.01)[::-1]
    for k in np.flatnonzero(ok):  # the first whose line has no other surface within 0.3 m
        line = hit[k] + s[:, None] * nrm[k]
        if np.all(sc.sdf(line[s > 0]) >= np.minimum(s[s > 0], 0.3) - 0.01):
            return line
    return None


def crossings(sdf: np.ndarray) -> int:
    """Sign changes along a profile."""
    s = np.sign(sdf[sdf != 0])
    return int(np.count_nonzero(s[1:] != s[:-1]))


def surfaces(sdf: np.ndarray, near: float = 0.02, apart: float = 0.05) -> int:
    """Surfaces met along a profile: the stretches where the served sdf is below ``near``,
    two of them counted apart only when the sdf rises above ``apart`` between them (a ghost
    wall 20 cm in front of the wall is one more; a profile that wavers about ``near`` at the
    wall is not; what lies behind the wall, where nothing was seen, can be either sign, so it
    does not count twice)."""
    n, state = 0, "far"
    for x in np.asarray(sdf, np.float64):
        if x < near and state == "far":
            n, state = n + 1, "near"
        elif x > apart:
            state = "far"
    return n


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


# ---------------------------------------------------------------- the report


def _yes(ok: bool | None) -> str:
    return "-" if ok is None else ("yes" if ok else "no")


def rows(res: dict) -> list[tuple[str, str, str, str]]:
    """(criterion, figure, target, met) of every part that ran."""
    out = []
    c = res.get("cart")
    if c:
        s = c["standing"]["occupied"]
        late = "" if c["standing"].get("before_removal", True) else " (measured after the removal!)"
        out.append((f"cart: its volume answered occupied while it stands{late}", f"{100 * s:.1f} %", ">= 80 %",
                    _yes(s >= 0.8)))
        out.append(("(beside it: a box of the office that never moved, answered occupied)",
                    f"{100 * c['standing']['still_occupied']:.1f} %", "", ""))
        if "occupied_unknown" in c["standing"]:
            su = c["standing"]["occupied_unknown"]
            out.append(("cart: the same for a planner treating unknown space as occupied (min(sdf, unknown), 1.6)",
                        f"{100 * su:.1f} % (the still box {100 * c['standing']['still_occupied_unknown']:.1f} %)",
                        ">= 80 %", _yes(su >= 0.8)))
        if "occupied_unknown" in c.get("after", {}):
            out.append(("cart: at the end, for a planner treating unknown space as occupied",
                        f"{100 * c['after']['occupied_unknown']:.1f} %", "<= 5 %",
                        _yes(c["after"]["occupied_unknown"] <= 0.05)))
        w = c["watch"]
        at10 = next((x["occupied"] for x in w if x["after_s"] == 10), w[-1]["occupied"])
        out.append((f"cart: still occupied 0 / {min(10, w[-1]['after_s'])} / {w[-1]['after_s']} s after the last "
                    "keyframe that saw it gone", f"{100 * w[0]['occupied']:.1f} / {100 * at10:.1f} / "
                    f"{100 * w[-1]['occupied']:.1f} %", "", ""))
        t = c["cleared_after_s"]
        out.append(("cart: time until <= 5 % occupied", f"{t} s" if t is not None else
                    f"not within {w[-1]['after_s']} s", "<= 10 s", _yes(t is not None and t <= 10)))
        if c.get("first_empty_frame") is not None:
            t1 = c.get("cleared_since_first_s")
            gap = c["seen_empty_t_s"] - c["first_empty_t_s"]
            out.append((f"(the same, from the first keyframe that saw it gone, {gap:.0f} s before the last)",
                        f"{t1} s" if t1 is not None else "not within the watch", "", ""))
        out.append(("cart: rest of the room's mean error, standing -> after",
                    f"{c['standing']['room_error_cm']:.2f} -> {c['after']['room_error_cm']:.2f} cm "
                    f"(x{c['room_ratio']:.2f})", "<= x1.10", _yes(c["room_ratio"] <= 1.10)))
    p = res.get("person")
    if p:
        out.append((f"person: most negative served - truth over its swept volume, {p['after_s']:g} s after",
                    f"{100 * p['worst_below_m']:+.1f} cm", ">= -20 cm", _yes(p["worst_below_m"] >= -0.20)))
        out.append(("person: swept volume answered occupied", f"{100 * p['occupied']:.1f} %", "", ""))
    d = res.get("drift")
    if d:
        fixed = "corrected" if d["corrections_available"] else \
            f"NOT corrected ({(d.get('corrections_error') or 'no aisdf.poses').split(':')[0]})"
        out.append((f"drift: mean error +{res['args']['after_s']:g} s, {fixed} vs true poses",
                    f"{d['drift_after']['error_cm']:.2f} vs {d['true_after']['error_cm']:.2f} cm (x{d['ratio']:.2f})",
                    "<= x1.2", _yes(d["ratio"] <= 1.2) if d["corrections_available"] else "-"))
        out.append(("drift: surfaces met along lines crossing walls, drifting at the end / after / true poses",
                    f"{d['drift_end']['surfaces']} / {d['drift_after']['surfaces']} / "
                    f"{d['true_after']['surfaces']}", "1 each (after)",
                    _yes(all(x == 1 for x in d["drift_after"]["surfaces"])) if d["corrections_available"] else "-"))
        out.append(("drift: served sdf at the walls (cm), drifting at the end / after / true poses",
                    f"{d['drift_end'].get('at_wall_cm')} / {d['drift_after'].get('at_wall_cm')} / "
                    f"{d['true_after'].get('at_wall_cm')}", "", ""))
        out.append(("drift: their zero crossings, drifting at the end / after / true poses",
                    f"{d['drift_end']['crossings']} / {d['drift_after']['crossings']} / "
                    f"{d['true_after']['crossings']}", "", ""))
    k = res.get("parked")
    if k:
        out.append((f"parked: keyframes kept of {k['frames']:,} frames at one pose",
                    f"{k['end']['keyframes']} ({k['redundant']:,} redundant)", "", ""))
        out.append(("parked: process memory start -> end",
                    f"{k['start']['rss_mb']} -> {k['end']['rss_mb']} MB "
                    f"({k['end']['rss_mb'] - k['start']['rss_mb']:+.1f})", "", ""))
    return out


def report(res: dict) -> str:
    a = res["args"]
    lines = [f"Changing scenes: {a['building']} (seed {a['seed']}), {a['frames']}-frame passes, mapper preset "
             f"{a['preset']}; frontend, mapper and query as processes over Zenoh on loopback; {res['date']}, "
             f"commit {res['commit']}; {res['wall_s']:.0f} s.", "",
             "| criterion | figure | target | met |", "|---|---|---|---|"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} |" for r in rows(res)]
    return "\n".join(lines)


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
