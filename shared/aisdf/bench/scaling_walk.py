"""The walk of ``aisdf bench scaling`` (``scaling.py`` holds its config, report and entry
point): a scene's keyframes added one per period of wall time while the mapper steps in
between, the bytes its publications would take, and the errors, with the clock paused while
scoring and encoding."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from ..structure.measured import MeasuredPoints, MeasuredSurface

if TYPE_CHECKING:
    from .scaling_config import ScalingConfig

log = logging.getLogger("aisdf.bench.scaling")


class _Clock:
    """Wall seconds since start, less the paused intervals."""

    def __init__(self) -> None:
        self.t0, self.paused = time.perf_counter(), 0.0

    def __call__(self) -> float:
        return time.perf_counter() - self.t0 - self.paused

    @contextmanager
    def pause(self):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.paused += time.perf_counter() - t


def scene_frames(name: str, cfg: ScalingConfig) -> tuple[Any, list[dict], float]:
    """The sequence, its keyframes rendered up front, and its stream seconds per keyframe.
    A building with a floor plan is walked whole: at 1 keyframe per stream second when
    ``keyframes`` cover the walk, else spread evenly over it."""
    from ..synthetic import PLANS, SyntheticSequence
    from ..synthetic.trajectory import walk_duration

    n = cfg.keyframes
    fps = 1.0 if name not in PLANS else min(1.0, n / walk_duration(PLANS[name]()))
    seq = SyntheticSequence(building=name, n_frames=n, H=cfg.H, W=cfg.W, fps=fps, noise=cfg.noise, seed=cfg.seed)
    return seq, [seq.frame(i) for i in range(n)], 1.0 / fps


def frame_of(f: dict):
    """The mapping Frame of a synthetic frame dict (what the walk adds as a keyframe)."""
    from ..mapping.frames import Frame

    return Frame(int(f["frame_id"]), float(f["stamp"]), f["depth"], f["K"], f["T_WC"])


TOO_HIGH_M = 0.05  # an answer this far above the exact SDF promises a planner room that is not there
# A point's nearest surface is "unmeasured" when the nearest measured point and the surfel map are both
# farther than |exact SDF| + this: no keyframe saw that surface (docs/experiments/scaling-notes.md: "Where the floor's
# remaining error is")
UNMEASURED_M = 0.05


class _Scorer:
    """Fixed evaluation points with their exact SDF. ``evaluate(pipe, measured)`` -> mean
    |error| in cm and the share of points (%) where the answer is more than ``TOO_HIGH_M``
    above the exact SDF (the unsafe side for a planner), per answer: the network alone
    (``implicit``), the network and the surfel map (``fused``, ``aisdf.structure.fusion``:
    protocol 1.3's answer), that with the measured surface (``measured``,
    ``structure.measured``; ``measured`` gives the distance to the nearest measured point),
    and what ``query/sdf`` serves by default for this mapper (``served``: ``measured`` when
    the mapper publishes measured points, protocols 1.4 and 1.5, else ``fused``), and the
    smaller of that and the distance to unobserved space (``unknown_occupied``: a planner
    that treats unknown space as occupied, protocol 1.6); and, given
    ``measured``, where the error of ``source``'s answer is: the share of points whose
    nearest surface no keyframe measured (``UNMEASURED_M``), their part of the mean error
    and the mean error on the other points. ``near_furniture`` (N,) bool (the labelled
    buildings, ``evaluation.near_furniture_mask``; None: unknown): ``evaluate_split`` also
    gives the error near furniture and away from it.
    ``score(pipe, source, measured)`` one of the means."""

    def __init__(self, points: np.ndarray, gt: np.ndarray, near_furniture: np.ndarray | None = None):
        self.points, self.gt, self.near_furniture = points, gt, near_furniture

    def _answers(self, pipe, measured=None) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """The answers, and the distance to the nearest observed surface (surfel or measured
        point; None without ``measured``)."""
        from ..query.answer import served_answer
        from ..structure.surfel_map import explicit_sdf

        f = np.asarray(pipe.sdf(self.points), dtype=np.float64)
        s = pipe.surfels()
        d_e = explicit_sdf(self.points, s)[0] if s is not None and len(s) else None
        out = {"implicit": f, "fused": np.asarray(served_answer(self.points, f, None, d_e, None, None)[0], np.float64)}
        observed = None
        if measured is not None:
            out["measured"] = np.asarray(served_answer(self.points, f, None, d_e, None, measured)[0], np.float64)
            d_m = measured.distance(self.points)
            observed = np.minimum(np.inf if d_e is None else np.abs(d_e), d_m)
        out["served"] = out["measured"] if serves_measured(pipe) and measured is not None else out["fused"]
        grid = _observed_grid(pipe)
        if grid is not None:  # protocol 1.6: a planner that treats unknown space as occupied
            out["unknown_occupied"] = np.minimum(out["served"], grid.unknown_distance(self.points))
        return out, observed

    def evaluate(self, pipe, measured=None, source: str = "served") -> tuple[dict, dict, dict]:
        """(mean |error| in cm, % of points more than TOO_HIGH_M above the truth) per answer, and
        for ``source``'s answer, given ``measured``: {"points_pct": share of points whose nearest
        surface is unmeasured, "error_cm": their part of the mean error, "rest_error_cm": the
        mean error on the others} (empty without ``measured``)."""
        return self.evaluate_split(pipe, measured, source)[:3]

    def evaluate_split(self, pipe, measured=None, source: str = "served") -> tuple[dict, dict, dict, dict]:
        """``evaluate``'s three, and for ``source``'s answer near furniture: {"points_pct": share of
        points near furniture, "error_cm": the mean error there, "away_error_cm": elsewhere, and
        given ``measured`` "unmeasured_pct" / "unmeasured_error_cm": near furniture with an
        unmeasured nearest surface} (empty where the points carry no labels)."""
        ans, observed = self._answers(pipe, measured)
        mae = {k: round(100.0 * float(np.mean(np.abs(v - self.gt))), 3) for k, v in ans.items()}
        high = {k: round(100.0 * float(np.mean(v - self.gt > TOO_HIGH_M)), 3) for k, v in ans.items()}
        unmeasured = {}
        if observed is not None:
            err = np.abs(ans[source] - self.gt)
            m = observed - np.abs(self.gt) > UNMEASURED_M
            unmeasured = {"points_pct": round(100.0 * float(m.mean()), 3),
                          "error_cm": round(100.0 * float(err[m].sum()) / len(err), 3),
                          "rest_error_cm": round(100.0 * float(err[~m].mean()), 3) if (~m).any() else 0.0}
        near: dict = {}
        if self.near_furniture is not None:
            err, nf = np.abs(ans[source] - self.gt), self.near_furniture
            mean = lambda k: round(100.0 * float(err[k].mean()), 3) if k.any() else None  # noqa: E731
            near = {"points_pct": round(100.0 * float(nf.mean()), 3), "error_cm": mean(nf), "away_error_cm": mean(~nf)}
            if observed is not None:
                um = nf & (observed - np.abs(self.gt) > UNMEASURED_M)
                near.update(unmeasured_pct=round(100.0 * float(um.mean()), 3), unmeasured_error_cm=mean(um))
        return mae, high, unmeasured, near

    def score(self, pipe, source: str = "served", measured=None) -> float:
        return self.evaluate(pipe, measured, source)[0][source]


_GRID: dict = {}  # the newest observed space scored and its grid: the rooms and the whole share one build


def _observed_grid(pipe):
    """The mapper's observed space as a grid (what the query service gets), or None. Built
    once per state of the space: it only grows, so its voxel count tells a change; the space
    itself is held, so no other object can take its identity while cached."""
    space = getattr(pipe, "observed", None)
    if space is None or not len(space):
        return None
    if _GRID.get("space") is not space or _GRID.get("n") != len(space):
        _GRID.clear()
        _GRID.update(space=space, n=len(space), grid=space.grid())
    return _GRID["grid"]


def serves_measured(pipe) -> bool:
    """Does this mapper publish measured points (by default: protocol 1.4 with submaps, 1.5 with one network)?"""
    return pipe.measured is not None


def measured_of(pipe, pooled: MeasuredSurface):
    """The measured points the answers use: those the mapper publishes (the union of its
    submaps' points, what the query service holds) when it publishes some, else the bench's
    own pool of every keyframe (an answer no service gives for this mapper)."""
    if serves_measured(pipe):
        return MeasuredPoints(pipe.measured_points())
    return pooled


def _pool_record(pipe, pooled: MeasuredSurface | None, add_ms: list[float]) -> dict:
    """Voxels, bytes and milliseconds per keyframe of the measured surface the answers used,
    and who pooled it (the mapper, on the clock, or the bench, off it)."""
    if pooled is None:
        held, ms, by = pipe.measured, pipe.stats().get("measured"), "mapper"
    else:
        held, ms, by = pooled, (float(np.mean(add_ms)) if add_ms else None), "bench"
    return {"voxels": len(held), "bytes": held.nbytes(), "add_ms_mean": None if ms is None else round(ms, 2),
            "pooled_by": by}


def whole_scorer(seq, frames: list[dict], cfg: ScalingConfig) -> _Scorer:
    from ..metrics import eval_points

    from .evaluation import near_furniture_mask

    p = eval_points(frames, n_points=cfg.n_points, every=1, rng=np.random.default_rng([cfg.seed, 7]), far_margin=0.1)
    near = near_furniture_mask(seq.scene, p) if getattr(seq.scene, "kinds", None) is not None else None
    return _Scorer(p, seq.gt_sdf(p), near)


def _room_scorer(seq, frames: list[dict], room: str, cfg: ScalingConfig) -> _Scorer | None:
    from ..metrics import eval_points

    if not frames:
        return None
    idx = seq.plan.names.index(room)
    p = eval_points(frames, n_points=4 * cfg.n_room_points, every=1, rng=np.random.default_rng([cfg.seed, 8, idx]),
                    far_margin=0.1)
    p = p[seq.region_of(p) == idx][: cfg.n_room_points]
    return _Scorer(p, seq.gt_sdf(p)) if len(p) >= 20 else None


def room_ratio(room: dict) -> float | None:
    """A room's error at the end over its error just after its visit (None if either is missing or 0)."""
    a, e = room.get("after_visit_cm"), room.get("end_cm")
    return round(e / a, 3) if a and e is not None else None


def _msg_bytes(msgs) -> int:
    return int(sum(len(k) + len(v) for k, v in msgs))


def walk(pipe, seq, frames: list[dict], stream_per_kf: float, cfg: ScalingConfig, whole: _Scorer,
         say: Callable[[str], None] = lambda s: None) -> dict:
    """One method on one scene; see the module docstring. Returns the run's record."""
    n, P = len(frames), cfg.period_s
    # Events in wall seconds: rooms scored after their visit, the walk's end, the end.
    events: list[tuple[float, str, str]] = []
    for room, (t_in, t_out) in getattr(seq, "visits", {}).items():
        left = t_out / stream_per_kf * P  # wall time at which the camera leaves the room
        events.append((min(left + cfg.after_visit_s, n * P), "room", room))
    t_walk = n * P
    events += [(t_walk, "walk_end", ""), (t_walk + cfg.tail_s, "end", "")]
    events.sort(key=lambda e: (e[0], e[1] != "room"))
    step_ms: list[float] = []
    periods: list[dict] = []
    rooms: dict[str, dict] = {}
    scorers: dict[str, _Scorer] = {}
    rec: dict[str, Any] = {"rejected": 0}
    late: list[float] = []  # how long after its time each keyframe was added (a busy mapper is late)
    # The measured surface the answers use: the mapper's own pool when it publishes one (the
    # submap mapper pools inside add_keyframe, on the clock), else the bench's pool of every
    # keyframe, built while the clock is paused (an answer no service gives for that mapper).
    measured = None if serves_measured(pipe) else MeasuredSurface(max_depth=pipe.cfg.max_depth)
    measured_ms: list[float] = []
    clock = _Clock()
    next_kf, next_period, version = 0, P, 1
    while True:
        t = clock()
        if next_kf < n and t >= next_kf * P:
            late.append(t - next_kf * P)
            try:
                pipe.add_keyframe(frame_of(frames[next_kf]))
            except ValueError as e:
                rec["rejected"] += 1
                log.info("keyframe %d rejected: %s", next_kf, e)
            else:  # the bench's pool: its time is reported, not taken from training
                if measured is not None:
                    with clock.pause():
                        s = time.perf_counter()
                        f = frames[next_kf]
                        measured.add(f["depth"], f["K"], f["T_WC"])
                        measured_ms.append(1e3 * (time.perf_counter() - s))
            next_kf += 1
            continue
        if t >= next_period:
            with clock.pause():
                changed = pipe.map_messages(version)  # marks what it sends as published
                full = pipe.map_messages(version, changed_only=False, mark=False)
            periods.append({"t": round(next_period, 3), "walking": next_period <= t_walk + 1e-9,
                            "bytes": _msg_bytes(changed), "messages": len(changed), "bytes_all": _msg_bytes(full),
                            "messages_all": len(full)})
            next_period += P
            version += 1
            continue
        if events and t >= events[0][0]:
            when, kind, room = events.pop(0)
            with clock.pause():
                if kind == "room":
                    t_in, t_out = seq.visits[room]
                    vis = [f for f in frames[:next_kf] if t_in - 1e-9 <= f["stamp"] <= t_out + 1e-9]
                    sc = _room_scorer(seq, vis, room, cfg)
                    if sc is not None:
                        scorers[room] = sc
                        rooms[room] = {"t_after_visit": round(when, 2), "t_scored": round(t, 2), "points": len(sc.points),
                                       "keyframes": len(vis),
                                       "after_visit_cm": sc.score(pipe, cfg.source, measured_of(pipe, measured))}
                        say(f"  {room}: {rooms[room]['after_visit_cm']:.2f} cm just after its visit "
                            f"({len(vis)} keyframes, t = {when:.0f} s)")
                else:
                    key = "walk_end" if kind == "walk_end" else "end"
                    pts = measured_of(pipe, measured)
                    both, high, unmeasured, near = whole.evaluate_split(pipe, pts, cfg.source)
                    rec[f"unmeasured_{key}"] = unmeasured
                    rec[f"near_furniture_{key}"] = near
                    rec[f"error_{key}_cm"] = both[cfg.source]
                    rec[f"error_{key}_by_source_cm"] = both
                    rec[f"too_high_{key}_pct"] = high[cfg.source]
                    rec[f"too_high_{key}_by_source_pct"] = high
                    rec[f"memory_{key}"] = {k: int(v) for k, v in pipe.memory().items()}
                    rec[f"steps_{key}"] = int(pipe.steps)
                    rec[f"t_{key}"] = round(t, 2)  # when it was scored (later than planned on a busy machine)
                    for r, sc in scorers.items():
                        rooms[r][f"{key}_cm"] = sc.score(pipe, cfg.source, pts)
                    say(f"  {'end of the walk' if key == 'walk_end' else f'+{cfg.tail_s:g} s'}: "
                        f"{rec[f'error_{key}_cm']:.2f} cm, {pipe.steps} steps")
            if kind == "end":
                break
            continue
        if pipe.n_keyframes == 0:  # nothing to train on yet
            time.sleep(max(0.0, min(next_kf * P, next_period) - t))
            continue
        s = time.perf_counter()
        pipe.step()
        step_ms.append(1e3 * (time.perf_counter() - s))
    walking = [p for p in periods if p["walking"]]
    mem = rec["memory_end"]
    total = int(sum(mem.values()))
    for r in rooms.values():
        r["ratio_end"] = room_ratio(r)
    rec.update({
        "keyframes": int(pipe.n_keyframes), "steps": int(pipe.steps),
        "step_ms": {"mean": round(float(np.mean(step_ms)), 2) if step_ms else None,
                    "p95": round(float(np.percentile(step_ms, 95)), 2) if step_ms else None, "n": len(step_ms)},
        "keyframe_late_s": {"mean": round(float(np.mean(late)), 3) if late else None,
                            "max": round(float(np.max(late)), 3) if late else None},
        "memory_bytes": total, "memory_per_keyframe": int(total / max(pipe.n_keyframes, 1)),
        "bytes_per_s": round(sum(p["bytes"] for p in walking) / (len(walking) * P), 1) if walking else None,
        "bytes_per_s_all": round(sum(p["bytes_all"] for p in walking) / (len(walking) * P), 1) if walking else None,
        "bytes_per_s_tail": round(sum(p["bytes"] for p in periods if not p["walking"])
                                  / max(1, len(periods) - len(walking)) / P, 1),
        "rooms": rooms, "periods": periods,
        "measured_surface": _pool_record(pipe, measured, measured_ms),
    })
    rec["bytes_ratio"] = round(rec["bytes_per_s"] / rec["bytes_per_s_all"], 4) if rec["bytes_per_s_all"] else None
    return rec
