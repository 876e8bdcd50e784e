"""Meshes of a field's zero level in bounded memory: marching cubes in tiles, seams welded."""

from __future__ import annotations

import numpy as np

from ..geometry import kdtree


def tiled_marching_cubes(fn, lo: np.ndarray, res: float, n, tile: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the zero level of ``fn`` (points (M, 3) float32 -> (M,)) on the
    lattice ``lo + res * (i, j, k)``, ``0 <= i < n[0]`` ..., in tiles of at most ``tile``
    samples per edge: neighbouring tiles share one plane of samples, so every cube is
    marched once and the vertices on a shared plane come out twice at the same place;
    those are welded. Memory: one tile's samples (and the mesh), whatever the box.
    Returns (vertices (V, 3) float64 world, faces (F, 3) int64)."""
    from skimage.measure import marching_cubes

    n = [int(x) for x in n]
    starts = [range(0, max(n[a] - 1, 1), tile - 1) for a in range(3)]
    verts, faces, count = [], [], 0
    for s0 in starts[0]:
        for s1 in starts[1]:
            for s2 in starts[2]:
                s = np.array([s0, s1, s2])
                e = np.minimum(s + tile, n)
                if np.any(e - s < 2):
                    continue
                axes = [lo[a] + res * np.arange(s[a], e[a]) for a in range(3)]
                pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
                vol = np.asarray(fn(pts), np.float32).reshape(tuple(e - s))
                del pts
                if not (vol.min() < 0 < vol.max()):
                    continue
                v, f, _, _ = marching_cubes(vol, level=0.0)
                verts.append(v.astype(np.float64) + s)  # lattice units
                faces.append(f.astype(np.int64) + count)
                count += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    V, F = np.concatenate(verts), np.concatenate(faces)
    # Weld the vertices on shared planes (integer lattice coordinates of a tile border).
    borders = [np.array([x for x in starts[a] if x > 0]) for a in range(3)]
    seam = np.zeros(len(V), bool)
    for a in range(3):
        if len(borders[a]):
            near = np.abs(V[:, a, None] - borders[a][None, :]).min(axis=1) < 1e-4
            seam |= near
    rep = np.arange(len(V))
    si = np.flatnonzero(seam)
    if len(si):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        pairs = kdtree(V[si]).query_pairs(1e-4, output_type="ndarray")
        if len(pairs):
            m = len(si)
            g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
            ncomp, lab = connected_components(g, directed=False)
            first = np.full(ncomp, m)
            np.minimum.at(first, lab, np.arange(m))  # the lowest index of each component
            rep[si] = si[first[lab]]
    keep = rep == np.arange(len(V))
    new_index = np.cumsum(keep) - 1
    return lo + res * V[keep], new_index[rep[F]]
