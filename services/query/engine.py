"""The query engine: the latest map (network + surfels) and the answers to SDF and
mesh requests. No Zenoh here: ``main.py`` wires it to the network, tests drive it
directly.

A new map is built completely aside and then swapped in with one reference
assignment, so a request always sees one consistent map.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np
import torch

from aisdf import protocol
from aisdf.collision import chomp_cost
from aisdf.fusion import fuse
from aisdf.network import build_model, load_numpy_state
from aisdf.surfel_types import Surfels

log = logging.getLogger(__name__)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@dataclass(frozen=True)
class MapState:
    version: int  # WeightSnapshot.version: the reply's map_version
    step: int
    net: torch.nn.Module
    bounds: np.ndarray | None  # (2, 3) world AABB of what was observed, when the mapper sent it
    surfels: Surfels | None
    surfel_version: int


class QueryEngine:
    def __init__(self, max_points: int = 1_000_000, chunk_points: int = 65_536, device: str = "auto",
                 fuse_radius: float = 0.5, mesh_resolution: float = 0.05, mesh_max_cells: int = 16_000_000):
        self.max_points = max_points
        self.chunk_points = chunk_points
        self.device = pick_device(device)
        self.fuse_radius = fuse_radius
        self.mesh_resolution = mesh_resolution
        self.mesh_max_cells = mesh_max_cells
        self._state: MapState | None = None
        self._surfels: tuple[int, Surfels] | None = None
        self._lock = threading.Lock()  # serialises writers only; readers take the reference

    @classmethod
    def from_config(cls, cfg) -> "QueryEngine":
        return cls(cfg.max_points, cfg.chunk_points, cfg.device, cfg.fuse_radius, cfg.mesh_resolution,
                   cfg.mesh_max_cells)

    # ------------------------------------------------------------------ map updates

    @property
    def state(self) -> MapState | None:
        return self._state

    def set_weights(self, snap: protocol.WeightSnapshot) -> bool:
        """Build the network of a snapshot and swap it in; False if it is not newer.
        Raises ValueError on a snapshot that cannot be loaded (the old map stays)."""
        cur = self._state
        if cur is not None and snap.version <= cur.version:
            return False
        net = build_model(snap.model)
        load_numpy_state(net, snap.state)
        net = net.to(self.device).eval()
        for p in net.parameters():
            p.requires_grad_(False)
        bounds = snap.model.get("bounds")
        bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3) if bounds is not None else None
        with self._lock:
            cur = self._state
            if cur is not None and snap.version <= cur.version:
                return False
            sv, surf = self._surfels if self._surfels else (-1, None)
            self._state = MapState(snap.version, snap.step, net, bounds, surf, sv)
        return True

    def set_surfels(self, smap: protocol.SurfelMap) -> bool:
        if self._surfels is not None and smap.version <= self._surfels[0]:
            return False
        surf = Surfels.from_protocol_dict(smap.surfels)
        with self._lock:
            self._surfels = (smap.version, surf)
            cur = self._state
            if cur is not None:
                self._state = MapState(cur.version, cur.step, cur.net, cur.bounds, surf, smap.version)
        return True

    # ------------------------------------------------------------------ evaluation

    def _implicit(self, net, pts: np.ndarray, gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        sdf = np.empty(len(pts), np.float32)
        grad = np.empty((len(pts), 3), np.float32) if gradient else None
        for i in range(0, len(pts), self.chunk_points):
            x = torch.from_numpy(np.array(pts[i:i + self.chunk_points], dtype=np.float32)).to(self.device)
            if gradient:
                with torch.enable_grad():
                    x.requires_grad_(True)
                    f = net(x).reshape(-1)
                    (g,) = torch.autograd.grad(f.sum(), x)
                grad[i:i + len(x)] = g.detach().cpu().numpy()
            else:
                with torch.inference_mode():
                    f = net(x).reshape(-1)
            sdf[i:i + len(x)] = f.detach().cpu().numpy()
        return sdf, grad

    def _explicit(self, surfels: Surfels, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from aisdf.surfel_map import explicit_sdf

        d, g, _ = explicit_sdf(pts.astype(np.float64), surfels)
        return d.astype(np.float32), g.astype(np.float32)

    def answer_sdf(self, req: protocol.SdfRequest) -> protocol.SdfReply:
        state = self._state
        if state is None:
            raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        if len(req.points) > self.max_points:
            raise protocol.ProtocolError("too_large", f"{len(req.points)} points exceed the limit {self.max_points}")
        pts = req.points
        has_surfels = state.surfels is not None and len(state.surfels) > 0
        if req.source == "explicit":
            if not has_surfels:
                raise protocol.ProtocolError("no_map", "no explicit planar map yet (no surfels published)")
            sdf, grad = self._explicit(state.surfels, pts)
        else:
            sdf, grad = self._implicit(state.net, pts, req.gradient)
            if req.source == "fused" and has_surfels:
                d_e, g_e = self._explicit(state.surfels, pts)
                sdf, grad, _ = fuse(sdf, grad, d_e, g_e, self.fuse_radius)
        coll = None
        if req.collision_epsilon is not None:
            coll = chomp_cost(sdf, req.collision_epsilon).astype(np.float32)
        return protocol.SdfReply(state.version, sdf.astype(np.float32), grad if req.gradient else None, coll)

    def answer_mesh(self, req: protocol.MeshRequest) -> protocol.MeshReply:
        from skimage.measure import marching_cubes

        state = self._state
        if state is None:
            raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        if state.bounds is None:
            raise protocol.ProtocolError("no_map", "the map carries no bounds yet (no keyframe observed)")
        res = req.resolution or self.mesh_resolution
        lo, hi = state.bounds[0] - 2 * res, state.bounds[1] + 2 * res
        n = np.maximum(np.ceil((hi - lo) / res).astype(int) + 1, 2)
        if int(np.prod(n)) > self.mesh_max_cells:
            raise protocol.ProtocolError(
                "too_large", f"resolution {res} m needs a {n[0]}x{n[1]}x{n[2]} grid, above {self.mesh_max_cells} cells; "
                "ask for a coarser resolution")
        axes = [lo[i] + res * np.arange(n[i]) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        vol = self._implicit(state.net, grid, False)[0].reshape(tuple(n))
        if not (vol.min() < 0 < vol.max()):
            return protocol.MeshReply(state.version, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(res, res, res))
        return protocol.MeshReply(state.version, (verts + lo).astype(np.float32), faces.astype(np.int32))
