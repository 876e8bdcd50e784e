"""Checkpoints of the submap mapper: everything to resume where it stopped (the keyframes
once, each submap's weights, AdamW state, keyframe keys and loss estimates, publication
state, counters and generators) of a :class:`~aisdf.submaps.pipeline.SubmapPipeline`
(``checkpoint``), and the pipeline again (``restore``); the format is plain types and numpy
arrays (the mapper service writes it with torch.save). Evicted keyframes are gone from it; the
measured points they gave are kept (the pool is saved, not rebuilt from the keyframes)."""

from __future__ import annotations

import numpy as np

from .. import network
from ..mapping.config import TrainingConfig
from ..mapping.frames import Frame, StoredFrame
from ..mapper.coverage import KeyframePolicy
from ..mapping.trainer import Trainer
from ..structure.measured import MeasuredSurface
from .config import SubmapConfig
from .grid import SubmapGrid
from .submap import Submap

CHECKPOINT_FORMAT = "aisdf-submaps-checkpoint"
# 2: keyframes sent as <u2 are written raw (depth_raw, depth_scale; depth None); 1 still loads.
# Optional keys since 1.10 (absent: defaults, the pool rebuilt from the keyframes): "keyframes"
# (the policy), "redundant", "evicted", "measured" (the pool: evicted keyframes' points stay);
# since 1.11 "retraining" (submaps a pose correction changed, owed steps before publication).
CHECKPOINT_VERSION = 2


def checkpoint(pipe) -> dict:
    """Everything to resume: keyframes once, each submap's weights, AdamW state, its
    keyframe keys and loss estimates, counters and generators."""
    subs = []
    for sm in pipe.submaps.values():
        tr = sm.trainer
        subs.append({
            "cell": list(sm.cell), "config": tr.cfg.model_dump(mode="json"), "state": tr.state_numpy(),
            "optimizer": tr.optimizer_numpy(), "steps": tr.steps,
            "dropped": tr.store.dropped, "rng": tr.rng.bit_generator.state, "published_step": sm.published_step,
            "version": sm.version, "dirty_since": sm.dirty_since, "lr_state": tr.lr_state(),
            "keyframes": [[k.frame.sensor, int(k.frame.frame_id), k.loss] for k in tr.store.keyframes],
        })
    return {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": pipe.cfg.model_dump(mode="json"),
        "submap_config": pipe.sub_cfg.model_dump(mode="json"), "atlanta": pipe.atlanta_on,
        "structure": None if pipe.structure is None else pipe.structure.state_dict(),
        "grid": None if pipe.grid is None else pipe.grid.to_msg(),
        "frames": [k.frame_dict() for k in pipe.frames.values()],
        "waiting": [list(k.frame.key) for k in pipe._waiting],
        "recent": [[[list(c), n] for c, n in seen.items()] for seen in pipe._recent],
        "credit": [[list(c), v] for c, v in pipe._credit.items()], "since_keyframe": pipe._since_keyframe,
        "submaps": subs, "steps": pipe._steps, "publications": pipe.publisher.publications,
        "rng": pipe.rng.bit_generator.state,
        "bounds": None if pipe.intake.bounds is None else pipe.intake.bounds.tolist(),
        "observed": pipe.observed.state_dict(),
        "keyframes": pipe.kf_policy.model_dump(mode="json"), "redundant": pipe.intake.redundant,
        "evicted": pipe.evicted, "measured": None if pipe.measured is None else pipe.measured.state_dict(),
        "retraining": [[list(c), int(n)] for c, n in pipe.retraining.items()],
    }


def restore(cls, d: dict):
    """The pipeline of ``checkpoint``: ``cls`` is the pipeline's class."""
    if d.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"not a submap checkpoint (format {d.get('format')!r})")
    if int(d.get("version", 0)) > CHECKPOINT_VERSION:
        raise ValueError(f"checkpoint version {d['version']} is newer than this build's {CHECKPOINT_VERSION}")
    p = cls(TrainingConfig.model_validate(d["config"]), atlanta=d["atlanta"],
            submaps=SubmapConfig.model_validate(d["submap_config"]), atlanta_state=d.get("structure"),
            keyframes=KeyframePolicy.model_validate(d.get("keyframes") or {}))
    saved = d.get("measured")  # since 1.10; before, the pool is rebuilt from the keyframes
    if p.measured is not None and saved is not None:
        p.intake.measured = MeasuredSurface.from_state_dict(saved)
    for fd in d["frames"]:
        f = Frame.from_dict(fd)
        p.frames[f.key] = StoredFrame.make(f, p.cfg.max_depth)
        p.intake.coverage.add(f.key, f)
        if p.measured is not None and saved is None:  # the same pixels, the same voxels
            p.measured.add(f.depth, f.K, f.T_WC)
    p.intake.redundant = int(d.get("redundant", 0))
    p.evicted = int(d.get("evicted", 0))
    p.retraining = {tuple(int(x) for x in c): int(n) for c, n in d.get("retraining", [])}  # 1.11, optional
    if d.get("grid") is not None:
        p.grid = SubmapGrid.from_msg(d["grid"])
    p._waiting = [p.frames[(s, int(i))] for s, i in d.get("waiting", [])]
    p._recent = [{tuple(c): int(n) for c, n in seen} for seen in d.get("recent", [])]
    for sd in d["submaps"]:
        c = tuple(int(x) for x in sd["cell"])
        tr = Trainer(TrainingConfig.model_validate(sd["config"]))
        p._attach_prior(c, tr)
        network.load_numpy_state(tr.net, sd["state"])
        tr.resume(sd["optimizer"], int(sd["steps"]), sd["rng"], sd.get("lr_state"))
        sm = Submap(c, tr, int(sd["published_step"]), int(sd["version"]))
        sm.dirty_since = sd.get("dirty_since")
        p.submaps[c] = sm
        for sensor, fid, loss in sd["keyframes"]:
            kf = p.frames[(sensor, int(fid))]
            tr.store.add_prepared(kf.view(p._pixel_mask(kf, c), p._region(c)))
            tr.store.keyframes[-1].loss = None if loss is None else float(loss)
            sm.seen_by.append(kf.frame.key)
        tr.store.dropped = int(sd["dropped"])
    p._steps = int(d["steps"])
    p.publisher.publications = int(d.get("publications", 0))
    p._since_keyframe = int(d.get("since_keyframe", 0))
    for c, v in d.get("credit", []):
        p._credit[tuple(int(x) for x in c)] = float(v)
    p.rng.bit_generator.state = d["rng"]
    if d.get("bounds") is not None:
        p.intake.bounds = np.asarray(d["bounds"])
    p.observed.load_state_dict(d["observed"])
    return p
