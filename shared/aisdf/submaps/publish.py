"""What the submap mapper publishes (protocol 1.3; docs/protocol.md): a
changed submap's weights on ``map/submaps/<id>``, the index on ``map/index`` and the global
surfel map on ``map/surfels``. Only submaps that changed and are due go out: those in view
at once, those refined in the background out of view in batches, so the bytes on the wire
follow what changed, not the size of the map.

:class:`SubmapPublisher` is held by :class:`~aisdf.submaps.pipeline.SubmapPipeline` and reads
its grid, submaps, observed space, measured points, structure and recent cells; each submap's
publication state (published step, version, first unpublished publication, cached observed
grid) lives on its ``Submap`` and is checkpointed with it, the publication count here.
"""

from __future__ import annotations

import time

import numpy as np

from .. import keys, protocol
from .submap import Submap


class SubmapPublisher:
    """The publication side of one ``SubmapPipeline`` (``pipe``)."""

    def __init__(self, pipe):
        self.pipe = pipe
        self.publications = 0  # map_messages(changed_only=True) calls
        self._measured_key, self._measured_pts = None, None  # the pool's points, once per new keyframe

    def observed_msg(self, sm: Submap) -> dict | None:
        key = (len(self.pipe.observed),)
        if sm.observed_key != key:
            c, grow = sm.cell, self.pipe.grid.overlap_m + self.pipe.observed.voxel
            g = self.pipe.observed.grid(keep=lambda centres: self.pipe.grid.inside(c, centres, grow=grow))
            sm.observed_msg, sm.observed_key = (None if g is None else g.to_msg()), key
        return sm.observed_msg

    def measured_msg(self, sm: Submap) -> dict | None:
        """The measured points (protocol 1.4) in the submap's extended box, or None when the
        mapper pools none."""
        m = self.pipe.measured
        if m is None:
            return None
        key = (id(m), m.version)  # (a pose correction pools the points again, in a new pool)
        if self._measured_key != key:  # the points, once per new keyframe
            self._measured_pts, self._measured_key = m.points(), key
        pts = self._measured_pts
        inside = self.pipe.grid.inside(sm.cell, pts, grow=self.pipe.grid.overlap_m) if len(pts) else np.zeros(0, bool)
        return {"voxel": m.voxel, "points": pts[inside].astype(np.float32)}

    def measured_points(self) -> np.ndarray:
        """(M, 3) the union of the measured points every submap publishes (points in overlaps
        once per submap): what a query service holding the whole map answers with."""
        msgs = [self.measured_msg(sm) for sm in self.pipe.submaps.values()] if self.pipe.grid is not None else []
        pts = [m["points"] for m in msgs if m is not None]
        return np.concatenate(pts) if pts else np.zeros((0, 3), np.float32)

    def submap_snapshot(self, sm: Submap, version: int, epoch: int = 0) -> protocol.WeightSnapshot:
        model = dict(sm.trainer.model_spec())
        c = sm.cell
        model["bounds"] = [self.pipe.grid.corners_W(c, self.pipe.grid.overlap_m).min(0).tolist(),
                           self.pipe.grid.corners_W(c, self.pipe.grid.overlap_m).max(0).tolist()]
        header = {"id": sm.id, "grid": self.pipe.grid.to_msg()}
        if self.pipe.cluster_header is not None:  # protocol 1.14: term and mapper of a shard's submap
            header.update(self.pipe.cluster_header(c))
        return protocol.WeightSnapshot(version, sm.trainer.steps, time.time(), model, sm.trainer.state_numpy(),
                                       epoch, self.observed_msg(sm), header, self.measured_msg(sm))

    def index(self, version: int, epoch: int = 0) -> protocol.SubmapIndex:
        return protocol.SubmapIndex(version, time.time(), self.pipe.grid.to_msg(),
                                    {sm.id: {"version": sm.version, "step": max(sm.published_step, 0)}
                                     for sm in self.pipe.submaps.values()}, epoch)

    def due(self, sm: Submap, mark: bool = True) -> bool:
        """Is this changed submap published now? New ones and those the newest keyframes see
        (where the robot is), at once; one changed only by background refinement out of view,
        once it has ``background_publish_steps`` unpublished steps or has waited
        ``background_publish_periods`` publications (bytes follow what changed, not the
        refinement's single steps)."""
        s = self.pipe.sub_cfg
        if sm.published_step < 0 or any(sm.cell in seen for seen in self.pipe._recent):
            return True
        since = self.publications if sm.dirty_since is None else sm.dirty_since
        if mark:
            sm.dirty_since = since
        return (sm.trainer.steps - sm.published_step >= s.background_publish_steps
                or self.publications - since >= s.background_publish_periods)

    def map_messages(self, version: int, changed_only: bool = True, epoch: int = 0,
                     mark: bool = True) -> list[tuple[str, bytes]]:
        """What the mapper publishes for map ``version``: every submap trained since its last
        publication that is due (``_due``; all of them with ``changed_only`` False) on
        ``map/submaps/<id>``, the index on ``map/index`` and the global surfel map. With
        ``mark`` False nothing is recorded as published (what a publication would cost)."""
        out = []
        if self.pipe.grid is None:
            return out
        if changed_only and mark:
            self.publications += 1
        for sm in self.pipe.submaps.values():
            if sm.cell in self.pipe.retraining:  # a pose correction's fresh network: held until trained (repose.py)
                continue
            if changed_only and not sm.measured_changed and (sm.trainer.steps == sm.published_step
                                                             or not self.due(sm, mark)):
                continue
            if mark:
                sm.published_step, sm.version, sm.dirty_since = sm.trainer.steps, version, None
                sm.measured_changed = False
            snap = self.submap_snapshot(sm, version, epoch)
            out.append((f"{keys.MAP_SUBMAPS}/{sm.id}", protocol.pack(snap.to_msg())))
        out.append((keys.MAP_INDEX, protocol.pack(self.index(version, epoch).to_msg())))
        smap = self.pipe.surfel_map(version)
        if smap is not None:
            smap.epoch = epoch
            out.append((keys.MAP_SURFELS, protocol.pack(smap.to_msg())))
        return out
