"""One field from many submaps: each point answered by the submaps whose extended boxes
hold it, blended with the grid's C¹ weights (see ``grid.py``):

    f = sum_i w_i f_i / W,   grad f = (sum_i (w_i grad f_i + f_i grad w_i) − f grad W) / W,   W = sum_i w_i.

A point no submap covers is answered by the submap whose core is nearest (unblended,
``covered`` False), so every point gets a value. No torch here: a submap is a callable
``fn(points (M, 3) float32, grad: bool) -> (f (M,), g (M, 3) or None)``, so the mapper
(its trainers) and the query service (its rebuilt networks, or baked fields) share it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .grid import SubmapGrid, pack_cells, unpack_cells

Evaluator = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]


def assign(grid: SubmapGrid, cells, points_W: np.ndarray) -> dict[tuple[int, int, int], np.ndarray]:
    """{cell: indices of the points inside that cell's extended box}, over ``cells``."""
    cells = list(cells)
    p = np.asarray(points_W, np.float64).reshape(-1, 3)
    if not cells or not len(p):
        return {}
    have = np.sort(pack_cells(np.asarray(cells, np.int64)))
    out: dict[tuple[int, int, int], list[np.ndarray]] = {}
    for idx, near in grid.grown_cells(grid.to_grid(p), grid.overlap_m):
        k = pack_cells(near)
        pos = np.clip(np.searchsorted(have, k), 0, len(have) - 1)
        ok = have[pos] == k
        if not ok.any():
            continue
        idx, k = idx[ok], k[ok]
        order = np.argsort(k, kind="stable")
        idx, k = idx[order], k[order]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        ends = np.r_[starts[1:], len(k)]
        for a0, b0, c in zip(starts, ends, unpack_cells(k[starts])):
            out.setdefault((int(c[0]), int(c[1]), int(c[2])), []).append(idx[a0:b0])
    return {c: np.sort(np.concatenate(v)) for c, v in out.items()}


def covering(grid: SubmapGrid, cell_sets, points_W: np.ndarray) -> list[np.ndarray]:
    """For each set of cells in ``cell_sets``, (N,) bool: the points inside the extended box
    of one of its cells (``assign``'s membership, in one pass over the points and without
    grouping them per cell)."""
    p = np.asarray(points_W, np.float64).reshape(-1, 3)
    haves = [np.sort(pack_cells(np.asarray(list(cs), np.int64).reshape(-1, 3))) for cs in cell_sets]
    outs = [np.zeros(len(p), bool) for _ in haves]
    if not len(p) or not any(len(h) for h in haves):
        return outs
    for idx, near in grid.grown_cells(grid.to_grid(p), grid.overlap_m):
        k = pack_cells(near)
        for have, out in zip(haves, outs):
            if len(have):
                pos = np.minimum(np.searchsorted(have, k), len(have) - 1)
                out[idx[have[pos] == k]] = True
    return outs


def nearest_cell(grid: SubmapGrid, cells, points_W: np.ndarray) -> list[tuple[int, int, int]]:
    """For each point, the cell among ``cells`` whose core box is nearest (grid metric)."""
    cells = list(cells)
    g = grid.to_grid(points_W)
    best = np.full(len(g), np.inf)
    arg = np.zeros(len(g), np.int64)
    for n, c in enumerate(cells):
        lo, hi = grid.core_box(c)
        d = np.linalg.norm(np.maximum(np.maximum(lo - g, g - hi), 0.0), axis=1)
        better = d < best
        best[better], arg[better] = d[better], n
    return [cells[i] for i in arg]


def blend(grid: SubmapGrid, evaluators: dict[tuple[int, int, int], Evaluator], points_W: np.ndarray,
          grad: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(f (N,) float32, grad (N, 3) float32 or None, covered (N,) bool)."""
    p = np.asarray(points_W, np.float64).reshape(-1, 3)
    n = len(p)
    f_acc = np.zeros(n)
    w_acc = np.zeros(n)
    g_acc = np.zeros((n, 3)) if grad else None
    gw_acc = np.zeros((n, 3)) if grad else None
    if not evaluators or not n:
        nan = np.full(n, np.nan, np.float32)
        return nan, (np.full((n, 3), np.nan, np.float32) if grad else None), np.zeros(n, bool)
    for cell, idx in assign(grid, evaluators, p).items():
        q = p[idx]
        if grad:
            w, dw = grid.weight(cell, q, grad=True)
        else:
            w = grid.weight(cell, q)
        keep = w > 0
        if not keep.any():
            continue
        idx, q, w = idx[keep], q[keep], w[keep]
        f, g = evaluators[cell](q.astype(np.float32), grad)
        f = np.asarray(f, np.float64)
        f_acc[idx] += w * f
        w_acc[idx] += w
        if grad:
            dw = dw[keep]
            g_acc[idx] += w[:, None] * np.asarray(g, np.float64) + f[:, None] * dw
            gw_acc[idx] += dw
    covered = w_acc > 0
    out_f = np.zeros(n)
    out_f[covered] = f_acc[covered] / w_acc[covered]
    out_g = None
    if grad:
        out_g = np.zeros((n, 3))
        W = w_acc[covered, None]
        out_g[covered] = (g_acc[covered] - out_f[covered, None] * gw_acc[covered]) / W
    rest = np.flatnonzero(~covered)
    if len(rest):
        near = nearest_cell(grid, evaluators, p[rest])
        by: dict = {}
        for i, c in zip(rest, near):
            by.setdefault(c, []).append(i)
        for c, ii in by.items():
            ii = np.asarray(ii)
            f, g = evaluators[c](p[ii].astype(np.float32), grad)
            out_f[ii] = f
            if grad:
                out_g[ii] = g
    return out_f.astype(np.float32), (None if out_g is None else out_g.astype(np.float32)), covered
