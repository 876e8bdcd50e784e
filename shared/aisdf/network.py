"""The SDF network: iSDF's positional encoding and MLP, configurable.

Default (``NetworkConfig()``) is iSDF's network (isdf-reference.md, "Network"):

* encoding: points (minus ``offset``) scaled by 0.05937, projected on 21 directions,
  sin and cos of each projection at 6 octaves (1, 2, ..., 32), plus the 3 scaled
  coordinates: 2*21*6 + 3 = 255 inputs. Layout: ``[x, sin(1 p), cos(1 p), sin(2 p), ...]``.
* MLP: Linear + Softplus(beta=100) blocks of width 256; the 4th block (index 3) takes
  the hidden state concatenated with the encoding (256 + 255 = 511 inputs); a linear
  256 -> 1 output, multiplied by 0.14. Xavier-normal weights, zero biases.
  460,033 parameters.

The 21 directions: the 42 vertices of a once-subdivided icosahedron (12 vertices plus
the 30 edge midpoints, projected on the unit sphere) come in 21 antipodal pairs; a
direction and its opposite give the same sin/cos features up to sign, so each pair is
folded to one direction (the one whose first non-zero coordinate is positive), and the
21 are sorted lexicographically. They are stored in the state (``encoding.dirs``), so a
snapshot carries the exact directions it was trained with.

The query service rebuilds a network from a WeightSnapshot: ``build_model(snapshot
["model"])`` then ``load_numpy_state(net, snapshot["state"])``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from pydantic import Field, field_validator
from torch import nn

from .config import Model

# Denormal floats (Softplus(beta=100) underflows produce them) are 5-10x slower on x86
# CPUs. Flush them to zero: the flag is per thread, and threads inherit it from the thread
# that creates them, so setting it here, in the importing thread and before torch makes
# its CPU thread pool, covers that pool and the threads a service starts later; the
# forward sets it again for threads that existed before.
torch.set_flush_denormal(True)

ARCH = "isdf-mlp"
SPEC_VERSION = 1

class NetworkConfig(Model):
    """Architecture and encoding hyper-parameters; defaults are iSDF's."""

    width: int = Field(256, ge=1, description="hidden width of every Linear+Softplus block")
    n_layers: int = Field(6, ge=1, description="number of Linear+Softplus blocks (before the linear output)")
    skip_layer: int | None = Field(
        3, ge=1, description="0-based block whose input is [hidden, encoding] (iSDF: 3 = the 4th); None = no skip"
    )
    octaves: int = Field(6, ge=0, description="sin/cos frequencies 2^0 .. 2^(octaves-1)")
    scale: float = Field(0.05937, gt=0, description="points are multiplied by this before the encoding")
    offset: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0], description="subtracted from points before scaling (scene centre)"
    )
    output_scale: float = Field(0.14, description="the linear output is multiplied by this")
    softplus_beta: float = Field(100.0, gt=0, description="beta of every Softplus")

    @field_validator("offset")
    @classmethod
    def _offset3(cls, v: list[float]) -> list[float]:
        if len(v) != 3:
            raise ValueError("offset must have 3 values")
        return [float(x) for x in v]


def icosahedron_directions() -> np.ndarray:
    """The 21 unit directions (21, 3) float64 described in the module docstring."""
    phi = (1.0 + math.sqrt(5.0)) / 2.0
    verts = []
    for a in (-1.0, 1.0):
        for b in (-phi, phi):
            verts += [(0.0, a, b), (a, b, 0.0), (b, 0.0, a)]
    V = np.array(verts)
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    # Edges of the icosahedron: vertex pairs at the minimal distance.
    d = np.linalg.norm(V[:, None] - V[None], axis=-1)
    edge = np.min(d[d > 1e-9])
    i, j = np.nonzero(np.triu(np.abs(d - edge) < 1e-9))
    mids = (V[i] + V[j]) / 2.0
    mids /= np.linalg.norm(mids, axis=1, keepdims=True)
    allv = np.concatenate([V, mids])  # 12 + 30 = 42
    assert len(allv) == 42
    out = []
    for v in allv:
        first = v[np.nonzero(np.abs(v) > 1e-9)[0][0]]
        c = v if first > 0 else -v
        if not any(np.allclose(c, o) for o in out):
            out.append(c)
    dirs = np.array(sorted(out, key=lambda r: tuple(np.round(r, 9)))) + 0.0  # no negative zeros
    assert dirs.shape == (21, 3)
    return dirs


