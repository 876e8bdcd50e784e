"""Finding the vertical of an Atlanta world from normals alone (atlanta.py's initialisation).

The vertical is never assumed to be a world axis. Candidates are the axial modes of the
normals (mean shift on the sphere, n ~ -n) and the cross products of pairs of modes (the
vertical when the first views hold walls but no floor). A candidate v *explains* the
normals within ``vertical_deg`` of +-v (floor, ceiling) or within ``wall_deg`` of its
horizon (walls); the true vertical of an Atlanta world explains every wall, a wall
direction does not explain the walls oblique to it. In a Manhattan world every axis
explains everything: the tie is broken by the ``up`` vector (a gravity hint, or the
cameras' up axis; candidates far from it are out), else by the most floor/ceiling-like
support. ``refine_vertical`` then
fits it by least squares (parallel to floor normals, orthogonal to wall normals).
"""

from __future__ import annotations

import numpy as np


def perpendicular(v: np.ndarray) -> np.ndarray:
    """A fixed unit vector orthogonal to v (from the world axis least aligned with it)."""
    a = np.eye(3)[int(np.argmin(np.abs(v)))]
    p = a - (a @ v) * v
    return p / np.linalg.norm(p)


def unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (S,3) . b (N,3) -> (S, N), without BLAS."""
    return a[:, 0, None] * b[:, 0] + a[:, 1, None] * b[:, 1] + a[:, 2, None] * b[:, 2]


def axial_modes(normals: np.ndarray, kernel_deg: float, min_fraction: float, n_seeds: int = 32,
                rng: np.random.Generator | None = None, max_points: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Axial mean-shift modes of unit vectors (n ~ -n): modes (K,3), support share (K,)."""
    rng = rng or np.random.default_rng(0)
    n = normals
    if len(n) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    c = np.cos(np.radians(kernel_deg))
    seeds = n[rng.choice(len(n), min(n_seeds, len(n)), replace=False)].copy()
    if len(n) > max_points:
        n = n[rng.choice(len(n), max_points, replace=False)]
    # Explicit per-component products, not @: multithreaded BLAS on these skinny products
    # is ten times slower on a busy CPU.
    for _ in range(10):
        d = _dots(seeds, n)
        w = np.where(np.abs(d) >= c, np.sign(d), 0.0)
        m = np.stack([(w * n[:, k]).sum(axis=1) for k in range(3)], axis=1)
        norm = np.linalg.norm(m, axis=1, keepdims=True)
        new = np.where(norm > 0, m / np.maximum(norm, 1e-12), seeds)
        done = np.min(np.abs(np.sum(new * seeds, axis=1))) > np.cos(np.radians(0.05))
        seeds = new
        if done:
            break
    support = (np.abs(_dots(seeds, n)) >= c).mean(axis=1)
    order = np.argsort(-support)
    modes: list[np.ndarray] = []
    sup: list[float] = []
    same = np.cos(np.radians(kernel_deg / 2))
    for i in order:
        if support[i] < min_fraction:
            break
        if all(abs(seeds[i] @ m) < same for m in modes):
            modes.append(seeds[i])
            sup.append(support[i])
    return np.array(modes).reshape(-1, 3), np.array(sup)


def vertical_lsq(normals: np.ndarray, v0: np.ndarray, floor_deg: float, wall_deg: float) -> np.ndarray:
    """(sum_wall n n^T - sum_floor n n^T) / N for inliers around v0: its smallest eigenvector is the vertical."""
    s = np.abs(normals @ v0)
    f = normals[s >= np.cos(np.radians(floor_deg))]
    w = normals[s <= np.sin(np.radians(wall_deg))]
    return (w.T @ w - f.T @ f) / max(len(normals), 1)


def smallest_eig(S: np.ndarray, v_prev: np.ndarray) -> np.ndarray:
    scale = max(np.abs(S).max(), 1e-12)
    _, V = np.linalg.eigh(S + 1e-3 * scale * (np.eye(3) - np.outer(v_prev, v_prev)))
    v = V[:, 0]
    return v if v @ v_prev >= 0 else -v


def refine_vertical(n: np.ndarray, v: np.ndarray, vertical_deg: float, wall_deg: float,
                    iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares vertical near v, and its normal matrix (see vertical_lsq)."""
    S = np.zeros((3, 3))
    for _ in range(iters):
        S = vertical_lsq(n, v, vertical_deg, wall_deg)
        v = smallest_eig(S, v)
    return v, S


def choose_vertical(n: np.ndarray, up: np.ndarray | None, *, mode_deg: float, min_fraction: float,
                    vertical_deg: float, wall_deg: float, tie_fraction: float,
                    rng: np.random.Generator, up_max_deg: float = 45.0) -> tuple[np.ndarray | None, bool]:
    """The vertical candidate that best explains normals n (N,3) and whether that is confident.

    Confident: it explains at least half the normals and has floor/ceiling support
    (``min_fraction``) or at least two wall modes on its horizon. With an ``up`` cue,
    candidates more than ``up_max_deg`` from it are out (None when none is left).
    """
    modes, _ = axial_modes(n, mode_deg, min_fraction, rng=rng)
    if len(modes) == 0:
        return None, False
    cands = list(modes)
    for i in range(len(modes)):
        for j in range(i + 1, len(modes)):
            c = np.cross(modes[i], modes[j])
            if np.linalg.norm(c) > np.sin(np.radians(30)):
                cands.append(unit(c))
    C = np.array(cands)
    dots = np.abs(_dots(C, n))
    par = dots >= np.cos(np.radians(vertical_deg))
    explained = (par | (dots <= np.sin(np.radians(wall_deg)))).mean(axis=1)
    parallel = par.mean(axis=1)
    n_walls = (np.abs(C @ modes.T) <= np.sin(np.radians(mode_deg))).sum(axis=1)
    if up is not None:  # a vertical far from the up cue is a wall seen face-on
        ok = np.abs(C @ up) >= np.cos(np.radians(up_max_deg))
        if not ok.any():
            return None, False
        explained = np.where(ok, explained, -1.0)
    tie = explained >= explained.max() - tie_fraction
    key = np.abs(C @ up) if up is not None else parallel
    best = int(np.argmax(np.where(tie, key, -np.inf)))
    confident = bool(explained[best] >= 0.5 and (parallel[best] >= min_fraction or n_walls[best] >= 2))
    return C[best], confident
