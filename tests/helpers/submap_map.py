"""The submap map of the query tests: three submaps (3 m cells, 0.5 m overlap) of the synthetic
Atlanta building around six keyframes, each a small network fitted to the building's exact SDF
over its own extended box (different networks, each with its own error of a few cm, as
neighbouring submaps have); the messages a submap mapper would publish for it, and helpers that
compare answers (used by tests/query/, whose conftest.py builds the map as ``submap_map``)."""

import time

import numpy as np
import torch

from aisdf import protocol
from aisdf.network import NetworkConfig, SDFNetwork, build_model, load_numpy_state, model_spec, state_to_numpy
from aisdf.observed import ObservedGrid, ObservedSpace
from aisdf.submaps.grid import SubmapGrid, cell_id
from aisdf.structure.surfel_types import Surfels
from aisdf.synthetic import SyntheticSequence
from aisdf.query.engine import QueryEngine

CELLS = [(1, 0, 0), (2, 0, 0), (1, -1, 0)]
EPOCH = 1_700_000_000_000


def fit_submap(seq, grid, cell, centres, seed, steps=200, pool=20_000, batch=512):
    """A small network fitted to the exact SDF near the observed space of the cell's extended box."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    pts = centres[grid.inside(cell, centres)]
    q = pts[rng.integers(0, len(pts), pool)] + rng.uniform(-0.05, 0.05, (pool, 3))
    q32 = torch.from_numpy(q.astype(np.float32))
    y = torch.from_numpy(seq.gt_sdf(q).astype(np.float32))
    net = SDFNetwork(NetworkConfig(width=32, offset=grid.centre_W(cell).tolist()))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(steps):
        j = torch.from_numpy(rng.integers(0, pool, batch))
        loss = (net(q32[j]).reshape(-1) - y[j]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net.eval()


def crop(obs: ObservedGrid, grid: SubmapGrid, cell) -> ObservedGrid:
    """The observed voxels inside the cell's extended box, on the same voxel lattice."""
    idx = np.argwhere(obs.occ)
    keep = grid.inside(cell, obs.origin + (idx + 0.5) * obs.voxel)
    idx = idx[keep]
    lo, hi = idx.min(0), idx.max(0) + 1
    occ = np.zeros(tuple(hi - lo), bool)
    occ[tuple((idx - lo).T)] = True
    return ObservedGrid(obs.origin + lo * obs.voxel, obs.voxel, occ)


def snapshot(net, grid, cell, version, observed, epoch=EPOCH, step=100, measured=None):
    spec = model_spec(net)
    lo, hi = observed.bounds
    spec["bounds"] = [lo.tolist(), hi.tolist()]
    snap = protocol.WeightSnapshot(version, step, time.time(), spec, state_to_numpy(net), epoch, observed.to_msg(),
                                   {"id": cell_id(cell), "grid": grid.to_msg()},
                                   None if measured is None else {"voxel": 0.1, "points": measured})
    return protocol.WeightSnapshot.from_msg(protocol.unpack(protocol.pack(snap.to_msg())))  # as received


def index(grid, versions: dict, version, epoch=EPOCH):
    return protocol.SubmapIndex(version, time.time(), grid.to_msg(),
                                {cell_id(c): {"version": v, "step": 100} for c, v in versions.items()}, epoch)


def surfel_map(surf: Surfels, version: int = 1) -> protocol.SurfelMap:
    """The SurfelMap message of ``surf``, as received (encoded and decoded)."""
    dtypes = {"direction": np.int32, "keyframe": np.int64}
    smap = protocol.SurfelMap(version, time.time(), np.array([0, 0, 1.0]), np.eye(3)[:1],
                              {f: getattr(surf, f).astype(dtypes.get(f, np.float32)) for f in (
                                  "center", "normal", "axis1", "axis2", "extent", "direction", "keyframe")}, EPOCH)
    return protocol.SurfelMap.from_msg(protocol.unpack(protocol.pack(smap.to_msg())))


def assert_same_bake(a, b, pts):
    """Two baked fields answer the same at ``pts``: coverage, values and gradients."""
    fa, ga, ca = a.query(pts)
    fb, gb, cb = b.query(pts)
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_allclose(fa, fb, atol=1e-6)
    np.testing.assert_allclose(ga, gb, atol=1e-5)


def make_submap_map():
    """The submap map: the sequence, its six keyframes, the grid, the fitted networks, the
    observed space of each submap, their snapshots (as received) and the observed voxels' centres."""
    seq = SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)
    frames = [seq.frame(i) for i in range(0, 120, 20)]
    space = ObservedSpace(voxel=0.1)
    for f in frames:
        space.add(f["depth"], f["K"], f["T_WC"])
    obs = space.grid()
    centres = obs.origin + (np.argwhere(obs.occ) + 0.5) * obs.voxel
    grid = SubmapGrid.around(frames[0]["T_WC"][:3, 3], cell_m=3.0, cell_height_m=6.0, overlap_m=0.5)
    nets = {c: fit_submap(seq, grid, c, centres, seed=n) for n, c in enumerate(CELLS)}
    observed = {c: crop(obs, grid, c) for c in CELLS}
    snaps = {c: snapshot(nets[c], grid, c, 1, observed[c]) for c in CELLS}
    return dict(seq=seq, frames=frames, grid=grid, nets=nets, observed=observed, snaps=snaps, centres=centres)


def engine_of(m, **kw):
    e = QueryEngine(device="cpu", **kw)
    for c in CELLS:
        assert e.set_submap(m["snaps"][c])
    return e


def evaluators(m, snaps=None):
    """The submaps' networks rebuilt from their messages, as blend's evaluators."""
    out = {}
    for c, s in (snaps or m["snaps"]).items():
        net = build_model(s.model)
        load_numpy_state(net, s.state)
        net.eval()

        def ev(q, grad, net=net):
            x = torch.from_numpy(np.asarray(q, np.float32))
            if not grad:
                with torch.no_grad():
                    return net(x).reshape(-1).numpy(), None
            x.requires_grad_(True)
            f = net(x).reshape(-1)
            (g,) = torch.autograd.grad(f.sum(), x)
            return f.detach().numpy(), g.numpy()

        out[c] = ev
    return out


def band_points(m, n, rng):
    """Observed points in the overlap bands (where two submaps blend) and elsewhere."""
    c = m["centres"]
    w = np.stack([m["grid"].weight(cell, c) for cell in CELLS], 1)
    both, some = (w > 0).sum(1) >= 2, (w > 0).any(1)
    pick = np.concatenate([c[both][rng.integers(0, both.sum(), n // 2)], c[some][rng.integers(0, some.sum(), n - n // 2)]])
    return pick + rng.uniform(-0.05, 0.05, pick.shape)
