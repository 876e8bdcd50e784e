"""The mapper's algorithm for whole buildings: one AiSDF network per submap.

Space is cut by a :class:`~aisdf.submaps.grid.SubmapGrid` (cells a few metres across,
aligned with the Atlanta frame, with overlap). A submap is an AiSDF trainer (the paper's
network, preset and losses) whose positional encoding is centred on its cell; it is
created when keyframes first observe its space, keeps its own keyframes (views of the
shared keyframes: arrays are not copied) and is trained only on them, on the rays that
meet its box and on the samples inside it. A step trains one submap: one the newest
keyframes see (shares by how much of them each sees); out of view submaps are not trained
(they cannot forget), except that while no new keyframe arrives for ``idle_steps`` steps,
or on every ``refine_every``-th step, the submap with the fewest steps per keyframe gets a
refinement step on its own keyframes. The cost of a step does not grow with the building.

The Atlanta frame, surfels and the global surfel map are shared (one ``Structure``). The
mapper interface as the one network (:class:`aisdf.mapper.Mapper`): ``add_keyframe``, ``step``,
``sdf``, ``map_messages`` (only the submaps that changed, ``map/index`` and the surfel map;
``publish.py``), ``memory``, ``checkpoint``/``restore`` (``persist.py``).

Ownership (protocol 1.14, mapper shards): ``owns`` (a cell -> bool, None = every cell)
restricts the submaps this process creates and trains to the cells it owns; keyframes
touching only other cells are still stored (a replica's) and given to those cells' submaps
when ownership changes (``shards.reassign``); ``shards.adopt_grid`` takes a shared grid.
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import Any

import numpy as np
import torch

from .. import geometry, network, protocol
from ..mapper.coverage import KeyframePolicy
from ..mapper.intake import KeyframeIntake
from ..mapping.frames import Frame, StoredFrame
from ..mapping.presets import structure_overrides, submap_training_config
from ..mapping.trainer import Trainer
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels
from . import evict, persist
from .config import SubmapConfig
from .field import blend
from .grid import SubmapGrid, cell_id, parse_cell_id
from .persist import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from .publish import SubmapPublisher
from .submap import Cell, Submap

PRIOR_REACH_M = 1.0  # surfels this far beyond a submap's box still bound its samples


class SubmapPipeline:
    """Keyframes in, submaps trained (``add_keyframe``, ``step``); answers (``sdf``,
    ``sdf_grad``); publication (``map_messages``, ``publish.py``); checkpoints
    (``checkpoint``/``restore``, ``persist.py``)."""

    kind = "submaps"

    def __init__(self, cfg, atlanta: bool = True, submaps: SubmapConfig | None = None,
                 atlanta_state: dict | None = None, keyframes: KeyframePolicy | None = None):
        self.cfg = cfg
        self.sub_cfg = submaps or SubmapConfig()
        self.kf_policy = keyframes or KeyframePolicy()
        self.atlanta_on = atlanta
        self.intake = KeyframeIntake(cfg.max_depth, cfg.seed, atlanta, atlanta_state, self.sub_cfg.measured,
                                     self.kf_policy)
        self.evicted = 0  # keyframes removed for max_keyframes_total (evict.py)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        self.grid: SubmapGrid | None = None
        self.submaps: dict[Cell, Submap] = {}
        self.frames: dict[tuple[str, int], StoredFrame] = {}  # every keyframe once, prepared
        self._waiting: list[StoredFrame] = []  # before the grid exists
        self._recent: list[dict[Cell, int]] = []  # cells the newest keyframes see, with point counts
        self._credit: dict[Cell, float] = defaultdict(float)
        self.rng = np.random.default_rng(cfg.seed)
        self._steps = 0
        self._since_keyframe = 0
        self.publisher = SubmapPublisher(self)
        self.retraining: dict[Cell, int] = {}  # pose corrections: submaps owed steps, trained first (mapper/repose.py)
        self.owns = None  # protocol 1.14: cell -> bool, the cells this process trains (None: all; shards.py)
        self.cluster_header = None  # protocol 1.14: cell -> extra submap header keys (term, mapper)

    @classmethod
    def from_settings(cls, preset: str = "auto", training: dict[str, Any] | None = None, atlanta: bool = True,
                      surfel_mask: bool = True, surfel_loss: bool = True, surfel_bounds: bool = True,
                      submaps: SubmapConfig | dict | None = None,
                      keyframes: KeyframePolicy | dict | None = None) -> "SubmapPipeline":
        overrides = structure_overrides(training, atlanta, surfel_mask, surfel_loss, surfel_bounds)
        sub = submaps if isinstance(submaps, SubmapConfig) else SubmapConfig.model_validate(submaps or {})
        kfp = keyframes if isinstance(keyframes, KeyframePolicy) else KeyframePolicy.model_validate(keyframes or {})
        return cls(submap_training_config(preset, **overrides), atlanta=atlanta, submaps=sub, keyframes=kfp)

    def describe(self) -> str:
        c, s = self.cfg, self.sub_cfg
        return (f"submaps of {s.cell_m:g} x {s.cell_m:g} x {s.cell_height_m:g} m (overlap {s.overlap_m:g} m), "
                f"preset {c.preset}, width {c.network.width}, atlanta {'on' if self.atlanta_on else 'off'}")

    # ------------------------------------------------------------------ state
    @property
    def structure(self):
        return self.intake.structure

    @property
    def observed(self):
        return self.intake.observed

    @property
    def measured(self) -> MeasuredSurface | None:
        return self.intake.measured

    @property
    def steps(self) -> int:
        return self._steps

    @property
    def n_keyframes(self) -> int:
        return len(self.frames)

    @property
    def ready(self) -> bool:
        """A submap exists (the grid waits a few keyframes for the Atlanta frame's vertical)."""
        return bool(self.submaps)

    @property
    def keyframes(self) -> list[Frame]:
        return [k.frame for k in self.frames.values()]

    def keyframe_keys(self) -> list[tuple[str, int]]:
        return list(self.frames)

    # ------------------------------------------------------------------ keyframes
    def add_keyframe(self, kf: protocol.Keyframe | Frame) -> bool:
        """Add a keyframe: True when stored, False when it adds nothing new (``redundant``,
        not stored: ``aisdf.mapper.coverage``). Beyond ``max_keyframes_total`` the keyframe
        best covered by the others is evicted (``evict.py``). Raises ValueError (and changes
        nothing) for one that cannot be used: a duplicate (sensor, frame_id), too few valid
        depth pixels, a mask of another shape."""
        frame = self.intake.accept(kf, self.frames.__contains__, self.frames.get)
        self._cleared(self.intake.touched)
        if frame is None:
            return False
        t0 = time.perf_counter()
        prepared = StoredFrame.make(frame, self.cfg.max_depth)
        self.frames[frame.key] = prepared
        self.intake.record(frame)
        if self.grid is None:
            self._waiting.append(prepared)
            self._maybe_make_grid(frame)
        else:
            self._assign(prepared)
        self._since_keyframe = 0
        self.intake.timings["assign"].append(1e3 * (time.perf_counter() - t0))
        evict.bound(self)
        return True

    def _cleared(self, touched: list[tuple[str, int]]) -> None:
        """After a keyframe's rays cleared measured points and stored keyframes' pixels
        (``aisdf.mapper.clearing``): the submaps whose published measured points may have
        changed are published again, and those holding a keyframe that lost pixels forget
        their loss estimate (replayed as new)."""
        pts = self.intake.cleared_points
        if self.grid is None or not (touched or len(pts)):
            return
        keys = set(touched)
        for c, sm in self.submaps.items():
            if len(pts) and self.grid.inside(c, pts, grow=self.grid.overlap_m).any():
                sm.measured_changed = True
            if keys:
                for v in sm.trainer.store.keyframes:
                    if v.frame.key in keys:
                        v.loss = None

    def _maybe_make_grid(self, frame: Frame) -> None:
        s = self.sub_cfg
        af = self.structure.atlanta_frame() if self.structure is not None else None
        if af is None and self.structure is not None and len(self._waiting) < s.grid_wait_keyframes:
            return  # wait a little for the vertical
        first = self._waiting[0].frame
        vertical = None if af is None else af.vertical
        reference = None if af is None else af.reference
        self.grid = SubmapGrid.around(first.T_WC[:3, 3], vertical, reference, s.cell_m, s.cell_height_m, s.overlap_m)
        waiting, self._waiting = self._waiting, []
        for kf in waiting:
            self._assign(kf)

    def _ray_points(self, kf: StoredFrame, stride: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """World points along a grid of the keyframe's rays (4 per ray, the last on the
        surface): what the keyframe observes. Also the camera centre."""
        d = kf.depth[::stride, ::stride]
        v, u = np.nonzero(d > 0)
        K, T = kf.frame.K, np.asarray(kf.frame.T_WC, np.float64)
        D = d[v, u].astype(np.float64)
        uu, vv = u * stride, v * stride
        dirs = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones(len(D))], axis=-1)
        fr = np.array([0.25, 0.5, 0.75, 1.0])
        pts_C = dirs[:, None, :] * (D[:, None] * fr)[..., None]
        return geometry.transform(T, pts_C.reshape(-1, 3)), T[:3, 3]

    def _cells_of(self, kf: StoredFrame) -> dict[Cell, int]:
        """{cell: ray points} of the submaps the keyframe observes enough of."""
        s = self.sub_cfg
        pts, _ = self._ray_points(kf)
        counts = self.grid.cells_touching(pts)
        need = max(s.min_points, s.min_share * len(pts))
        seen = {c: n for c, n in counts.items() if n >= need}
        if not seen and counts:  # a keyframe always lands somewhere: its best cell
            c = max(counts, key=counts.get)
            seen = {c: counts[c]}
        return seen

    def _give(self, kf: StoredFrame, c: Cell) -> None:
        sm = self.submaps.get(c) or self._new_submap(c)
        sm.trainer.store.add_prepared(kf.view(self._pixel_mask(kf, c), self._region(c)))
        sm.seen_by.append(kf.frame.key)

    def _assign(self, kf: StoredFrame) -> None:
        """Give the keyframe to every submap it observes enough of (creating them); with
        ``owns``, only to the cells this process owns."""
        seen = self._cells_of(kf)
        if self.owns is not None:
            seen = {c: n for c, n in seen.items() if self.owns(c)}
        for c in seen:
            self._give(kf, c)
        if seen or self.owns is None:
            self._recent = ([seen] + self._recent)[: self.sub_cfg.active_keyframes]

    def _new_submap(self, c: Cell) -> Submap:
        """A new submap. With ``warm_start`` and a trained neighbour (one of the 26 cells
        around), its network starts as a copy of the most trained neighbour's (that
        network's field carried on into the new cell: floor, ceiling and walls that run on),
        keeping that neighbour's encoding centre (a cell away: coordinates stay small);
        otherwise a fresh network centred on the cell."""
        s = self.sub_cfg
        donor = None
        if s.warm_start:
            near = [sm for d, sm in self.submaps.items()
                    if max(abs(d[0] - c[0]), abs(d[1] - c[1]), abs(d[2] - c[2])) == 1 and sm.trainer.steps > 0]
            donor = max(near, key=lambda sm: (sm.trainer.steps, sm.id), default=None)
        centre = donor.trainer.cfg.network.offset if donor is not None else [float(x) for x in self.grid.centre_W(c)]
        net_cfg = self.cfg.network.model_copy(update={"offset": list(centre)})
        seed = int(self.cfg.seed * 1_000_003 + (hash(c) % 1_000_003))
        cfg = self.cfg.model_copy(update={"network": net_cfg, "seed": seed})
        tr = Trainer(cfg)
        self._attach_prior(c, tr)
        if donor is not None:
            network.load_numpy_state(tr.net, donor.trainer.state_numpy())
        sm = Submap(c, tr)
        self.submaps[c] = sm
        return sm

    def _attach_prior(self, c: Cell, tr: Trainer) -> None:
        """With ``surfel_bounds``: the global surfel map near the submap's box bounds its samples."""
        if self.structure is None or not tr.cfg.surfel_bounds:
            return
        from ..structure.prior import SurfelPrior

        box = self.grid.corners_W(c, self.grid.overlap_m + tr.cfg.trunc_distance)
        centre = box.mean(0)
        reach = float(np.linalg.norm(box - centre, axis=1).max()) + PRIOR_REACH_M
        tr.bound_prior = SurfelPrior(self.structure, centre, reach)

    def _region(self, c: Cell):
        grid, o = self.grid, self.grid.overlap_m

        def region(points: np.ndarray, grow: float) -> np.ndarray:
            return grid.inside(c, points, grow=o + grow)

        return region

    def _pixel_mask(self, kf: StoredFrame, c: Cell) -> np.ndarray:
        """Pixels whose sampled segment [min_depth, D + margin] meets the submap's box grown
        by a truncation distance (slab test in grid coordinates)."""
        cfg, grid = self.cfg, self.grid
        H, W = kf.shape
        v, u = np.mgrid[0:H, 0:W]
        K, T = kf.frame.K, np.asarray(kf.frame.T_WC, np.float64)
        dirs_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(-1, 3)
        d_G = dirs_C @ (grid.R_WG.T @ T[:3, :3]).T  # ray direction per unit camera z, grid axes
        o_G = grid.to_grid(T[:3, 3][None])[0]
        lo, hi = grid.core_box(c)
        grow = grid.overlap_m + cfg.trunc_distance
        lo, hi = lo - grow, hi + grow
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - o_G) / d_G
            t2 = (hi - o_G) / d_G
        tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
        tmax = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
        par = d_G == 0  # parallel to a slab: inside it or never
        inside_slab = (o_G >= lo) & (o_G <= hi)
        tmin = np.where(par, np.where(inside_slab, -np.inf, np.inf), tmin)
        tmax = np.where(par, np.where(inside_slab, np.inf, -np.inf), tmax)
        enter, leave = tmin.max(1), tmax.min(1)
        D = kf.depth.reshape(-1).astype(np.float64)
        near, far = cfg.min_depth, D + cfg.depth_margin
        return ((enter <= leave) & (leave >= near) & (enter <= far) & (D > 0)).reshape(H, W)

    # ------------------------------------------------------------------ training
    def _pick(self) -> Submap:
        if self.retraining:  # the submaps a pose correction changed first (aisdf.mapper.repose)
            from ..mapper.repose import retrain_pick

            return retrain_pick(self)
        s = self.sub_cfg
        idle = self._since_keyframe >= s.idle_steps
        refine = idle or (s.refine_every and (self._steps + 1) % s.refine_every == 0)
        if refine and len(self.submaps) > 1 or not self._recent:
            def need(sm: Submap) -> float:
                return sm.trainer.steps / max(1, sm.trainer.n_keyframes)

            active = set(self._recent[0]) if (self._recent and not idle) else set()
            pool = [sm for c, sm in self.submaps.items() if c not in active] or list(self.submaps.values())
            return min(pool, key=lambda sm: (need(sm), sm.id))
        shares: dict[Cell, float] = defaultdict(float)
        for seen in self._recent:
            tot = sum(seen.values())
            for c, n in seen.items():
                shares[c] += n / tot
        for c, v in shares.items():  # deficit round robin: steps in proportion to what is seen
            self._credit[c] += v / len(self._recent)
        for c in list(self._credit):
            if c not in shares:
                del self._credit[c]
        c = max(self._credit, key=lambda k: (self._credit[k], cell_id(k)))
        self._credit[c] -= 1.0
        return self.submaps[c]

    def step(self) -> dict:
        if not self.submaps:
            raise RuntimeError("step() needs at least one keyframe (and a grid)")
        extra = self.intake.take_pending()
        t = time.perf_counter()
        sm = self._pick()
        info = sm.trainer.step(extra_timings_ms=extra)
        info["submap"] = sm.id
        self._steps += 1
        self._since_keyframe += 1
        self.intake.record_step(info, 1e3 * (time.perf_counter() - t))
        return info

    def stats(self) -> dict:
        return {**self.intake.stats(), "submaps": len(self.submaps), "evicted": self.evicted,
                "dropped_keyframes": sum(sm.trainer.dropped_keyframes for sm in self.submaps.values())}

    # ------------------------------------------------------------------ answers
    def _evaluators(self):
        def make(tr: Trainer):
            def fn(q: np.ndarray, grad: bool):
                if grad:
                    return tr.sdf_grad(q)
                return tr.sdf(q), None

            return fn

        return {c: make(sm.trainer) for c, sm in self.submaps.items()}

    def sdf(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if not self.submaps:
            return np.full(len(p), np.nan, np.float32)
        return blend(self.grid, self._evaluators(), p, grad=False)[0]

    def sdf_grad(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, g, _ = blend(self.grid, self._evaluators(), np.asarray(points, np.float64).reshape(-1, 3), grad=True)
        return f, g

    def memory(self) -> dict[str, int]:
        """Bytes held, by part: keyframes (with each submap's pixel masks), model (weights and
        AdamW moments), observed space (and the stored keyframes' voxels, ``coverage``), measured points."""
        kf = sum(k.nbytes() for k in self.frames.values())
        masks = sum(v.pixel_bits.nbytes for sm in self.submaps.values() for v in sm.trainer.store.keyframes
                    if v.pixel_bits is not None)
        n_par = sum(p.numel() for sm in self.submaps.values() for p in sm.trainer.net.parameters())
        return {"keyframes": int(kf + masks), "model": int(3 * 4 * n_par),
                "observed": int(self.observed.nbytes() + self.intake.coverage.nbytes()),
                "measured": 0 if self.measured is None else self.measured.nbytes()}


    # ------------------------------------------------------------------ outputs
    def surfels(self) -> Surfels | None:
        return self.intake.surfels()

    def surfel_map(self, version: int) -> protocol.SurfelMap | None:
        return self.intake.surfel_map(version)

    def measured_points(self) -> np.ndarray:
        """(M, 3) the union of the measured points every submap publishes (points in overlaps
        once per submap): what a query service holding the whole map answers with."""
        return self.publisher.measured_points()

    def map_messages(self, version: int, changed_only: bool = True, epoch: int = 0,
                     mark: bool = True) -> list[tuple[str, bytes]]:
        """``SubmapPublisher.map_messages``: the submaps that changed and are due, the index
        and the surfel map."""
        return self.publisher.map_messages(version, changed_only, epoch, mark)

    # ------------------------------------------------------------------ pose corrections
    def repose(self, corrections: dict) -> dict:
        """New poses for stored keyframes, ``{(sensor, frame_id): T_WC}`` (protocol 1.11):
        ``aisdf.mapper.repose.repose_submaps``. ValueError (nothing changed) for a bad one."""
        from ..mapper.repose import repose_submaps

        return repose_submaps(self, corrections).as_dict()

    # ------------------------------------------------------------------ checkpoints
    def checkpoint(self) -> dict:
        return persist.checkpoint(self)

    @classmethod
    def restore(cls, d: dict[str, Any]) -> "SubmapPipeline":
        return persist.restore(cls, d)


__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "SubmapConfig", "SubmapPipeline", "parse_cell_id"]
