"""Meshes from the query engine (``aisdf.query.meshing``): tiled meshes equal untiled ones
(a single network and the submap map's blended field), stay within a memory bound, and
tiled marching cubes weld their seams."""

import tracemalloc

import numpy as np
import torch

from aisdf import query_messages
from aisdf.query.engine import QueryEngine
from aisdf.query.mapstate import MapState
from aisdf.query.meshing import tiled_marching_cubes
from helpers.submap_map import engine_of

torch.set_num_threads(1)


class Balls(torch.nn.Module):
    """A few spheres (off the lattice), for meshes with known geometry."""

    def __init__(self, centres, r=0.4):
        super().__init__()
        self.c = torch.tensor(np.asarray(centres, np.float32))
        self.r = r
        self.calls = []

    def forward(self, x):
        self.calls.append(len(x))
        return (torch.cdist(x, self.c).min(dim=1).values - self.r).unsqueeze(-1)


def test_tiled_mesh_equals_the_untiled_mesh(submap_map):
    from scipy.spatial import cKDTree

    # A single network: marching cubes of the whole box at once vs tiles of 7, 17 samples.
    net = Balls([[0.013, 0.021, 0.007], [0.75, 0.61, 0.33]])
    st = MapState(3, 0, net, np.array([[-0.6, -0.6, -0.6], [1.3, 1.2, 0.9]]), None, -1)
    meshes = {}
    for tile in (7, 17, 1000):
        e = QueryEngine(device="cpu", mesh_tile=tile)
        e._state = st
        meshes[tile] = e.answer_mesh(query_messages.MeshRequest(0.05))
    ref = meshes[1000]
    assert len(ref.faces) > 1000
    for tile in (7, 17):
        v = meshes[tile]
        assert len(v.vertices) == len(ref.vertices) and len(v.faces) == len(ref.faces)
        assert cKDTree(ref.vertices).query(v.vertices)[0].max() < 1e-5
        assert cKDTree(v.vertices).query(ref.vertices)[0].max() < 1e-5
        # Welded: every vertex is used, so no seam leaves a crack of duplicated vertices.
        assert len(np.unique(v.faces)) == len(v.vertices)
    # The submap map: the blended field, tiled vs not.
    m = submap_map
    e1, e2 = engine_of(m, mesh_tile=16), engine_of(m, mesh_tile=1000)
    a, b = e1.answer_mesh(query_messages.MeshRequest(0.12)), e2.answer_mesh(query_messages.MeshRequest(0.12))
    assert len(b.faces) > 1000 and len(a.faces) == len(b.faces)
    assert cKDTree(b.vertices).query(a.vertices)[0].max() < 1e-4
    assert cKDTree(a.vertices).query(b.vertices)[0].max() < 1e-4


def test_tiled_mesh_memory_stays_bounded_on_a_big_box():
    # A 14 x 12 x 3 m box at 5 cm: 3.6 M samples (the untiled volume, points and lattice
    # indices would take ~120 MB of numpy arrays); tiles of 32^3 samples.
    net = Balls([[1.01, 2.03, 1.02], [9.07, 7.01, 1.53]], r=0.6)
    e = QueryEngine(device="cpu", mesh_tile=32, mesh_max_cells=10 ** 7)
    e._state = MapState(1, 0, net, np.array([[0.0, 0.0, 0.0], [14.0, 12.0, 3.0]]), None, -1)
    tracemalloc.start()
    try:
        rep = e.answer_mesh(query_messages.MeshRequest(0.05))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    r = np.min(np.linalg.norm(rep.vertices[:, None] - net.c.numpy()[None], axis=2), axis=1)
    assert len(rep.faces) > 5000 and np.abs(r - 0.6).max() < 0.01
    assert max(net.calls) <= 32 ** 3
    assert peak < 25e6, f"peak numpy/python memory {peak / 1e6:.1f} MB"


def test_tiled_marching_cubes_welds_seams_on_a_generic_field():
    def fn(p):
        p = np.asarray(p, np.float64)
        return (np.linalg.norm(p - [0.1013, 0.2071, 0.3033], axis=1) - 0.7).astype(np.float32)

    from skimage.measure import marching_cubes

    lo, res, n = np.array([-1.0, -1.0, -1.0]), 0.06, np.array([37, 35, 30])
    axes = [lo[a] + res * np.arange(n[a]) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    v, f, _, _ = marching_cubes(fn(pts).reshape(tuple(n)), 0.0, spacing=(res,) * 3)
    for tile in (3, 8, 16):
        V, F = tiled_marching_cubes(fn, lo, res, n, tile)
        assert len(V) == len(v) and len(F) == len(f)
        key = lambda VV, FF: np.sort(np.sort(np.round(VV[FF], 4).reshape(len(FF), 3, 3), axis=1).reshape(len(FF), -1),
                                     axis=0)
        np.testing.assert_allclose(key(V, F), key(v + lo, f), atol=2e-4)

