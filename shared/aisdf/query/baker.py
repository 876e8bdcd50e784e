"""The query service's baker: bakes the fused field of the newest map (``aisdf.baked``)
in a background thread and swaps each finished bake in with one reference assignment.

A bake of a new submap map reuses every sample of the previous bake outside the extended
boxes of the submaps that changed (and away from surfels that changed), so a bake costs
what changed, not the building. It runs at a lower CPU priority and at most ``duty`` of
the time, leaving the machine to the answers and a mapper beside it, in bounded units (a
chunk of points: the field, the surfels and the measured points; the activations and the
nearest-point searches of one chunk in memory at a time). While requests wait, the answers
do not wait for it: a trailing bake answers them (``QueryEngine.answer_sdf``). Resting the
bake while requests wait was measured and left out: the space mapped since its last bake
is then answered by the networks for longer, which costs the planners more than the rest
gives them (docs/benchmarks.md, Planners under load).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from ..baked import BakeConfig, BakedField, bake
from ..memory import trim
from ..structure.fusion import DEFAULT_FUSE_RADIUS
from ..structure.surfel_types import Surfels
from .answer import FLOOR_SUPPORT, predicted_layout, served_answer
from .changes import layout_changes, measured_changes, measured_dirty, submaps_changed_at, surfel_dirty
from .mapstate import MapState

log = logging.getLogger(__name__)
BAKE_CHUNK = 2048  # network points per pass while baking: bounds the activations (~15 MB at width 128)


@dataclass(frozen=True)
class BakedMap:
    state: MapState  # the map it was baked from (its network answers points outside the bake)
    field: BakedField
    surfel_ref: Surfels | None = None  # the surfels its samples were computed with (within bake_surfel_tol)
    layout: object = None  # the predicted layout points its samples were capped with (None: none)


def _nowhere(points: np.ndarray) -> np.ndarray:
    return np.zeros(len(points), bool)


class Baker:
    """Bakes the newest map of ``newest()`` whenever ``map_arrived`` says there is one.

    ``field(state, points, gradient) -> (sdf, grad)`` is the map's implicit field (the
    engine's: a network, or the blend of submaps); the fused field adds the surfels."""

    def __init__(self, field: Callable, newest: Callable[[], MapState | None], device: torch.device,
                 chunk_points: int = 65_536, fuse_radius: float = DEFAULT_FUSE_RADIUS,
                 config: BakeConfig | None = None, threads: int = 2, duty: float = 0.75, nice: int = 0,
                 surfel_tol: float = 0.001, enabled: bool = True):
        self.field = field
        self.newest = newest
        self.device = device
        self.chunk_points = chunk_points
        self.fuse_radius = fuse_radius
        self.config = config or BakeConfig()
        self.threads = threads
        self.duty = duty
        self.nice = nice
        self.surfel_tol = float(surfel_tol)
        self.enabled = enabled
        self.layout_prior = True  # 1.13: cap answers at the predicted layout (structure.layout)
        self.warm_unknown = False  # 1.6: a planner asked for unknown distances; index each map's observed space
        self.baked: BakedMap | None = None  # swapped whole under _lock; readers take the reference
        self.bakes = 0
        self.extensions = 0  # bakes of the newly mapped space alone, ahead of a re-bake
        self.last_extension: dict = {}  # the newest one's figures
        self.failures = 0
        self.last: dict = {}  # the newest bake's figures
        self._lock = threading.Lock()
        self._wanted = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._arrivals: deque = deque(maxlen=256)  # ((epoch, version), monotonic arrival) of maps

    def map_arrived(self, state: MapState) -> None:
        """A new map is the newest: note when it came (for ``lag``) and bake it."""
        self._arrivals.append((state.order, state.received))
        self._wanted.set()

    def wake(self) -> None:
        """Bake again (the surfels changed, the map's order did not)."""
        self._wanted.set()

    def layout(self, state: MapState | None):
        """The map's predicted layout points (``answer.predicted_layout``), None without the prior."""
        return predicted_layout(state) if self.layout_prior and state is not None else None

    def fused_fn(self, state: MapState, chunk: int | None = None, layout=False):
        """points (M, 3) -> (sdf, grad) of the fused field of ``state`` (what ``fused``
        answers), in bounded memory: the network in chunks of ``chunk`` points, the
        surfels in chunks of candidate pairs. ``layout``: the predicted layout points to cap
        with (default: ``state``'s)."""
        from ..structure.surfel_map import ExplicitSdf

        chunk = chunk or (BAKE_CHUNK if self.device.type == "cpu" else self.chunk_points)  # on a GPU: big batches
        explicit = ExplicitSdf(state.surfels, chunk_pairs=131_072) if state.surfels is not None and len(
            state.surfels) else None
        lay = self.layout(state) if layout is False else layout

        def fn(pts: np.ndarray):
            sdf = np.empty(len(pts), np.float32)
            grad = np.empty((len(pts), 3), np.float32)

            def one(i: int) -> None:
                # One bounded unit of work: the field, the surfels and the measured points of a chunk.
                q = pts[i:i + chunk]
                f, g = self.field(state, q, True)
                if explicit is not None or state.measured is not None or lay is not None:
                    d_e, g_e = (None, None)
                    if explicit is not None:
                        d_e, g_e, _ = explicit(q.astype(np.float64))
                        d_e, g_e = d_e.astype(np.float32), g_e.astype(np.float32)
                    f, g = served_answer(q, f, g, d_e, g_e, state.measured, self.fuse_radius, layout=lay)
                sdf[i:i + chunk], grad[i:i + chunk] = f, g

            starts = range(0, len(pts), chunk)
            if self.threads > 1 and self.device.type == "cpu" and len(starts) > 1:
                # torch releases the GIL inside its ops: chunks run side by side.
                with ThreadPoolExecutor(self.threads, thread_name_prefix="bake",
                                        initializer=self._lower_priority if self._on_thread() else None) as ex:
                    list(ex.map(one, starts))
            else:
                for i in starts:
                    one(i)
            return sdf, grad

        return fn

    def bake_now(self) -> BakedMap | None:
        """Bake the newest map (if it has observed space and is not baked yet) and swap it in."""
        st = self.newest()
        if st is None or st.observed is None:
            return self.baked
        cur = self.baked
        if cur is not None and cur.state.same_field(st):
            # Nothing to evaluate (the index's version moved on): the same bake answers for it.
            if cur.state.order != st.order or cur.state.surfel_version != st.surfel_version:
                self._warm(st)
                with self._lock:
                    if self.baked is cur:
                        self.baked = BakedMap(st, cur.field, cur.surfel_ref, cur.layout)
            return self.baked
        t = time.perf_counter()
        dirty, ref = self._dirty(cur, st) if cur is not None else (None, st.surfels)
        previous = cur.field if dirty is not None else None
        # Every sample with the same surfels: the reference (surfels that moved less than
        # surfel_tol keep the geometry the reused samples were computed with), so new samples
        # agree with the reused ones also where a tiny move flips a gate (the fusion radius, the
        # measured rule's ramp). A full bake of the new surfels differs from it by those moves.
        layout = self.layout(st)  # of the newest surfels: its moves are what _dirty finds
        fn = self.fused_fn(st if ref is st.surfels else st.with_surfels(ref, st.surfel_version), layout=layout)
        if previous is not None and st.submaps is not None and st.observed is not cur.state.observed:
            # The robot's surroundings first: the space mapped since the bake (its blocks alone,
            # every sample of the bake kept) answers from the newest map within a fraction of the
            # re-bake's time, instead of from the networks at every request until it is done.
            ext = bake(fn, st.observed, self.config, previous=previous, dirty=_nowhere)
            if ext.stats["evaluations"]:
                with self._lock:
                    if self.baked is cur:
                        self.baked = BakedMap(cur.state, ext, cur.surfel_ref, cur.layout)
                previous = ext
                self.extensions += 1
                self.last_extension = ext.stats
        fld = bake(fn, st.observed, self.config, previous=previous, dirty=dirty)
        self._warm(st)
        with self._lock:
            cur = self.baked
            if cur is None or cur.state.order <= st.order:
                self.baked = BakedMap(st, fld, ref, layout)
        self.bakes += 1
        trim()  # the bake's temporaries (and the previous field, once no reader holds it) back to the system
        self.last = {**fld.stats, "wall_s": round(time.perf_counter() - t, 3), "version": st.version,
                     "epoch": st.epoch}
        log.info("baked map version %d: %d blocks (%d fine), %d evaluations (%d reused), %.2f s, %.1f MB",
                 st.version, fld.stats["blocks"], fld.stats["fine_blocks"], fld.stats["evaluations"],
                 fld.stats["reused"], self.last["wall_s"], fld.nbytes / 1e6)
        return self.baked

    def _warm(self, st: MapState) -> None:
        """Once planners ask for unknown distances (1.6): build the map's index of unobserved
        space here, before its bake answers, not in the first request that needs it."""
        if self.warm_unknown and st.observed is not None:
            st.observed.unknown_index()

    def _dirty(self, baked: BakedMap, new: MapState):
        """Where the fused field of ``new`` may differ from the samples of ``baked``: (a
        function of world points (M, 3) -> (M,) bool, or None when it may differ everywhere
        (a new network, a new mapper incarnation or grid); the new surfel reference). The
        blend at a point depends only on the submaps whose extended boxes hold it; the fused
        answer only on surfels within ``fuse_radius`` (surfels that moved less than
        ``surfel_tol``, as all do a little when the Atlanta frame is refined, count as unchanged)
        and measured points (1.4) within ``fuse_radius``: those of changed submaps that moved."""
        old = baked.state
        if (old.submaps is None) != (new.submaps is None) or old.epoch != new.epoch:
            return None, new.surfels
        if new.submaps is None:
            if old.net is not new.net:
                return None, new.surfels
            changed, grid, cells = [], None, None
        else:
            if not old.submaps.grid.same_as(new.submaps.grid):
                return None, new.surfels
            changed, grid = new.submaps.changed_since(old.submaps), new.submaps.grid
            cells, old_cells = set(new.submaps.submaps), set(old.submaps.submaps)
        grow = self.fuse_radius + 0.05
        near_changed_surfel, ref = surfel_dirty(baked.surfel_ref, new.surfels, self.surfel_tol, grow)
        moved = measured_changes(old.submaps, new.submaps, changed) if grid is not None else None
        new_layout = self.layout(new)
        layout_moved = layout_changes(baked.layout, new_layout)

        def dirty(points: np.ndarray) -> np.ndarray:
            d = near_changed_surfel(points)
            if moved is not None:  # a measured point counts within fuse_radius, where it is the nearest
                # (or, 1.15's floor, within FLOOR_SUPPORT of the nearest surfel's point it supports)
                d |= measured_dirty(moved, new.measured, points, grow, support=FLOOR_SUPPORT)
            if layout_moved is not None:  # the same rule for the predicted points
                d |= measured_dirty(layout_moved, new_layout, points, grow)
            if grid is not None:
                d |= submaps_changed_at(grid, cells, old_cells, changed, points)
            return d

        return dirty, ref

    def _lower_priority(self) -> None:
        """Bake with a lower CPU priority (Linux nice is per thread): a mapper or the answers
        on the same machine go first, the bake takes what is left."""
        if self.nice and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
            except OSError as e:  # not permitted, or not Linux: bake at normal priority
                log.debug("could not lower the baker's priority: %s", e)

    def _loop(self) -> None:
        self._lower_priority()
        while not self._stop.is_set():
            if not self._wanted.wait(0.5):
                continue
            self._wanted.clear()
            t = time.monotonic()
            try:
                self.bake_now()
            except Exception:  # noqa: BLE001 - keep answering from the last good bake / the network
                self.failures += 1
                log.exception("bake failed; answers keep coming from the previous bake or the network")
            # Bake at most duty of the time: with weights every second, rest a third of
            # the bake's time (at 0.75), leaving some of the machine to the mapper and the answers.
            took = time.monotonic() - t
            self._stop.wait(took * (1.0 / self.duty - 1.0))

    def start(self) -> None:
        """Start the background baker (no-op when baking is off)."""
        if self.enabled and self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="baker", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def _on_thread(self) -> bool:
        return self._thread is not None and threading.current_thread() is self._thread

    def lag(self) -> dict:
        """How far answers trail the newest weights, now: ``versions`` behind, and ``behind_s``:
        seconds since the first weights newer than the answering ones arrived (0 when the
        newest map answers)."""
        st, bk = self.newest(), self.baked
        if st is None:
            return {"versions": 0, "behind_s": 0.0}
        if bk is None or bk.state.order >= st.order:
            return {"versions": 0, "behind_s": 0.0}
        newer = [(o, t) for o, t in list(self._arrivals) if o > bk.state.order]
        first = min(t for _, t in newer) if newer else st.received
        return {"versions": len(newer), "behind_s": round(time.monotonic() - first, 3)}
