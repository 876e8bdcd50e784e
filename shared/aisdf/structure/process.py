"""Per keyframe, the structure part of AiSDF: update the global Atlanta frame from the
keyframe's normals (Sec. III-B), extract Atlanta-aware surfels and the surfel mask
(Sec. III-C), and merge the surfels into the global planar map (beyond the paper).
Pure numpy; the pipeline calls :meth:`Structure.process` for each keyframe.

Late surfels (beyond the paper): a keyframe's surfels lie only on the directions published
when it arrives, and a direction is published only once ``confirm_keyframes`` keyframes
have seen it, so the keyframes that saw a wall first, often the only ones that saw it
well, would never give it a surfel. The structure keeps the block-averaged points of the
last ``tentative_keyframes`` keyframes (the window in which a direction is confirmed; about
150 KB each; not in checkpoints); when a direction is published (or the frame initialised,
publishing the vertical and the first directions), those keyframes' surfels on the new
directions are extracted and merged into the global map (``late`` lists them, per
keyframe). They are for the planar map and what reads it (subscribers, the query service's
layout prior): training keeps the surfels and masks each keyframe was given on arrival, and
late extraction draws on its own random numbers (seeded by the keyframe), so training is
what it was without them."""

from __future__ import annotations

import json
import time
from collections import deque

import numpy as np

from ..geometry import valid_depth
from .atlanta import AtlantaConfig, AtlantaEstimator, AtlantaFrame
from ..mapping.frames import Frame
from .surfel_map import GlobalSurfelMap, SurfelMapConfig
from .surfel_types import Surfels
from .surfels import KeyframePoints, SurfelConfig, extract_surfels, keyframe_points, surfels_of_points


