"""The one-network mapper (``mapper: single``): the Atlanta frame and surfels per keyframe
(when on), continual training of one network for the whole map, and the map as protocol
messages (``map/weights``, ``map/surfels``). Implements :class:`aisdf.mapper.Mapper`.

    pipe = MappingPipeline.from_settings("cpu", atlanta=True)
    pipe.add_keyframe(keyframe)      # protocol.Keyframe or mapping.Frame
    pipe.step()
    pipe.weight_snapshot(version), pipe.surfel_map(version)
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .. import keys, protocol
from ..mapping.frames import Frame
from ..mapping.presets import structure_overrides, training_config
from ..mapping.trainer import Trainer
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels
from .coverage import KeyframePolicy
from .intake import KeyframeIntake


class MappingPipeline:
    kind = "single"

    def __init__(self, trainer: Trainer, atlanta: bool = True, atlanta_state: dict | None = None,
                 measured: bool = True, keyframes: KeyframePolicy | None = None):
        self.trainer = trainer
        self.atlanta_on = atlanta
        # Every keyframe's depth pixels pooled into 10 cm voxels, sent with each snapshot
        # (protocol 1.5: the query service's fused answers use them). Keyframes that add nothing
        # new are not stored (coverage.py); the store's own bound (training.max_keyframes) holds.
        self.kf_policy = keyframes or KeyframePolicy()
        self.intake = KeyframeIntake(trainer.cfg.max_depth, trainer.cfg.seed, atlanta, atlanta_state, measured,
                                     self.kf_policy)
        if self.structure is not None and trainer.cfg.surfel_bounds:
            from ..structure.prior import SurfelPrior

            trainer.bound_prior = SurfelPrior(self.structure)

    @property
    def structure(self):
        return self.intake.structure

    @property
    def observed(self):
        return self.intake.observed

    @property
    def measured(self) -> MeasuredSurface | None:
        return self.intake.measured

    @classmethod
    def from_settings(cls, preset: str = "auto", training: dict[str, Any] | None = None, atlanta: bool = True,
                      surfel_mask: bool = True, surfel_loss: bool = True,
                      surfel_bounds: bool = True, measured: bool = True,
                      keyframes: KeyframePolicy | dict | None = None) -> "MappingPipeline":
        """Preset + overrides; the Table II switches (and ``surfel_bounds``, beyond the paper)
        only matter with ``atlanta`` on. ``measured``: pool the depth pixels and publish them
        (protocol 1.5; false: 1.4's snapshots, without points)."""
        overrides = structure_overrides(training, atlanta, surfel_mask, surfel_loss, surfel_bounds)
        kfp = keyframes if isinstance(keyframes, KeyframePolicy) else KeyframePolicy.model_validate(keyframes or {})
        return cls(Trainer(training_config(preset, **overrides)), atlanta=atlanta, measured=measured,
                   keyframes=kfp)

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

    @property
    def ready(self) -> bool:
        return self.trainer.n_keyframes > 0

    def add_keyframe(self, kf: protocol.Keyframe | Frame) -> bool:
        """Add a keyframe: True when stored, False when it adds nothing new (not stored,
        counted as ``redundant``). Raises ValueError (and changes nothing) for one that cannot
        be used: a duplicate (sensor, frame_id), too few valid depth pixels, a bad mask."""
        stored = {k.frame.key: k for k in self.trainer.store.keyframes}
        frame = self.intake.accept(kf, stored.__contains__, stored.get)
        for k in self.trainer.store.keyframes:  # a keyframe that lost pixels is replayed as new
            if k.frame.key in self.intake.touched:
                k.loss = None
        if frame is None:
            return False
        self.trainer.add_keyframe(frame)
        self.intake.record(frame)
        for key in set(self.intake.coverage.views) - set(self.keyframe_keys()):  # dropped by the store
            self.intake.coverage.remove(key)
        return True

    def keyframe_keys(self) -> list[tuple[str, int]]:
        return [f.key for f in self.trainer.keyframes]

    # ------------------------------------------------------------------ training

    def step(self) -> dict:
        extra = self.intake.take_pending()
        t = time.perf_counter()
        info = self.trainer.step(extra_timings_ms=extra)
        info.setdefault("timings_ms", {})
        self.intake.record_step(info, 1e3 * (time.perf_counter() - t))
        return info

    def stats(self) -> dict:
        """Mean per-module timings in ms over recent steps/keyframes (the paper's Table III)."""
        return {**self.intake.stats(), "dropped_keyframes": self.trainer.dropped_keyframes}

    # ------------------------------------------------------------------ outputs

    def weight_snapshot(self, version: int) -> protocol.WeightSnapshot:
        model = dict(self.trainer.model_spec())
        if self.intake.bounds is not None:
            model["bounds"] = self.intake.bounds.tolist()
        return protocol.WeightSnapshot(version, self.steps, time.time(), model, self.trainer.state_numpy(),
                                       observed=self.observed.message(),
                                       measured=None if self.measured is None else self.measured.message())

    def measured_points(self) -> np.ndarray:
        """(M, 3) float32: the measured points every snapshot carries (none without pooling)."""
        if self.measured is None:
            return np.zeros((0, 3), np.float32)
        return self.measured.message()["points"]

    def surfels(self) -> Surfels | None:
        return self.intake.surfels()

    def surfel_map(self, version: int) -> protocol.SurfelMap | None:
        return self.intake.surfel_map(version)

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
        AdamW moments), observed space (and the stored keyframes' voxels), measured points
        (the pool's voxels)."""
        kf = sum(k.nbytes() for k in self.trainer.store.keyframes)
        n_par = sum(p.numel() for p in self.trainer.net.parameters())
        return {"keyframes": int(kf), "model": int(3 * 4 * n_par),
                "observed": int(self.observed.nbytes() + self.intake.coverage.nbytes()),
                "measured": 0 if self.measured is None else self.measured.nbytes()}

    # ------------------------------------------------------------------ pose corrections

    def repose(self, corrections: dict) -> dict:
        """New poses for stored keyframes, ``{(sensor, frame_id): T_WC}`` (protocol 1.11):
        ``aisdf.mapper.repose.repose_single``. ValueError (nothing changed) for a bad one."""
        from .repose import repose_single

        return repose_single(self, corrections).as_dict()

    # ------------------------------------------------------------------ checkpoints

    def checkpoint(self) -> dict:
        return {"trainer": self.trainer.checkpoint(), "atlanta": self.atlanta_on,
                "keyframes": self.kf_policy.model_dump(mode="json"), "redundant": self.intake.redundant,
                "structure": None if self.structure is None else self.structure.state_dict(),
                "bounds": None if self.intake.bounds is None else self.intake.bounds.tolist(),
                "observed": self.observed.state_dict(),
                "measured": None if self.measured is None else self.measured.state_dict()}

    @classmethod
    def restore(cls, d: dict) -> "MappingPipeline":
        # A checkpoint from before 1.5 has no "measured": the pool is rebuilt from the kept keyframes
        # (those the keyframe store dropped are gone); None: the mapper pooled none.
        has = "measured" in d
        p = cls(Trainer.from_checkpoint(d["trainer"]), atlanta=d["atlanta"], atlanta_state=d.get("structure"),
                measured=not has or d["measured"] is not None,
                keyframes=KeyframePolicy.model_validate(d.get("keyframes") or {}))
        p.intake.redundant = int(d.get("redundant", 0))
        for f in p.trainer.keyframes:
            p.intake.coverage.add(f.key, f)
        if has and d["measured"] is not None:
            p.intake.measured = MeasuredSurface.from_state_dict(d["measured"])
        if d.get("bounds") is not None:
            p.intake.bounds = np.asarray(d["bounds"])
        if d.get("observed") is not None:
            p.observed.load_state_dict(d["observed"])
        else:  # a checkpoint from before observed space: rebuild it from the kept keyframes
            for f in p.trainer.keyframes:
                p.observed.add(f.metres(), f.K, f.T_WC, p.trainer.cfg.max_depth)
        if not has:
            for f in p.trainer.keyframes:
                p.measured.add(f.metres(), f.K, f.T_WC)
        return p
