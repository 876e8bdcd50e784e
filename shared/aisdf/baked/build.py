"""Baking (``aisdf.baked``, its docstring says the layout): sampling a field over observed
space coarse to fine, and re-baking what changed on an older bake's lattice."""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np

from .field import BakedField


@dataclass
class BakeConfig:
    block: float = 0.2  # block edge (m), also the coarse spacing
    fine: int = 2  # fine cells per block edge: spacing block / fine
    band: float = 0.05  # extra margin (m) on the surface-proximity test of the coarse corners
    tol: float = 0.005  # refine a block whose coarse interpolant misses the field at its centre by more (m)
    near_surface: bool = False  # also refine every block a surface may cross


_CORNERS = list(itertools.product((0, 1), repeat=3))  # a cell's 8 corners as index offsets


def _dilate26(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, structure=np.ones((3, 3, 3), bool))


def _lattice_offset(previous: "BakedField | None", origin: np.ndarray, B: float, nf: int) -> np.ndarray | None:
    """Integer block offset of ``origin`` in ``previous``'s lattice, or None when the two
    lattices differ (then nothing is reused)."""
    if previous is None or previous.centres is None or previous.nf != nf or abs(previous.block - B) > 1e-9 * B:
        return None
    off = (origin - previous.origin) / B
    r = np.round(off)
    if np.abs(off - r).max() > 1e-6:
        return None
    return r.astype(np.int64)