class PositionalEncoding(nn.Module):
    """(N, 3) points -> (N, 3 + 2 * n_dirs * octaves) features."""

    def __init__(self, octaves: int = 6, scale: float = 0.05937, offset=(0.0, 0.0, 0.0)):
        super().__init__()
        self.scale = float(scale)
        self.register_buffer("dirs", torch.tensor(icosahedron_directions(), dtype=torch.float32).T.contiguous())
        self.register_buffer("offset", torch.tensor(list(offset), dtype=torch.float32), persistent=False)
        self.register_buffer("freqs", 2.0 ** torch.arange(octaves, dtype=torch.float32), persistent=False)

    @property
    def out_dim(self) -> int:
        return 3 + 2 * self.dirs.shape[1] * len(self.freqs)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        x = (points - self.offset) * self.scale
        proj = x @ self.dirs  # (N, 21)
        feats = [x]
        for f in self.freqs:
            feats += [torch.sin(f * proj), torch.cos(f * proj)]
        return torch.cat(feats, dim=-1)


class SDFNetwork(nn.Module):
    """iSDF's MLP over the positional encoding: (N, 3) points -> (N,) SDF."""

    def __init__(self, cfg: NetworkConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or NetworkConfig()
        if cfg.skip_layer is not None and cfg.skip_layer >= cfg.n_layers:
            raise ValueError(f"skip_layer {cfg.skip_layer} must be < n_layers {cfg.n_layers}")
        self.encoding = PositionalEncoding(cfg.octaves, cfg.scale, cfg.offset)
        n_in = self.encoding.out_dim
        layers = []
        for k in range(cfg.n_layers):
            d_in = n_in if k == 0 else cfg.width
            if k == cfg.skip_layer:
                d_in += n_in
            layers.append(nn.Linear(d_in, cfg.width))
        self.layers = nn.ModuleList(layers)
        self.act = nn.Softplus(beta=cfg.softplus_beta)
        self.out = nn.Linear(cfg.width, 1)
        for m in [*self.layers, self.out]:
            nn.init.xavier_normal_(m.weight)
            nn.init.zeros_(m.bias)

    @property
    def n_inputs(self) -> int:
        return self.encoding.out_dim

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if points.device.type == "cpu":
            torch.set_flush_denormal(True)  # see the top of this module
        enc = self.encoding(points)
        h = enc
        for k, layer in enumerate(self.layers):
            if k == self.cfg.skip_layer:
                h = torch.cat([h, enc], dim=-1)
            h = self.act(layer(h))
        return self.out(h)[..., 0] * self.cfg.output_scale


def n_params(net: nn.Module) -> int:
    return int(sum(p.numel() for p in net.parameters()))


def sdf_and_grad(net: nn.Module, points: torch.Tensor, create_graph: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """SDF (N,) and its gradient (N, 3) by autograd. ``create_graph`` for losses on the gradient."""
    with torch.enable_grad():
        x = points.detach().requires_grad_(True)
        f = net(x)
        (g,) = torch.autograd.grad(f, x, torch.ones_like(f), create_graph=create_graph)
    if not create_graph:
        f, g = f.detach(), g.detach()
    return f, g


# ----------------------------------------------------------------------------- snapshots


def model_spec(net: SDFNetwork) -> dict:
    """Architecture + hyper-parameters as plain JSON/msgpack types; ``build_model`` inverts it."""
    return {
        "name": "aisdf-sdf",
        "arch": ARCH,
        "spec_version": SPEC_VERSION,
        "config": net.cfg.model_dump(mode="json"),
        "n_inputs": int(net.n_inputs),
        "n_params": n_params(net),
    }


def build_model(spec: dict) -> SDFNetwork:
    """Rebuild the network ``model_spec`` described (weights are Xavier-initialised; load a state)."""
    if spec.get("arch") != ARCH:
        raise ValueError(f"unknown network arch {spec.get('arch')!r}; this build knows {ARCH!r}")
    if int(spec.get("spec_version", SPEC_VERSION)) > SPEC_VERSION:
        raise ValueError(f"model spec version {spec['spec_version']} is newer than this build's {SPEC_VERSION}")
    net = SDFNetwork(NetworkConfig.model_validate(spec.get("config", {})))
    if "n_params" in spec and int(spec["n_params"]) != n_params(net):
        raise ValueError(f"model spec says {spec['n_params']} parameters, the rebuilt network has {n_params(net)}")
    return net


def state_to_numpy(net: nn.Module) -> dict[str, np.ndarray]:
    """The network's persistent tensors as float32 numpy arrays (a WeightSnapshot's ``state``)."""
    return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in net.state_dict().items()}


def load_numpy_state(net: nn.Module, state: dict[str, np.ndarray]) -> None:
    """Load ``state_to_numpy``'s output; ValueError naming every missing/unexpected/mis-shaped tensor."""
    own = net.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    bad = [
        f"{k}: expected {tuple(own[k].shape)}, got {tuple(np.shape(state[k]))}"
        for k in own
        if k in state and tuple(np.shape(state[k])) != tuple(own[k].shape)
    ]
    if missing or unexpected or bad:
        parts = []
        if missing:
            parts.append(f"missing tensors {missing}")
        if unexpected:
            parts.append(f"unexpected tensors {unexpected}")
        if bad:
            parts.append("shape mismatch " + "; ".join(bad))
        raise ValueError("network state does not match the architecture: " + ", ".join(parts))
    tensors = {}
    for k, ref in own.items():
        a = np.asarray(state[k])
        if not np.issubdtype(a.dtype, np.number):
            raise ValueError(f"network state tensor {k} has non-numeric dtype {a.dtype}")
        tensors[k] = torch.as_tensor(np.array(a, dtype=np.float32), device=ref.device).to(ref.dtype)
    net.load_state_dict(tensors)


# ----------------------------------------------------------------------------- rigid moves


@torch.no_grad()
def move_network(net: SDFNetwork, T: np.ndarray) -> None:
    """Moves the field rigidly, in place: afterwards ``net(x)`` is what ``net(T^-1 x)`` was,
    for the rigid 4x4 ``T`` (old world to new world). Exact up to float32 rounding: the
    encoding's directions turn with the rotation (they are in the state, so snapshots carry
    them) and the translation becomes a phase, which the first block and the skip block take
    up by mixing each frequency's sin and cos columns; distances and their gradients' lengths
    are unchanged by a rigid motion, so nothing else changes. Used after a pose correction
    moves a submap's keyframes (nearly) rigidly: the network keeps what it learnt, at the
    corrected place."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    enc = net.encoding
    s = enc.scale
    off = enc.offset.detach().cpu().numpy().astype(np.float64)
    dirs = enc.dirs.detach().cpu().numpy().astype(np.float64)  # (3, n)
    # old scaled coordinates from new ones u = (x - off) s:  x_old_s = R^T u + c
    c = s * (R.T @ (off - t) - off)
    phase = c @ dirs  # (n,): old projections = u @ (R dirs) + phase
    n = dirs.shape[1]
    freqs = enc.freqs.detach().cpu().numpy().astype(np.float64)

    def fix(layer: nn.Linear, start: int) -> None:
        W = layer.weight.detach().cpu().numpy().astype(np.float64)
        b = layer.bias.detach().cpu().numpy().astype(np.float64)
        Wx = W[:, start:start + 3]
        b = b + Wx @ c
        W[:, start:start + 3] = Wx @ R.T
        for j, f in enumerate(freqs):
            i_s = start + 3 + 2 * n * j
            i_c = i_s + n
            th = f * phase
            Ws, Wc = W[:, i_s:i_s + n].copy(), W[:, i_c:i_c + n].copy()
            # Ws sin(fp + th) + Wc cos(fp + th), written over sin(fp) and cos(fp)
            W[:, i_s:i_s + n] = Ws * np.cos(th) - Wc * np.sin(th)
            W[:, i_c:i_c + n] = Ws * np.sin(th) + Wc * np.cos(th)
        layer.weight.copy_(torch.as_tensor(W, dtype=layer.weight.dtype))
        layer.bias.copy_(torch.as_tensor(b, dtype=layer.bias.dtype))

    fix(net.layers[0], 0)
    if net.cfg.skip_layer is not None:
        fix(net.layers[net.cfg.skip_layer], net.cfg.width)
    enc.dirs.copy_(torch.as_tensor(R @ dirs, dtype=enc.dirs.dtype))
