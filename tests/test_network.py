"""The SDF network: iSDF's layout, encoding, snapshot round trip."""

import json

import numpy as np
import pytest
import torch

from aisdf.network import (
    NetworkConfig, PositionalEncoding, SDFNetwork, build_model, icosahedron_directions, load_numpy_state,
    model_spec, move_network, n_params, sdf_and_grad, state_to_numpy,
)

torch.set_num_threads(1)  # 2 threads stall badly when another process holds a core


def test_icosahedron_directions():
    d = icosahedron_directions()
    assert d.shape == (21, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    cos = np.abs(d @ d.T)
    assert cos[~np.eye(21, dtype=bool)].max() < 1 - 1e-6  # no two parallel or antipodal
    # The 12 icosahedron vertices fold to 6 directions, the 30 edge midpoints to 15; the
    # midpoints include the 3 coordinate axes.
    for axis in np.eye(3):
        assert np.isclose(np.abs(d @ axis).max(), 1.0)


def test_encoding_dims_and_values():
    enc = PositionalEncoding()
    assert enc.out_dim == 255
    assert PositionalEncoding(octaves=2).out_dim == 3 + 2 * 21 * 2
    x = torch.tensor([[1.0, -2.0, 0.5]])
    e = enc(x)
    assert e.shape == (1, 255)
    xs = x * 0.05937
    proj = xs @ torch.tensor(icosahedron_directions(), dtype=torch.float32).T
    torch.testing.assert_close(e[:, :3], xs)
    torch.testing.assert_close(e[:, 3:24], torch.sin(proj))  # octave 1
    torch.testing.assert_close(e[:, 24:45], torch.cos(proj))
    torch.testing.assert_close(e[:, -21:], torch.cos(32 * proj))  # octave 32


def test_isdf_network_shape_and_params():
    net = SDFNetwork()
    assert net.n_inputs == 255
    # 255*256+256 + 2*(256*256+256) + 511*256+256 + 2*(256*256+256) + 257
    assert n_params(net) == 460033
    assert [tuple(l.weight.shape) for l in net.layers][3] == (256, 511)
    out = net(torch.randn(7, 3))
    assert out.shape == (7,)
    assert all(torch.all(l.bias == 0) for l in net.layers)


def test_sdf_and_grad_matches_finite_differences():
    torch.manual_seed(0)
    net = SDFNetwork(NetworkConfig(width=32)).double()
    x = torch.randn(4, 3, dtype=torch.float64)
    f, g = sdf_and_grad(net, x)
    assert f.shape == (4,) and g.shape == (4, 3) and not g.requires_grad
    h = 1e-6
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = h
        fd = (net(x + e) - net(x - e)) / (2 * h)
        torch.testing.assert_close(g[:, k], fd.detach(), rtol=1e-5, atol=1e-7)
    f, g = sdf_and_grad(net, x, create_graph=True)
    g.norm(dim=1).sum().backward()
    assert net.layers[0].weight.grad is not None


@pytest.mark.parametrize("cfg", [NetworkConfig(), NetworkConfig(width=32, n_layers=3, skip_layer=None,
                                                                  octaves=4, offset=[1.0, 2.0, 0.5])])
def test_spec_round_trip_reproduces_outputs(cfg):
    net = SDFNetwork(cfg)
    spec = json.loads(json.dumps(model_spec(net)))  # plain JSON types
    assert spec["arch"] == "isdf-mlp" and spec["n_params"] == n_params(net)
    state = state_to_numpy(net)
    assert all(a.dtype == np.float32 for a in state.values())
    net2 = build_model(spec)
    load_numpy_state(net2, state)
    x = torch.randn(50, 3) * 3
    assert torch.equal(net(x), net2(x))


def test_bad_state_and_spec_raise():
    net = SDFNetwork(NetworkConfig(width=16))
    state = state_to_numpy(net)
    missing = {k: v for k, v in state.items() if k != "out.bias"}
    with pytest.raises(ValueError, match="missing tensors.*out.bias"):
        load_numpy_state(net, missing)
    with pytest.raises(ValueError, match="unexpected tensors.*extra"):
        load_numpy_state(net, {**state, "extra": np.zeros(1, np.float32)})
    with pytest.raises(ValueError, match=r"layers.0.weight: expected \(16, 255\), got \(16, 3\)"):
        load_numpy_state(net, {**state, "layers.0.weight": np.zeros((16, 3), np.float32)})
    with pytest.raises(ValueError, match="unknown network arch"):
        build_model({"arch": "nerf"})
    spec = model_spec(net)
    with pytest.raises(ValueError, match="parameters"):
        build_model({**spec, "n_params": 5})
    with pytest.raises(ValueError, match="skip_layer"):
        SDFNetwork(NetworkConfig(n_layers=3, skip_layer=3))


@pytest.mark.parametrize("skip", [3, None])
def test_a_moved_network_answers_at_the_new_place_what_it_answered_at_the_old(skip):
    """move_network(net, T): net(T x) afterwards is net(x) before, gradients turned with T,
    and a snapshot (state round trip) carries the move."""
    torch.manual_seed(0)
    net = SDFNetwork(NetworkConfig(offset=[1.0, -2.0, 0.5], width=64, skip_layer=skip))
    a = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(7.0)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    T[:3, 3] = [0.2, -0.15, 0.05]
    x = torch.tensor(np.random.default_rng(0).uniform(-3, 3, (500, 3)), dtype=torch.float32)
    f0, g0 = sdf_and_grad(net, x)
    move_network(net, T)
    xn = x @ torch.tensor(T[:3, :3].T, dtype=torch.float32) + torch.tensor(T[:3, 3], dtype=torch.float32)
    f1, g1 = sdf_and_grad(net, xn)
    assert float(f0.abs().mean()) > 1e-3  # a field that is not flat
    torch.testing.assert_close(f1, f0, atol=1e-5, rtol=0)
    torch.testing.assert_close(g1, g0 @ torch.tensor(T[:3, :3].T, dtype=torch.float32), atol=1e-4, rtol=0)
    back = build_model(model_spec(net))
    load_numpy_state(back, state_to_numpy(net))
    torch.testing.assert_close(back(xn), f0, atol=1e-5, rtol=0)
    assert not torch.allclose(net(x), f0, atol=1e-4)  # it did move
