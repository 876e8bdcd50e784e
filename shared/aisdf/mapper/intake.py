"""The keyframe intake both mappers share: a received keyframe checked and decoded, the
Atlanta frame and surfels updated (``structure``), and the map's bookkeeping that does not
depend on how the map is learnt: the box of what was seen, the observed space, the pool of
measured points, the stored keyframes' coverage (``coverage``: keyframes that add nothing
new are not stored) and the per-module timings. A mapper holds one :class:`KeyframeIntake`
and stores the frame for training between ``accept`` and ``record``."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np

from .. import geometry, protocol
from ..mapping.frames import Frame
from ..observed import ObservedSpace
from ..structure.measured import MeasuredSurface
from ..structure.surfel_types import Surfels
from . import clearing
from .coverage import KeyframeCoverage, KeyframePolicy

MIN_VALID_PIXELS = 64
TIMING_HISTORY = 200  # recent values kept per timing


def frame_from_keyframe(kf: protocol.Keyframe) -> Frame:
    """The frame of a received keyframe: depth in metres, and for ``<u2`` depth the raw
    values too (a stored keyframe holds those: half the bytes, the same metres). Masked
    pixels (1.10) are no measurement in both: 0, as invalid depth, for every use of the frame
    (training, measured points, surfels, observed space). ValueError for a mask of another shape."""
    if kf.mask is not None and np.shape(kf.mask) != kf.depth.shape:
        raise ValueError(f"mask shape {np.shape(kf.mask)} does not match depth's {kf.depth.shape}")
    raw = kf.depth if kf.depth.dtype == np.uint16 and kf.depth_scale is not None else None
    if raw is not None and kf.mask is not None:
        raw = np.where(np.asarray(kf.mask).astype(bool), np.uint16(0), raw)
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


class KeyframeIntake:
    """``accept`` (check, decode, structure) then ``record`` (bounds, observed, measured)."""

    def __init__(self, max_depth: float, seed: int, atlanta: bool = True, atlanta_state: dict | None = None,
                 measured: bool = True, policy: KeyframePolicy | None = None):
        self.max_depth = max_depth
        self.structure = None
        if atlanta:
            from ..structure import Structure

            self.structure = Structure(seed=seed, max_depth=max_depth)
            if atlanta_state:
                self.structure.load_state_dict(atlanta_state)
        self.bounds: np.ndarray | None = None
        self.observed = ObservedSpace()
        self.measured = MeasuredSurface(max_depth=max_depth) if measured else None
        self.policy = policy or KeyframePolicy()
        self.coverage = KeyframeCoverage(self.policy, max_depth)
        # what newer keyframes' rays passed through (clearing.py): measured voxels, stored
        # keyframes' pixels (and how many keyframes lost some), global surfels
        self.cleared = {"measured": 0, "pixels": 0, "keyframes": 0, "surfels": 0}
        self.touched: list[tuple[str, int]] = []  # the last accepted keyframe's: stored keyframes it cleared pixels of
        self.cleared_points = np.zeros((0, 3))  # ... and the measured points it removed
        self.redundant = 0  # keyframes acknowledged but not stored: they added nothing new
        self.timings: dict[str, list[float]] = defaultdict(list)
        self._pending: dict[str, float] = {}  # keyframe timings not yet reported with a step

    def accept(self, kf: protocol.Keyframe | Frame, known: Callable[[tuple[str, int]], bool],
               stored: Callable[[tuple[str, int]], object] | None = None) -> Frame | None:
        """The keyframe's frame, after its rays have cleared what they pass through
        (``clearing``: measured points, the pixels of the stored keyframes ``stored(key)``
        returns (a ``StoredFrame`` or None), surfels) and the structure has processed it;
        None for a keyframe that adds nothing new and clears nothing (``coverage``: counted as
        ``redundant``). Returns the keys of stored keyframes that lost pixels in ``.touched``.
        Raises ValueError (and changes nothing) for one that cannot be used: a mask of another
        shape, too few valid depth pixels, or a (sensor, frame_id) ``known`` says is in the map."""
        frame = frame_from_keyframe(kf) if isinstance(kf, protocol.Keyframe) else kf
        valid = geometry.valid_depth(frame.depth, self.max_depth)
        if int(valid.sum()) < MIN_VALID_PIXELS:
            raise ValueError(f"only {int(valid.sum())} valid depth pixels (need {MIN_VALID_PIXELS})")
        if known(frame.key):
            raise ValueError(f"keyframe {frame.sensor}/{frame.frame_id} is already in the map")
        self.touched: list[tuple[str, int]] = []
        self.cleared_points = np.zeros((0, 3))
        news = False
        if self.policy.clear_free_space:
            t = time.perf_counter()
            news = self._clear(frame, stored)
            self.timings["clearing"].append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        redundant = not news and self.coverage.is_redundant(frame)
        self.timings["coverage"].append(1e3 * (time.perf_counter() - t))
        if redundant:
            self.redundant += 1
            return None
        if self.structure is not None:
            for k, v in self.structure.process(frame).items():
                self._pending[k] = self._pending.get(k, 0.0) + v
                self.timings[k].append(v)
            for key, S in self.structure.late if stored is not None else ():  # kept to move with a correction
                held = stored(key)
                if held is not None:
                    f = getattr(held, "frame", held)
                    f.late_surfels = S if f.late_surfels is None else Surfels.concat([f.late_surfels, S])
        return frame

    def _clear(self, frame: Frame, stored) -> bool:
        """``clearing``'s three retirements for one new keyframe; True when they are news
        (``clearing.NEWS_VOXELS``: the keyframe is then not redundant)."""
        p = self.policy
        ev = clearing.FreeSpace(frame.depth, frame.K, frame.T_WC, self.max_depth, p.clear_margin_m, p.clear_sigmas,
                                window_deg=p.clear_window_deg)
        keys, self.cleared_points, solid = clearing.clear_measured(self.measured, ev, p.clear_passes)
        n_meas = len(keys)
        if stored is not None and (n_meas or self.measured is None):
            cands = (clearing.candidate_keyframes(self.coverage, keys) if self.measured is not None
                     else list(self.coverage.views))
            for key in cands:
                sf = stored(key)
                if sf is None:
                    continue
                n = clearing.clear_pixels(sf.raw, sf.scale, sf.frame.K, sf.frame.T_WC, ev)
                if n:
                    self.coverage.remove(key)
                    self.coverage.add(key, sf.frame)
                    self.cleared["pixels"] += n
                    self.cleared["keyframes"] += 1
                    self.touched.append(key)
        n_surf = 0
        if self.structure is not None and len(self.structure.map):
            n_surf = self.structure.remove_surfels(clearing.surfels_passed(self.structure.map.surfels(), ev))
        self.cleared["measured"] += n_meas
        self.cleared["surfels"] += n_surf
        return solid >= clearing.NEWS_VOXELS or n_surf > 0

    def record(self, frame: Frame) -> None:
        """The stored keyframe's part in the box, the observed space, the measured points and
        the coverage."""
        self.bounds = grow_bounds(self.bounds, frame, self.max_depth)
        self.coverage.add(frame.key, frame)
        t = time.perf_counter()
        self.observed.add(frame.depth, frame.K, frame.T_WC, self.max_depth)
        self.timings["observed"].append(1e3 * (time.perf_counter() - t))
        if self.measured is not None:
            t = time.perf_counter()
            self.measured.add(frame.depth, frame.K, frame.T_WC)
            self.timings["measured"].append(1e3 * (time.perf_counter() - t))

    def take_pending(self) -> dict[str, float]:
        """The keyframe timings since the last step (a step reports them with its own)."""
        out, self._pending = self._pending, {}
        return out

    def record_step(self, info: dict, wall_ms: float) -> None:
        for k, v in info.get("timings_ms", {}).items():
            self.timings[k].append(v)
        self.timings["step_wall"].append(wall_ms)
        for v in self.timings.values():
            del v[:-TIMING_HISTORY]

    def stats(self) -> dict:
        """Mean timings (ms) over recent values, and the structure's counters."""
        out = {k: round(float(np.mean(v)), 3) for k, v in self.timings.items() if v}
        out["redundant"] = self.redundant
        out.update({f"cleared_{k}": v for k, v in self.cleared.items()})
        if self.structure is not None:
            out.update(self.structure.stats())
        return out

    def surfel_map(self, version: int) -> protocol.SurfelMap | None:
        return surfel_map_message(self.structure, version)

    def surfels(self):
        return None if self.structure is None else self.structure.global_surfels()
