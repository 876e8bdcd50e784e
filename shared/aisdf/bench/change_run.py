"""The harness of ``aisdf bench change`` (:mod:`aisdf.bench.change`): the three services on
loopback for one change, the keyframes the frontend selects seen from here, the rays that saw a
box's space empty, the office box most like the cart, and the lines crossing walls the drift
part measures the served sdf along."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np

from .. import keys, transport
from ..client import SdfClient
from ..geometry import ray_dirs_C
from ..keyframes import KeyframeSelector
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



# ---------------------------------------------------------------- the boxes



def still_box(seq):
    """The building's box most like the cart that never moves (the office's cabinet, 0.8 x
    0.45 x 1.0 m): the share of it answered occupied is what the cart's can be compared with."""
    from ..synthetic.changes import CART_SIZE, BoxPlacement

    bx = seq.scene.boxes
    k = int(np.argmin(np.abs(2 * bx.halves - np.asarray(CART_SIZE)).sum(axis=1)))
    R = bx.rotations[k]
    return BoxPlacement(bx.centers[k], float(np.arctan2(R[1, 0], R[0, 0])), 2 * bx.halves[k])



# ---------------------------------------------------------------- lines crossing walls

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
