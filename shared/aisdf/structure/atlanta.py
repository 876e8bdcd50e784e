"""The global Atlanta frame, estimated continually from keyframe normals (paper Sec. III-B).

An Atlanta frame is a vertical direction and M horizontal directions orthogonal to it.
``AtlantaEstimator.update(normals_W)`` takes the world-frame unit normals of one keyframe
and returns the keyframe's ``LocalAtlanta`` (the published global directions it supports).

Initialisation (first keyframes, atlanta_init.py): the vertical is found from the data,
never assumed to be a world axis: of the axial modes of the normals and the cross
products of pairs of them, the candidate that explains the most normals as floor/ceiling
or wall; Manhattan ties are broken by ``up_hint`` (a world vector, e.g. gravity) when the
caller has one, else by the cameras' up axis (-y of the OpenCV camera in ``T_WC``),
else by the most floor/ceiling support. Initialisation waits (up to
``init_max_keyframes``) until one candidate is confident (floor/ceiling support, or two
wall directions on its horizon) and, with an up cue, within ``init_up_max_deg`` of it.
Failure modes: cameras rolled or pitched by about 45 degrees or more with no
``up_hint`` (the camera cue then misleads); a Manhattan scene with neither ``T_WC`` nor
``up_hint`` (every axis explains everything: the axis with the most support wins, often
the wall seen face-on); first views of a single plane (it waits, then takes the best
guess or the up cue); scenes whose dominant planes are not Atlanta (sloped ceilings)
bias the vertical. The vertical points up when an up cue is given.

Per keyframe (initialised): the vertical is refined slowly (exponentially weighted
least squares over ``vertical_memory`` keyframes, at most ``max_vertical_step_deg`` per
keyframe); normals within ``horizon_deg`` of the horizon give a ``bins``-bin histogram
of their horizontal angle (1 degree bins over -180..180), folded modulo 180 degrees (the
two faces of a wall are one direction), smoothed with a circular Gaussian; its peaks
with enough support are candidates, refined to sub-degree by the axial mean of the
normals near the peak, and associated with the nearest direction within ``assoc_deg``
(refined by a weighted running average) or added as a new *tentative* direction. A
tentative direction is published (gets the next index of ``AtlantaFrame.horizontal``)
once seen in ``confirm_keyframes`` keyframes, and dropped if that does not happen
within ``tentative_keyframes`` keyframes of its first sighting. Published indices never
change (surfels refer to them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import Field
from scipy.ndimage import gaussian_filter1d

from .atlanta_init import choose_vertical, perpendicular, refine_vertical, smallest_eig, unit, vertical_lsq
from ..config import Model


class AtlantaConfig(Model):
    """Atlanta frame estimation; angles in degrees."""

    horizon_deg: float = Field(20.0, description="normals within this of the horizon vote for horizontal directions")
    assoc_deg: float = Field(20.0, description="a candidate within this of a known direction is that direction")
    bins: int = Field(361, description="histogram bins over -180..180 (361: 1 degree bins)")
    smooth_sigma_deg: float = Field(1.5, description="Gaussian smoothing of the histogram")
    peak_window_deg: float = Field(4.0, description="half-width around a peak that counts as its support")
    refine_window_deg: float = Field(9.0, description="half-width of the mean shift that refines a peak's angle")
    min_peak_fraction: float = Field(0.03, description="peak support / all normals of the keyframe, at least")
    min_peak_points: int = Field(30, description="peak support in normals, at least")
    peak_contrast: float = Field(4.0, description="peak support / support of a uniform spread of the band, at least")
    confirm_keyframes: int = Field(2, description="keyframes a new direction must be seen in before it is published")
    tentative_keyframes: int = Field(
        10, description="a tentative direction not confirmed this many keyframes after its first sighting is dropped")
    direction_memory: float = Field(30.0, description="running-average memory of a direction, in keyframes")
    vertical_inlier_deg: float = Field(10.0, description="floor/ceiling normals: within this of +-vertical")
    wall_inlier_deg: float = Field(8.0, description="walls constraining the vertical: within this of the horizon")
    vertical_memory: float = Field(30.0, description="vertical refinement memory, in keyframes")
    max_vertical_step_deg: float = Field(0.5, description="largest change of the vertical per keyframe")
    init_mode_deg: float = Field(10.0, description="mean-shift kernel radius on the sphere of normals")
    init_min_fraction: float = Field(0.05, description="a normal mode must hold this share of normals")
    init_tie_fraction: float = Field(0.15, description="vertical candidates explaining within this of the best tie")
    init_up_max_deg: float = Field(45.0, description="with an up cue, the vertical is within this of it")
    init_max_keyframes: int = Field(5, description="keyframes to wait for a confident initialisation")
    min_normals: int = Field(100, description="a keyframe with fewer valid normals is skipped")
    max_normals: int = Field(20000, description="random subsample above this (speed)")


@dataclass
class AtlantaFrame:
    """The published global Atlanta frame (world frame).

    vertical (3,) unit; horizontal (M,3) unit, orthogonal to vertical, index k is the
    ``direction`` k of surfels (vertical is -1); counts (M,) keyframes that saw each;
    vertical_count: keyframes that refined the vertical; valid: False before initialisation
    (then vertical is a placeholder and surfel extraction returns nothing).
    """

    vertical: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    horizontal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    counts: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    vertical_count: int = 0
    valid: bool = True  # False until the estimator has found the vertical

    @property
    def indices(self) -> np.ndarray:
        return np.arange(len(self.horizontal))

    @property
    def reference(self) -> np.ndarray:
        """horizontal[0], or a fixed horizontal vector while there is none."""
        return self.horizontal[0] if len(self.horizontal) else perpendicular(self.vertical)

    def direction(self, index: int) -> np.ndarray:
        """The unit vector of direction ``index`` (-1 = vertical)."""
        return self.vertical if index < 0 else self.horizontal[index]

    def angles_deg(self) -> np.ndarray:
        """Angle of each horizontal direction about the vertical from horizontal[0] (paper's alpha)."""
        e1 = self.reference
        e2 = np.cross(self.vertical, e1)
        return np.degrees(np.arctan2(self.horizontal @ e2, self.horizontal @ e1))

    def rotation(self) -> np.ndarray:
        """The paper's AF parametrisation R = [vertical, horizontal[0], vertical x horizontal[0]]."""
        e1 = self.reference
        return np.stack([self.vertical, e1, np.cross(self.vertical, e1)], axis=1)


@dataclass
class LocalAtlanta:
    """The directions one keyframe supports: published indices into ``frame.horizontal``."""

    vertical: np.ndarray
    horizontal: np.ndarray  # (K, 3)
    indices: np.ndarray  # (K,) int
    support: np.ndarray  # (K,) share of the keyframe's normals
    frame: AtlantaFrame  # the global frame after this update
    initialised: bool = True

    @property
    def reference(self) -> np.ndarray:
        return self.frame.reference


@dataclass
class _Direction:
    vector: np.ndarray
    weight: float
    seen: int
    first_seen: int
    last_seen: int
    index: int = -1  # published index, -1 while tentative


def _axial_diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b modulo 180, in [-90, 90)."""
    return (np.asarray(a) - b + 90.0) % 180.0 - 90.0


class AtlantaEstimator:
    """Continual global Atlanta frame estimation; see the module docstring."""

    def __init__(self, config: AtlantaConfig | None = None, seed: int = 0) -> None:
        self.config = config or AtlantaConfig()
        self.rng = np.random.default_rng(seed)
        self.vertical: np.ndarray | None = None
        self._S = np.zeros((3, 3))
        self._dirs: list[_Direction] = []
        self._published: list[_Direction] = []
        self._k = 0  # keyframes seen
        self._buffer: list[np.ndarray] = []
        self._ups: list[np.ndarray] = []
        self.vertical_count = 0

    # ------------------------------------------------------------------ public
    @property
    def initialised(self) -> bool:
        return self.vertical is not None

    @property
    def frame(self) -> AtlantaFrame:
        v = self.vertical if self.vertical is not None else np.array([0.0, 0.0, 1.0])
        hs = np.array([d.vector for d in self._published]).reshape(-1, 3)
        return AtlantaFrame(v.copy(), hs, np.array([d.seen for d in self._published], dtype=np.int64),
                            self.vertical_count, self.initialised)

    @property
    def n_tentative(self) -> int:
        return sum(d.index < 0 for d in self._dirs)

    def update(self, normals_W: np.ndarray, T_WC: np.ndarray | None = None,
               up_hint: np.ndarray | None = None) -> LocalAtlanta:
        """Take one keyframe's world-frame unit normals (N,3); return its local Atlanta frame.

        ``T_WC`` (4x4) gives the camera-up cue for initialisation and the vertical's sign;
        ``up_hint`` (a world vector, e.g. from gravity) overrides it. Both are optional.
        """
        cfg = self.config
        n = np.asarray(normals_W, dtype=np.float64).reshape(-1, 3)
        n = n[np.isfinite(n).all(axis=1)]
        if len(n) > cfg.max_normals:
            n = n[self.rng.choice(len(n), cfg.max_normals, replace=False)]
        up = self._up(T_WC, up_hint)
        self._k += 1
        if len(n) < cfg.min_normals:
            return self._empty_local()
        if not self.initialised:
            self._buffer = self._buffer[-(cfg.init_max_keyframes - 1):] + [n] if cfg.init_max_keyframes > 1 else [n]
            if up is not None:
                self._ups = self._ups[-(cfg.init_max_keyframes - 1):] + [up] if cfg.init_max_keyframes > 1 else [up]
            if not self._try_init(up_hint):
                return self._empty_local()
            locals_ = [self._horizontal_step(b) for b in self._buffer]
            self._buffer, self._ups = [], []
            self._prune()
            return locals_[-1]
        self._refine_vertical(n)
        local = self._horizontal_step(n)
        self._prune()
        return local

    def turn(self, rotations: dict[int, np.ndarray], default: np.ndarray) -> None:
        """Turns the estimate by rotations (3x3): the vertical (and its scatter) by
        ``rotations[-1]``, published direction ``k`` by ``rotations[k]``, the others by
        ``default``; the horizontals are made orthogonal to the vertical again. For pose
        corrections: the normals a direction was averaged from turn with their keyframes."""
        if self.vertical is None:
            return
        R = rotations.get(-1, default)
        self.vertical = unit(R @ self.vertical)
        self._S = R @ self._S @ R.T
        for d in self._dirs:
            h = rotations.get(d.index, default) @ d.vector if d.index >= 0 else default @ d.vector
            h = h - (h @ self.vertical) * self.vertical
            if np.linalg.norm(h) > 1e-9:
                d.vector = unit(h)

    # ------------------------------------------------------------------ state (checkpoints)
    def state_dict(self) -> dict:
        return {
            "vertical": None if self.vertical is None else self.vertical.tolist(),
            "S": self._S.tolist(), "k": self._k, "vertical_count": self.vertical_count,
            "dirs": [{"vector": d.vector.tolist(), "weight": d.weight, "seen": d.seen,
                      "first_seen": d.first_seen, "last_seen": d.last_seen, "index": d.index} for d in self._dirs],
        }

    def load_state_dict(self, state: dict) -> None:
        self.vertical = None if state["vertical"] is None else np.asarray(state["vertical"], dtype=np.float64)
        self._S = np.asarray(state["S"], dtype=np.float64)
        self._k = int(state["k"])
        self.vertical_count = int(state["vertical_count"])
        self._dirs = [_Direction(np.asarray(d["vector"], dtype=np.float64), float(d["weight"]), int(d["seen"]),
                                 int(d["first_seen"]), int(d["last_seen"]), int(d["index"])) for d in state["dirs"]]
        self._published = sorted((d for d in self._dirs if d.index >= 0), key=lambda d: d.index)

    # ------------------------------------------------------------------ steps
    @staticmethod
    def _up(T_WC: np.ndarray | None, up_hint: np.ndarray | None) -> np.ndarray | None:
        if up_hint is not None:
            return unit(np.asarray(up_hint, dtype=np.float64))
        if T_WC is not None:
            return -np.asarray(T_WC, dtype=np.float64)[:3, 1]  # OpenCV: image y points down
        return None

    def _empty_local(self) -> LocalAtlanta:
        f = self.frame
        return LocalAtlanta(f.vertical, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0), f,
                            self.initialised)

    def _try_init(self, up_hint: np.ndarray | None) -> bool:
        cfg = self.config
        n = np.concatenate(self._buffer)
        if len(n) > cfg.max_normals:
            n = n[self.rng.choice(len(n), cfg.max_normals, replace=False)]
        up = unit(np.asarray(up_hint, dtype=np.float64)) if up_hint is not None else (
            unit(np.mean(self._ups, axis=0)) if self._ups else None)
        v, confident = choose_vertical(
            n, up, mode_deg=cfg.init_mode_deg, min_fraction=cfg.init_min_fraction,
            vertical_deg=cfg.vertical_inlier_deg, wall_deg=cfg.wall_inlier_deg,
            tie_fraction=cfg.init_tie_fraction, rng=self.rng, up_max_deg=cfg.init_up_max_deg)
        last_chance = len(self._buffer) >= cfg.init_max_keyframes
        if v is None:
            v = up
        if v is None or not (confident or last_chance):
            return False
        v, self._S = refine_vertical(n, v, cfg.vertical_inlier_deg, cfg.wall_inlier_deg)
        if up is not None and v @ up < 0:
            v = -v
        self.vertical = v
        self.vertical_count = len(self._buffer)
        return True

    def _refine_vertical(self, n: np.ndarray) -> None:
        cfg = self.config
        v = self.vertical
        M = vertical_lsq(n, v, cfg.vertical_inlier_deg, cfg.wall_inlier_deg)
        self._S = self._S * (1.0 - 1.0 / cfg.vertical_memory) + M
        v_new = smallest_eig(self._S, v)
        ang = np.arccos(np.clip(v_new @ v, -1.0, 1.0))
        max_step = np.radians(cfg.max_vertical_step_deg)
        if ang > max_step:  # slerp towards v_new by max_step
            axis = v_new - (v_new @ v) * v
            v_new = np.cos(max_step) * v + np.sin(max_step) * axis / np.linalg.norm(axis)
        self.vertical = unit(v_new)
        self.vertical_count += 1
        for d in self._dirs:  # keep horizontals on the horizon
            d.vector = unit(d.vector - (d.vector @ self.vertical) * self.vertical)

    def _basis(self) -> tuple[np.ndarray, np.ndarray]:
        e1 = self._published[0].vector if self._published else perpendicular(self.vertical)
        return e1, np.cross(self.vertical, e1)

    def _candidates(self, n: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> list[tuple[float, float]]:
        """Peaks of the folded horizontal-angle histogram: [(angle deg in [0,180), support share)]."""
        cfg = self.config
        band = np.abs(n @ self.vertical) <= np.sin(np.radians(cfg.horizon_deg))
        nb = n[band]
        if len(nb) < cfg.min_peak_points:
            return []
        ang = np.degrees(np.arctan2(nb @ e2, nb @ e1))  # -180..180
        width = 360.0 / (cfg.bins - 1)
        half = (cfg.bins - 1) // 2  # bins per 180 degrees
        idx = np.rint((ang + 180.0) / width).astype(np.int64)  # 0..bins-1
        hist = np.bincount(idx % half, minlength=half).astype(np.float64)  # folded: angle mod 180
        sm = gaussian_filter1d(hist, cfg.smooth_sigma_deg / width, mode="wrap")
        peaks = np.flatnonzero((sm >= np.roll(sm, 1)) & (sm > np.roll(sm, -1)) & (sm > 0))
        peaks = peaks[np.argsort(-sm[peaks])]
        min_support = max(cfg.min_peak_points, cfg.min_peak_fraction * len(n),
                          cfg.peak_contrast * len(nb) * 2 * cfg.peak_window_deg / 180.0)
        out: list[tuple[float, float]] = []
        for p in peaks[:16]:
            a0 = p * width
            d = _axial_diff_deg(ang, a0)
            near = np.abs(d) <= cfg.peak_window_deg
            support = int(near.sum())
            if support < min_support:
                continue
            a = a0
            for _ in range(5):  # sub-bin refinement: mean shift with a flat window (unbiased for symmetric noise)
                dd = _axial_diff_deg(ang, a)
                w = np.abs(dd) <= cfg.refine_window_deg
                step = dd[w].mean() if w.any() else 0.0
                a = (a + step) % 180.0
                if abs(step) < 0.01:
                    break
            if any(abs(_axial_diff_deg(a, b)) < 2 * cfg.peak_window_deg for b, _ in out):
                continue
            out.append((a, support / len(n)))
        return out

    def _horizontal_step(self, n: np.ndarray) -> LocalAtlanta:
        cfg = self.config
        e1, e2 = self._basis()
        cands = self._candidates(n, e1, e2)
        known = np.array([np.degrees(np.arctan2(d.vector @ e2, d.vector @ e1)) for d in self._dirs])
        claimed: set[int] = set()
        matched: list[tuple[_Direction, float]] = []
        for a, support in cands:  # strongest first
            if len(known):
                diff = _axial_diff_deg(a, known)
                j = int(np.argmin(np.abs(diff)))
                if abs(diff[j]) <= cfg.assoc_deg:
                    if j in claimed:
                        continue
                    claimed.add(j)
                    d = self._dirs[j]
                    mean_w = d.weight / max(d.seen, 1)
                    alpha = support / (d.weight + support)
                    th = np.radians(known[j] + alpha * diff[j])
                    d.vector = unit(np.cos(th) * e1 + np.sin(th) * e2)
                    d.weight = min(d.weight + support, cfg.direction_memory * max(mean_w, support))
                    d.seen += 1
                    d.last_seen = self._k
                    if d.index < 0 and d.seen >= cfg.confirm_keyframes:
                        self._publish(d)
                    matched.append((d, support))
                    continue
            th = np.radians(a)
            d = _Direction(unit(np.cos(th) * e1 + np.sin(th) * e2), support, 1, self._k, self._k)
            self._dirs.append(d)
            known = np.append(known, a)
            claimed.add(len(self._dirs) - 1)
            if cfg.confirm_keyframes <= 1:
                self._publish(d)
            matched.append((d, support))
        pub = [(d, s) for d, s in matched if d.index >= 0]
        pub.sort(key=lambda t: t[0].index)
        f = self.frame
        return LocalAtlanta(
            f.vertical, np.array([d.vector for d, _ in pub]).reshape(-1, 3),
            np.array([d.index for d, _ in pub], dtype=np.int64), np.array([s for _, s in pub]), f, True)

    def _publish(self, d: _Direction) -> None:
        d.index = len(self._published)
        self._published.append(d)

    def _prune(self) -> None:
        k = self._k
        self._dirs = [d for d in self._dirs if d.index >= 0 or k - d.first_seen < self.config.tentative_keyframes]
