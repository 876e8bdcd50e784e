"""A submap pipeline as one shard of a map several mapper processes share (protocol 1.14):
the grid the cluster agreed on (``adopt_grid``), the cells this process owns (``reassign``:
submaps of cells it lost go, cells it gained get submaps trained on the keyframes it holds,
starting from the last published weights when it has them), and keyframes it does not hold
that still feed its Atlanta frame and surfels (``observe_only``)."""

from __future__ import annotations

import logging

from .. import network, protocol
from ..mapper.intake import frame_from_keyframe
from ..network import NetworkConfig
from ..mapping.trainer import Trainer
from .grid import SubmapGrid
from .submap import Submap

log = logging.getLogger("aisdf.mapper")


def adopt_grid(pipe, grid: SubmapGrid) -> bool:
    """Use the cluster's grid. True when the pipeline had another grid: its submaps are
    dropped and made again on the new grid from the stored keyframes."""
    if pipe.grid is not None and pipe.grid.same_as(grid):
        return False
    rebuilt = pipe.grid is not None
    pipe.grid = grid
    pipe.submaps.clear()
    pipe._credit.clear()
    pipe._recent = []
    pipe.retraining.clear()
    pipe._waiting = []
    for kf in pipe.frames.values():
        pipe._assign(kf)
    return rebuilt


def install_warm_start(pipe, snapshot_of) -> None:
    """New submaps start from ``snapshot_of(cell)`` (a WeightSnapshot: the cell's last published
    weights, another mapper's) when it gives one that loads, else as before (a trained
    neighbour's network, or a fresh one)."""
    plain = pipe._new_submap

    def new_submap(c) -> Submap:
        snap = snapshot_of(c)
        if snap is not None:
            try:
                net_cfg = NetworkConfig.model_validate(snap.model["config"])
                seed = int(pipe.cfg.seed * 1_000_003 + (hash(c) % 1_000_003))
                tr = Trainer(pipe.cfg.model_copy(update={"network": net_cfg, "seed": seed}))
                network.load_numpy_state(tr.net, snap.state)
                pipe._attach_prior(c, tr)
                sm = Submap(c, tr)
                pipe.submaps[c] = sm
                pipe.warm_started = getattr(pipe, "warm_started", 0) + 1
                return sm
            except Exception as e:  # noqa: BLE001 - weights of another shape: start as any new submap
                log.warning("submap %s: its last published weights could not be loaded (%s); starting anew", c, e)
        return plain(c)

    pipe._new_submap = new_submap


def reassign(pipe, owns) -> tuple[list, list]:
    """This process now owns the cells ``owns`` says: (cells gained, cells lost). Lost
    submaps are dropped (another mapper trains them now); gained cells get a submap
    (``install_warm_start``) and every stored keyframe that observes them, in arrival order."""
    pipe.owns = owns
    if pipe.grid is None:
        return [], []
    lost = [c for c in pipe.submaps if not owns(c)]
    for c in lost:
        del pipe.submaps[c]
        pipe._credit.pop(c, None)
        pipe.retraining.pop(c, None)
    pipe._recent = [r for r in ({c: n for c, n in seen.items() if owns(c)} for seen in pipe._recent) if r]
    gained: dict = {}
    for kf in pipe.frames.values():
        for c in pipe._cells_of(kf):
            if not owns(c) or (c in pipe.submaps and c not in gained):
                continue
            if c not in pipe.submaps:
                gained[c] = pipe._new_submap(c)
            pipe._give(kf, c)
    return sorted(gained), sorted(lost)


def observe_only(pipe, kf: protocol.Keyframe) -> None:
    """A keyframe this process does not hold: its Atlanta frame and surfels only (every
    mapper's structure sees every keyframe, so whichever publishes the surfel map has it all)."""
    if pipe.structure is None:
        return
    pipe.structure.process(frame_from_keyframe(kf))
