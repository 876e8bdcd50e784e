"""The replay's models (``aisdf.bench.methods``): the compute clock each one runs on, the
interface the replay feeds (``Runner``) and the Voxblox-like voxel map (``VoxelRunner``); the
networks' runner is :class:`aisdf.bench.methods.NeuralRunner`."""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np


class ComputeClock:
    """Seconds of a model's own compute: the sum of the measured blocks, times ``slowdown``."""

    def __init__(self, timer: Callable[[], float] = time.perf_counter, slowdown: float = 1.0):
        self.timer, self.slowdown, self.t = timer, float(slowdown), 0.0

    @contextmanager
    def measure(self):
        t0 = self.timer()
        try:
            yield
        finally:
            self.t += max(self.timer() - t0, 1e-9) * self.slowdown


class Runner:
    """One model fed by the replay: ``see(frame, train)``, ``step()``, ``query(view, points)``."""

    name: str

    def __init__(self, name: str, clock: ComputeClock):
        self.name, self.clock = name, clock
        self.frames_seen = self.keyframes = self.steps = self.rejected = 0
        self.seen_ids: list[int] = []

    def see(self, frame: dict, train: bool) -> None:
        raise NotImplementedError

    def step(self) -> bool:
        return False

    def prepare(self) -> None:
        """Make the map queryable (e.g. build the ESDF); not counted as compute."""

    def query(self, view: str, points: np.ndarray, grad: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError

    def summary(self, up: np.ndarray | None = None) -> dict:
        return {"frames_seen": self.frames_seen, "keyframes": self.keyframes, "steps": self.steps,
                "rejected_keyframes": self.rejected, "compute_s": round(self.clock.t, 3)}


class VoxelRunner(Runner):
    """The Voxblox-like TSDF -> ESDF map (``aisdf.bench.voxel.VoxelEsdf``), every frame it sees."""

    def __init__(self, name, clock, bounds: np.ndarray, max_depth: float, voxel_size: float = 0.055):
        from .voxel import VoxelEsdf

        super().__init__(name, clock)
        self.map = VoxelEsdf(voxel_size=voxel_size, max_depth=max_depth, bounds=bounds)
        self._dirty = False

    def see(self, frame, train):
        with self.clock.measure():
            self.map.integrate(frame["depth"], frame["K"], frame["T_WC"])
        self.frames_seen += 1
        self.seen_ids.append(frame["frame_id"])
        self._dirty = True

    def prepare(self):
        if self._dirty:
            self.map.finalize()
            self._dirty = False

    def query(self, view, points, grad=True):
        self.prepare()
        return self.map.sdf(points), (self.map.gradient(points) if grad else None)

    def timings(self) -> dict:
        s = self.map.timing_summary()
        fin = self.map.timings["finalize_ms"]
        return {"integrate": round(s["integrate_ms"], 3), "esdf": round(float(np.mean(fin)) if fin else 0.0, 3)}

    def memory_mb(self) -> dict:
        """The TSDF's allocated blocks (tsdf and weight, float32), the dense ESDF with its
        observed mask and, once built, its gradient grids (float32); MB."""
        self.prepare()
        return {k: round(v / 1e6, 3) for k, v in self.map.memory_bytes().items()}

    def summary(self, up=None):
        return {**super().summary(), "keyframes": None, "steps": None, "timings_ms": self.timings(),
                "voxel_size": self.map.voxel_size, "memory_mb": self.memory_mb()}