def _take(arr: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """arr[idx] for integer index rows (M, k) into arr's first k axes; NaN rows where out of range."""
    k = idx.shape[1]
    out = np.full((len(idx),) + arr.shape[k:], np.nan, np.float32)
    ok = np.all((idx >= 0) & (idx < np.array(arr.shape[:k])), axis=1)
    if ok.any():
        out[ok] = arr[tuple(idx[ok].T)]
    return out


def bake(fn, observed, cfg: BakeConfig | None = None, previous: BakedField | None = None,
         dirty=None) -> BakedField:
    """Bake ``fn`` (points (M, 3) float32 -> (sdf (M,), grad (M, 3)); called with all the
    points of a stage at once, it bounds its own memory) over the observed
    space ``observed`` (an :class:`aisdf.observed.ObservedGrid`), coarse to fine.

    With ``previous`` (an older bake on the same lattice) samples of it are reused where
    ``dirty`` (world points (M, 3) float64 -> (M,) bool, True where the field may differ
    from the one ``previous`` baked; None = nowhere) is False."""
    cfg = cfg or BakeConfig()
    t0 = time.perf_counter()
    B, nf = float(cfg.block), int(cfg.fine)
    origin = observed.origin.copy()
    off = _lattice_offset(previous, origin, B, nf)
    reused = 0
    extent = observed.voxel * np.array(observed.occ.shape)
    nb = np.maximum(np.ceil(extent / B - 1e-9).astype(np.int64), 1)
    # Blocks holding an observed voxel (voxel centres, so a voxel belongs to one block).
    vox_centres = (np.argwhere(observed.occ) + 0.5) * observed.voxel
    bidx = np.minimum(np.floor(vox_centres / B).astype(np.int64), nb - 1)
    state = np.zeros(tuple(nb), np.int8)
    state[bidx[:, 0], bidx[:, 1], bidx[:, 2]] = 1
    blocks = np.argwhere(state > 0)
    evals = 0

    def evaluate(pts: np.ndarray, old: np.ndarray | None = None) -> np.ndarray:
        """The field at ``pts``; ``old`` (M, 4) the previous bake's samples there (NaN: none)."""
        nonlocal evals, reused
        out = np.empty((len(pts), 4), np.float32)
        todo = np.ones(len(pts), bool)
        if old is not None and len(pts):
            todo = ~np.isfinite(old).all(axis=1)
            if dirty is not None and (~todo).any():
                todo[~todo] = np.asarray(dirty(pts[~todo]), bool)
            out[~todo] = old[~todo]
            reused += int((~todo).sum())
        n = int(todo.sum())
        if n:
            f, g = fn(pts[todo].astype(np.float32))  # fn chunks its own work (memory)
            out[todo, 0] = f
            out[todo, 1:] = g
        evals += n
        return out

    # Coarse level: the corners of every baked block.
    corner_mask = np.zeros(tuple(nb + 1), bool)
    for a, b, c in _CORNERS:
        corner_mask[blocks[:, 0] + a, blocks[:, 1] + b, blocks[:, 2] + c] = True
    corners = np.argwhere(corner_mask)
    C = np.full(tuple(nb + 1) + (4,), np.nan, np.float32)
    C[corners[:, 0], corners[:, 1], corners[:, 2]] = evaluate(
        origin + corners * B, None if off is None else _take(previous.C, corners + off))
    t_coarse = time.perf_counter() - t0
    # Core blocks: a surface may pass within band of them.
    absf = np.abs(C[..., 0])
    minc = np.full(tuple(nb), np.inf, np.float32)
    for a, b, c in _CORNERS:
        minc = np.fmin(minc, absf[a:a + nb[0], b:b + nb[1], c:c + nb[2]])
    near = minc < B * math.sqrt(3) / 2 + cfg.band
    # Coarse to fine: check the coarse interpolant at the centre of every baked block
    # against the field itself; where it is off by more than ``tol`` (object edges, the
    # distance field's ridges, curved surfaces) the block gets the fine level.
    no_fine = np.full(tuple(nb), -1, np.int32)
    coarse_only = BakedField(origin, B, (state > 0).astype(np.int8), C, no_fine, np.zeros(tuple(nb + 1), np.float32),
                             np.zeros((0, nf + 1, nf + 1, nf + 1, 4), np.float32), nf)
    centres = origin + (blocks + 0.5) * B
    centre_vals = evaluate(centres, None if off is None else _take(previous.centres, blocks + off))
    M = np.full(tuple(nb) + (4,), np.nan, np.float32)
    M[blocks[:, 0], blocks[:, 1], blocks[:, 2]] = centre_vals
    pred = coarse_only.query(centres, gradient=False)[0]
    bent = np.zeros(tuple(nb), bool)
    bent[blocks[:, 0], blocks[:, 1], blocks[:, 2]] = np.abs(pred - centre_vals[:, 0]) > cfg.tol
    core = (state > 0) & ((near & cfg.near_surface) | bent)
    fine = _dilate26(core) & (state > 0)
    state[fine] = 2
    fblocks = np.argwhere(fine)
    fidx = np.full(tuple(nb), -1, np.int32)
    fidx[fblocks[:, 0], fblocks[:, 1], fblocks[:, 2]] = np.arange(len(fblocks), dtype=np.int32)
    # Blend weights: 1 at a corner none of whose 8 blocks is a baked coarse-only block
    # (blocks outside the bake never answer, so they do not pull the blend down).
    padded = np.ones(tuple(nb + 2), bool)
    padded[1:-1, 1:-1, 1:-1] = fine | (state == 0)
    A = np.ones(tuple(nb + 1), bool)
    for a, b, c in _CORNERS:
        A &= padded[a:a + nb[0] + 1, b:b + nb[1] + 1, c:c + nb[2] + 1]
    A = A.astype(np.float32)
    # Fine level: unique lattice points (spacing B/nf) of the fine blocks, evaluated once.
    F = np.zeros((len(fblocks), nf + 1, nf + 1, nf + 1, 4), np.float32)
    if len(fblocks):
        local = np.stack(np.meshgrid(*(np.arange(nf + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
        lat = (fblocks[:, None, :] * nf + local[None]).reshape(-1, 3)  # global fine lattice index
        dims = nb * nf + 1
        key = (lat[:, 0] * dims[1] + lat[:, 1]) * dims[2] + lat[:, 2]
        ukey, inv = np.unique(key, return_inverse=True)
        uz = ukey % dims[2]
        uy = (ukey // dims[2]) % dims[1]
        ux = ukey // (dims[1] * dims[2])
        vals = np.empty((len(ukey), 4), np.float32)
        todo = np.ones(len(ukey), bool)
        if nf % 2 == 0:  # block centres are fine lattice points: evaluated already
            cl = blocks * nf + nf // 2
            ckey = (cl[:, 0] * dims[1] + cl[:, 1]) * dims[2] + cl[:, 2]
            pos = np.searchsorted(ukey, ckey)
            hit = (pos < len(ukey)) & (ukey[np.minimum(pos, len(ukey) - 1)] == ckey)
            vals[pos[hit]] = centre_vals[hit]
            todo[pos[hit]] = False
        ulat = np.stack([ux[todo], uy[todo], uz[todo]], -1)
        old = None
        if off is not None:  # the same lattice point in any refined block of the previous bake
            old = np.full((len(ulat), 4), np.nan, np.float32)
            plat = ulat + off * nf
            for d in _CORNERS:
                d = np.asarray(d)
                blk = plat // nf - d
                loc = plat - blk * nf
                ok = np.all((loc >= 0) & (loc <= nf), axis=1) & ~np.isfinite(old).all(axis=1)
                ok &= np.all((blk >= 0) & (blk < np.array(previous.fidx.shape)), axis=1)
                fi = np.full(len(blk), -1, np.int64)
                fi[ok] = previous.fidx[tuple(blk[ok].T)]
                ok &= fi >= 0
                if ok.any():
                    old[ok] = previous.F[fi[ok], loc[ok, 0], loc[ok, 1], loc[ok, 2]]
        vals[todo] = evaluate(origin + ulat * (B / nf), old)
        F[...] = vals[inv.reshape(-1)].reshape(F.shape)
    stats = {"blocks": int(len(blocks)), "fine_blocks": int(len(fblocks)), "core_blocks": int(core.sum()),
             "bent_blocks": int((bent & (state > 0)).sum()), "near_blocks": int((near & (state > 0)).sum()),
             "evaluations": int(evals), "reused": int(reused), "coarse_s": round(t_coarse, 3),
             "bake_s": round(time.perf_counter() - t0, 3)}
    field = BakedField(origin, B, state, C, fidx, A, F, nf, stats, centres=M)
    field.stats["bytes"] = field.nbytes
    return field
