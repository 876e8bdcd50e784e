"""The mapper's algorithm in one object, driven in-process by the mapper service, the
benchmark and the tests alike: per keyframe, the Atlanta frame and surfels (when on),
then continual training, and the map as protocol messages. No Zenoh, no files.

    pipe = MappingPipeline.from_settings("cpu", atlanta=True)
    pipe.add_keyframe(keyframe)      # protocol.Keyframe or mapping.Frame
    pipe.step()
    pipe.weight_snapshot(version), pipe.surfel_map(version)
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import Any

import numpy as np

from . import geometry, keys, protocol
from .mapping.frames import Frame
from .mapping.presets import training_config
from .mapping.trainer import Trainer
from .observed import ObservedSpace
from .structure.measured import MeasuredSurface
from .structure.surfel_types import Surfels

MIN_VALID_PIXELS = 64


def frame_from_keyframe(kf: protocol.Keyframe) -> Frame:
    """The frame of a received keyframe: depth in metres, and for ``<u2`` depth the raw
    values too (a stored keyframe holds those: half the bytes, the same metres)."""
    raw = kf.depth if kf.depth.dtype == np.uint16 and kf.depth_scale is not None else None
    return Frame(kf.frame_id, kf.stamp, kf.depth_m(), kf.K, kf.T_WC, sensor=kf.sensor, depth_raw=raw,
                 depth_scale=None if raw is None else float(kf.depth_scale))


def grow_bounds(bounds: np.ndarray | None, frame: Frame, max_depth: float = np.inf) -> np.ndarray:
    """(2, 3) world box of what is seen so far, grown by a keyframe's valid points
    (``geometry.valid_depth``) and its camera."""
    d = frame.depth[::4, ::4]
    d = np.where(geometry.valid_depth(d, max_depth), d, 0.0)
    K = frame.K.copy()
    K[:2] /= 4
    pts = geometry.backproject(d, K).reshape(-1, 3)
    pts = geometry.transform(frame.T_WC, pts[np.isfinite(pts[:, 0])])
    pts = np.concatenate([pts, frame.T_WC[None, :3, 3]])
    lo, hi = pts.min(0), pts.max(0)
    if bounds is None:
        return np.stack([lo, hi])
    return np.stack([np.minimum(bounds[0], lo), np.maximum(bounds[1], hi)])


def surfel_map_message(structure, version: int) -> protocol.SurfelMap | None:
    """The global surfel map with its Atlanta frame (None without structure or a frame yet)."""
    if structure is None:
        return None
    frame = structure.atlanta_frame()
    if frame is None:
        return None
    s = structure.global_surfels()
    return protocol.SurfelMap(version, time.time(), frame.vertical, frame.horizontal, s.to_protocol_dict())


class MappingPipeline:
    def __init__(self, trainer: Trainer, atlanta: bool = True, atlanta_state: dict | None = None,
                 measured: bool = True):
        self.trainer = trainer
        self.atlanta_on = atlanta
        self.structure = None
        if atlanta:
            from .structure import Structure

            self.structure = Structure(seed=trainer.cfg.seed, max_depth=trainer.cfg.max_depth)
            if atlanta_state:
                self.structure.load_state_dict(atlanta_state)
            if trainer.cfg.surfel_bounds:
                from .structure.prior import SurfelPrior

                trainer.bound_prior = SurfelPrior(self.structure)
        self._timings: dict[str, list[float]] = defaultdict(list)
        self._pending_timings: dict[str, float] = {}
        self._bounds: np.ndarray | None = None
        self.last_ids: set[int] = set()
        self.observed = ObservedSpace()
        # Protocol 1.5: every keyframe's depth pixels pooled into 10 cm voxels, sent with each
        # snapshot (the query service's fused answers use them, as a submap mapper's since 1.4).
        self.measured = MeasuredSurface(max_depth=trainer.cfg.max_depth) if measured else None

    @classmethod
    def from_settings(cls, preset: str = "auto", training: dict[str, Any] | None = None, atlanta: bool = True,
                      surfel_mask: bool = True, surfel_loss: bool = True,
                      surfel_bounds: bool = True, measured: bool = True) -> "MappingPipeline":
        """Preset + overrides; the Table II switches (and ``surfel_bounds``, beyond the paper)
        only matter with ``atlanta`` on. ``measured``: pool the depth pixels and publish them
        (protocol 1.5; false: 1.4's snapshots, without points)."""
        overrides = dict(training or {})
        overrides.setdefault("surfel_bounds", bool(atlanta and surfel_bounds))
        overrides.setdefault("surfel_mask", bool(atlanta and surfel_mask))
        overrides.setdefault("surfel_loss", bool(atlanta and surfel_loss))
        return cls(Trainer(training_config(preset, **overrides)), atlanta=atlanta, measured=measured)

    def describe(self) -> str:
        c = self.trainer.cfg
        return (f"preset {c.preset}, width {c.network.width}, device {self.trainer.device}, "
                f"atlanta {'on' if self.atlanta_on else 'off'}, surfel mask {c.surfel_mask}, surfel loss {c.surfel_loss}")

    # ------------------------------------------------------------------ keyframes

    @property
    def cfg(self):
        """The training configuration (``SubmapPipeline.cfg`` too: the same interface)."""
        return self.trainer.cfg

    @property
    def steps(self) -> int:
        return self.trainer.steps

    @property
    def n_keyframes(self) -> int:
        return self.trainer.n_keyframes

    def add_keyframe(self, kf: protocol.Keyframe | Frame) -> None:
        """Add a keyframe. Raises ValueError (and changes nothing) for one that cannot be
        used: a duplicate (sensor, frame_id), too few valid depth pixels."""
        frame = frame_from_keyframe(kf) if isinstance(kf, protocol.Keyframe) else kf
        depth = frame.depth
        valid = geometry.valid_depth(depth, self.trainer.cfg.max_depth)
        if int(valid.sum()) < MIN_VALID_PIXELS:
            raise ValueError(f"only {int(valid.sum())} valid depth pixels (need {MIN_VALID_PIXELS})")
        if frame.key in {f.key for f in self.trainer.keyframes}:
            raise ValueError(f"keyframe {frame.sensor}/{frame.frame_id} is already in the map")
        if self.structure is not None:
            t = self.structure.process(frame)
            for k, v in t.items():
                self._pending_timings[k] = self._pending_timings.get(k, 0.0) + v
                self._timings[k].append(v)
        self.trainer.add_keyframe(frame)
        self._grow_bounds(frame)
        t = time.perf_counter()
        self.observed.add(depth, frame.K, frame.T_WC, self.trainer.cfg.max_depth)
        self._timings["observed"].append(1e3 * (time.perf_counter() - t))
        if self.measured is not None:
            t = time.perf_counter()
            self.measured.add(depth, frame.K, frame.T_WC)
            self._timings["measured"].append(1e3 * (time.perf_counter() - t))

    def _grow_bounds(self, frame: Frame) -> None:
        self._bounds = grow_bounds(self._bounds, frame, self.trainer.cfg.max_depth)

    # ------------------------------------------------------------------ training

    def step(self) -> dict:
        extra, self._pending_timings = self._pending_timings, {}
        t = time.perf_counter()
        info = self.trainer.step(extra_timings_ms=extra)
        info.setdefault("timings_ms", {})
        for k, v in info["timings_ms"].items():
            self._timings[k].append(v)
        self._timings["step_wall"].append(1e3 * (time.perf_counter() - t))
        for v in self._timings.values():
            del v[:-200]  # keep recent history only
        return info

    def stats(self) -> dict:
        """Mean per-module timings in ms over recent steps/keyframes (the paper's Table III)."""
        out = {k: round(float(np.mean(v)), 3) for k, v in self._timings.items() if v}
        out["dropped_keyframes"] = self.trainer.dropped_keyframes
        if self.structure is not None:
            out.update(self.structure.stats())
        return out

    # ------------------------------------------------------------------ outputs

    def weight_snapshot(self, version: int) -> protocol.WeightSnapshot:
        model = dict(self.trainer.model_spec())
        if self._bounds is not None:
            model["bounds"] = self._bounds.tolist()
        return protocol.WeightSnapshot(version, self.steps, time.time(), model, self.trainer.state_numpy(),
                                       observed=self.observed.message(),
                                       measured=None if self.measured is None else self.measured.message())

    def measured_points(self) -> np.ndarray:
        """(M, 3) float32: the measured points every snapshot carries (none without pooling)."""
        if self.measured is None:
            return np.zeros((0, 3), np.float32)
        return self.measured.message()["points"]

    def surfels(self) -> Surfels | None:
        return None if self.structure is None else self.structure.global_surfels()

    def surfel_map(self, version: int) -> protocol.SurfelMap | None:
        return surfel_map_message(self.structure, version)

    def sdf(self, points: np.ndarray) -> np.ndarray:
        return self.trainer.sdf(points)

    def map_messages(self, version: int, changed_only: bool = True, epoch: int = 0,
                     mark: bool = True) -> list[tuple[str, bytes]]:
        """What the mapper publishes for map ``version``: (key under the namespace, payload).
        One network is one message: it is all sent every time, changed or not (``mark`` is
        for the submap pipeline's interface: nothing here records a publication)."""
        snap = self.weight_snapshot(version)
        snap.epoch = epoch
        out = [(keys.MAP_WEIGHTS, protocol.pack(snap.to_msg()))]
        smap = self.surfel_map(version)
        if smap is not None:
            smap.epoch = epoch
            out.append((keys.MAP_SURFELS, protocol.pack(smap.to_msg())))
        return out

    def memory(self) -> dict[str, int]:
        """Bytes held, by part: keyframes (depth, surfel masks, surfels), model (weights and
        AdamW moments), observed space, measured points (the pool's voxels)."""
        kf = sum(k.nbytes() for k in self.trainer.store.keyframes)
        n_par = sum(p.numel() for p in self.trainer.net.parameters())
        return {"keyframes": int(kf), "model": int(3 * 4 * n_par), "observed": int(self.observed.nbytes()),
                "measured": 0 if self.measured is None else self.measured.nbytes()}

    # ------------------------------------------------------------------ checkpoints

    def checkpoint(self) -> dict:
        return {"trainer": self.trainer.checkpoint(), "atlanta": self.atlanta_on,
                "structure": None if self.structure is None else self.structure.state_dict(),
                "bounds": None if self._bounds is None else self._bounds.tolist(),
                "observed": self.observed.state_dict(),
                "measured": None if self.measured is None else self.measured.state_dict()}

    @classmethod
    def restore(cls, d: dict) -> "MappingPipeline":
        # A checkpoint from before 1.5 has no "measured": the pool is rebuilt from the kept keyframes
        # (those the keyframe store dropped are gone); None: the mapper pooled none.
        has = "measured" in d
        p = cls(Trainer.from_checkpoint(d["trainer"]), atlanta=d["atlanta"], atlanta_state=d.get("structure"),
                measured=not has or d["measured"] is not None)
        if has and d["measured"] is not None:
            p.measured = MeasuredSurface.from_state_dict(d["measured"])
        if d.get("bounds") is not None:
            p._bounds = np.asarray(d["bounds"])
        if d.get("observed") is not None:
            p.observed.load_state_dict(d["observed"])
        else:  # a checkpoint from before observed space: rebuild it from the kept keyframes
            for f in p.trainer.keyframes:
                p.observed.add(f.metres(), f.K, f.T_WC, p.trainer.cfg.max_depth)
        if not has:
            for f in p.trainer.keyframes:
                p.measured.add(f.metres(), f.K, f.T_WC)
        return p