class Structure:
    def __init__(self, atlanta: AtlantaConfig | None = None, surfels: SurfelConfig | None = None,
                 surfel_map: SurfelMapConfig | None = None, seed: int = 0, max_depth: float = np.inf):
        self.max_depth = float(max_depth)  # pixels beyond it (the mapper's max_depth) are not used
        self.estimator = AtlantaEstimator(atlanta, seed=seed)
        self.surfel_cfg = surfels or SurfelConfig()
        self.map = GlobalSurfelMap(surfel_map)
        self.rng = np.random.default_rng(seed)
        self.n_keyframes = 0
        self._aligned: tuple[int, Surfels] | None = None
        # (key, frame_id, points as float32) of the last keyframes, for their late surfels
        self._recent: deque = deque(maxlen=max(self.estimator.config.tentative_keyframes, 1))
        self.late: list[tuple[tuple, Surfels]] = []  # the last process()'s late surfels, per earlier keyframe
        self.n_late = 0  # late surfels produced, in all

    def process(self, frame: Frame) -> dict[str, float]:
        """Fills ``frame.surfels`` and ``frame.surfel_mask`` from the frame's valid depth
        (``geometry.valid_depth`` with ``max_depth``); returns timings in ms
        (``atlanta``: points, normals and the frame update; ``surfels``: extraction, mask
        and the global merge)."""
        t0 = time.perf_counter()
        depth = self._depth(frame)
        kp = keyframe_points(depth, frame.K, frame.T_WC, self.surfel_cfg)
        before = self._published()
        local = self.estimator.update(kp.normals_W, frame.T_WC)
        t1 = time.perf_counter()
        surfels, mask = extract_surfels(depth, frame.K, frame.T_WC, local.frame, self.surfel_cfg, self.rng,
                                        frame.frame_id, points=kp)
        frame.surfels, frame.surfel_mask = surfels, mask
        self.map.add(surfels)
        self.late = self._late(self._published() - before)
        self._recent.append((frame.key, frame.frame_id, _compact(kp)))
        t2 = time.perf_counter()
        self.n_keyframes += 1
        return {"atlanta": 1e3 * (t1 - t0), "surfels": 1e3 * (t2 - t1)}

    def _depth(self, frame: Frame) -> np.ndarray:
        """The frame's depth in metres, 0 where ``valid_depth`` (with ``max_depth``) says no: the
        mapper's rule, no surfel or normal from a pixel it would not train on."""
        depth = frame.metres()
        valid = valid_depth(depth, self.max_depth)
        return depth if valid.all() else np.where(valid, depth, 0.0).astype(np.float32)

    def _published(self) -> set[int]:
        """The direction indices published so far (-1: the vertical, once initialised)."""
        f = self.estimator.frame
        return set() if not f.valid else {-1, *(int(i) for i in f.indices)}

    def _late(self, new: set[int]) -> list[tuple[tuple, Surfels]]:
        """The earlier keyframes' surfels on the directions ``new`` (just published), merged into
        the global map: [(keyframe key, surfels)] for those that have any."""
        out: list[tuple[tuple, Surfels]] = []
        if not new:
            return out
        frame = self.estimator.frame
        for key, frame_id, kp in self._recent:
            s = surfels_of_points(kp, frame, self.surfel_cfg, None, frame_id, directions=new)
            if len(s):
                self.map.add(s)
                out.append((key, s))
                self.n_late += len(s)
        return out

    def extract_again(self, frame: Frame) -> None:
        """Fits ``frame.surfels`` (and ``surfel_mask``) afresh from its depth at its (corrected)
        pose, on every published direction of the current frame, without touching the frame
        estimate or the global map: surfels fitted at a drifted pose, on directions averaged
        from drifting normals, keep a tilt of their own once moved. Its late surfels are then
        among them (``late_surfels`` is cleared). A keyframe that gave no surfel gives none.
        Random numbers seeded by the keyframe (repeatable)."""
        own, late = frame.surfels, frame.late_surfels
        if not self.estimator.initialised or not ((own is not None and len(own)) or (late is not None and len(late))):
            return
        depth = self._depth(frame)
        rng = np.random.default_rng([int(frame.frame_id) & 0x7FFFFFFF, 7])
        frame.surfels, frame.surfel_mask = extract_surfels(depth, frame.K, frame.T_WC, self.estimator.frame,
                                                           self.surfel_cfg, rng, frame.frame_id,
                                                           floor_axes=self._floor_axes(own, late))
        frame.late_surfels = None

    def _floor_axes(self, *old: Surfels | None) -> np.ndarray | None:
        """The current frame's horizontals that a keyframe's horizontal surfels (``old``, moved
        with its pose) were aligned with (each axis to the nearest, modulo 90 degrees); None
        when it had no horizontal surfel (then every horizontal is a candidate)."""
        f = self.estimator.frame
        H = np.asarray(f.horizontal, np.float64).reshape(-1, 3)
        axes = [np.asarray(S.axis1, np.float64)[np.asarray(S.direction) < 0] for S in old if S is not None and len(S)]
        axes = np.concatenate(axes) if axes else np.zeros((0, 3))
        if not len(axes) or not len(H):
            return None
        v = np.asarray(f.vertical, np.float64)
        # the axial angle modulo 90 degrees: |cos| or |sin| of the angle between them, in the floor
        c = np.abs(axes @ H.T)
        s = np.abs(np.cross(axes[:, None], H[None]) @ v)
        near = np.argmax(np.maximum(c, s), axis=1)
        return H[np.unique(near)]

    def follow_corrections(self, frames: list, moved: dict) -> dict[int, float]:
        """After a pose correction (``moved``: key -> the old pose; ``frames`` the stored ones at
        their new poses): the Atlanta frame turns with the keyframes that support it. Each
        published direction (and the vertical) is turned by the mean of its supporting
        keyframes' rotations, weighted by the area of their surfels on it (a keyframe not moved
        counts with none), the tentative ones by the mean over all stored keyframes; so a frame
        estimated from drifting poses becomes the frame of the corrected ones (a 2 degree drift
        otherwise leaves the directions, and the surfels aligned to them, a degree off).
        Returns the angle (degrees) each direction turned by (-1: the vertical)."""
        rot = {}
        for f in frames:
            if f.key in moved:
                R = np.asarray(f.T_WC, np.float64)[:3, :3] @ np.asarray(moved[f.key], np.float64)[:3, :3].T
                rot[f.key] = R
        if not rot or not self.estimator.initialised:
            return {}
        I = np.eye(3)
        acc: dict[int, list] = {}
        for f in frames:
            S = f.surfels
            if S is None or not len(S):
                continue
            area = np.prod(np.asarray(S.extent, np.float64), axis=1)
            R = rot.get(f.key, I)
            for j in np.unique(S.direction):
                w = float(area[S.direction == j].sum())
                a = acc.setdefault(int(j), [0.0, np.zeros((3, 3))])
                a[0] += w
                a[1] += w * R
        mean = {j: _nearest_rotation(M / w) for j, (w, M) in acc.items() if w > 0}
        default = _nearest_rotation(sum(rot.values(), np.zeros((3, 3))) / len(frames) + I * (1 - len(rot) / len(frames)))
        before = self.estimator.frame
        self.estimator.turn(mean, default)
        after = self.estimator.frame
        self._aligned = None
        out = {-1: float(np.degrees(np.arccos(np.clip(before.vertical @ after.vertical, -1, 1))))}
        for k, (h0, h1) in enumerate(zip(np.asarray(before.horizontal), np.asarray(after.horizontal))):
            out[int(before.indices[k])] = float(np.degrees(np.arccos(np.clip(abs(h0 @ h1), -1, 1))))
        return out

    def forget_recent(self, keys) -> None:
        """Drops the kept points of these keyframes (moved by a pose correction: the points are
        where the old pose put them)."""
        keys = set(keys)
        kept = [r for r in self._recent if r[0] not in keys]
        self._recent.clear()
        self._recent.extend(kept)

    def remove_surfels(self, which: np.ndarray) -> int:
        """Removes global surfels (a boolean mask over ``map``): seen through as free space."""
        n = self.map.remove(which)
        if n:
            self._aligned = None
        return n

    def atlanta_frame(self) -> AtlantaFrame | None:
        f = self.estimator.frame
        return f if f.valid else None

    def global_surfels(self) -> Surfels:
        f = self.atlanta_frame()
        if f is not None:
            self.map.realign(f)
        return self.map.surfels()

    def aligned_surfels(self) -> Surfels:
        """The global map realigned to the current Atlanta frame, as a copy, without touching
        the map (so that reading it changes nothing; once per keyframe, shared by its readers:
        do not modify it)."""
        if self._aligned is None or self._aligned[0] != self.n_keyframes:
            self._aligned = (self.n_keyframes, self.map.aligned(self.atlanta_frame()))
        return self._aligned[1]

    def stats(self) -> dict:
        f = self.atlanta_frame()
        return {"horizontal_directions": 0 if f is None else int(len(f.horizontal)),
                "surfels_produced": int(self.map.n_produced), "surfels_kept": int(self.map.n_kept),
                "surfels_late": int(self.n_late)}

    def state_dict(self) -> dict:
        return {"estimator": self.estimator.state_dict(), "map": self.map.state_dict(),
                "n_keyframes": self.n_keyframes, "rng": json.dumps(self.rng.bit_generator.state)}

    def load_state_dict(self, state: dict) -> None:
        self.estimator.load_state_dict(state["estimator"])
        self.map.load_state_dict(state["map"])
        self.n_keyframes = int(state.get("n_keyframes", 0))
        if state.get("rng") is not None:  # absent in checkpoints before 2026-12-02: a fresh generator
            self.rng.bit_generator.state = json.loads(state["rng"])
        self._aligned = None


def _compact(kp: KeyframePoints) -> KeyframePoints:
    """The points kept for late surfels, as float32 (half the memory; extraction's tolerances
    are millimetres and more)."""
    f = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return KeyframePoints(f(kp.points_W), f(kp.normals_W), f(kp.depth), f(kp.spacing), np.asarray(kp.cam_W, np.float64),
                          kp.stride)


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` (3x3; a mean of rotations), by SVD."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R
