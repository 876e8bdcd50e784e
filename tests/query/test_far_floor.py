"""The far-field floor of the served answer (protocol 1.15, ``aisdf.query.answer.far_floor``):
away from every measured point a network that answers too low is raised to the distance to
the nearest surface the map holds (measured point, surfel, predicted point); near measured
points and inside surfaces the answer is left alone; the gradient is the blend's own."""

import numpy as np

from aisdf.query.answer import FLOOR_BAND, FLOOR_NEAR, far_floor, served_answer
from aisdf.structure.measured import MeasuredPoints


def floor_points(step: float = 0.02) -> MeasuredPoints:
    """A measured floor: z = 0, x and y in [-3, 3], every ``step``."""
    g = np.arange(-3.0, 3.0 + 1e-9, step)
    x, y = np.meshgrid(g, g, indexing="ij")
    return MeasuredPoints(np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1))


def column(zs) -> np.ndarray:
    """Points above the floor's lattice point (0, 0, 0)."""
    return np.stack([np.zeros(len(zs)), np.zeros(len(zs)), np.asarray(zs, float)], axis=1)


def test_a_network_too_low_far_from_the_floor_is_raised_to_the_floor_distance():
    m = floor_points()
    z = np.array([0.05, 0.1, 0.25, 0.4, 0.8, 1.5, 1.9])
    q = column(z)
    low = (0.6 * z).astype(np.float32)  # the network: 40 % low everywhere
    grad = np.tile(np.float32([0, 0, 0.6]), (len(z), 1))  # its gradient
    f, g = served_answer(q, low, grad, None, None, m)
    w = np.clip((z - FLOOR_NEAR) / FLOOR_BAND, 0, 1)
    np.testing.assert_allclose(f, 0.6 * z + w * 0.4 * z, atol=1e-6)
    assert f[0] == np.float32(0.6 * 0.05) and f[1] == np.float32(0.6 * 0.1)  # near the floor: the network's
    np.testing.assert_allclose(f[4:], z[4:], atol=1e-6)  # fully beyond near + band: the true distance
    # d/dz (0.6 z + w 0.4 z): 0.6 near the floor, 0.6 + 0.4 (w + z / band) on the ramp, 1 beyond
    ramp = (w > 0) & (w < 1)
    want = 0.6 + 0.4 * (w + np.where(ramp, z / FLOOR_BAND, 0.0))
    np.testing.assert_allclose(g[:, 2], want, atol=1e-5)
    np.testing.assert_allclose(g[:, :2], 0.0, atol=1e-6)


def test_the_floor_never_lowers_an_answer_nor_touches_inside_or_beyond_the_radius():
    m = floor_points(0.05)
    z = np.array([0.5, 1.0, 1.0, 2.5])
    q = column(z)
    f, _ = served_answer(q, np.float32([0.3, 1.0, -0.2, 1.0]), None, None, None, m)
    assert abs(f[0] - 0.5) < 0.002  # raised
    assert abs(f[1] - 1.0) < 1e-6  # the network's, already right (the cap holds it at most 1 cm above)
    assert f[2] == np.float32(-0.2)  # inside by the network: left alone
    assert f[3] == np.float32(1.0)  # no measured point within the 2 m radius: nothing to raise to


def test_a_nearer_surfel_or_predicted_surface_bounds_the_floor():
    m = floor_points(0.05)
    q = column([1.0])
    low = np.float32([0.2])
    # a wall surfel x = 0.6 (nearest point (0.6, 0, 1)) whose pixels were pooled 8 cm to its sides:
    # measured there, so it holds the floor at 0.6
    def wall(gap):
        y = np.concatenate([np.arange(-1.0, -gap + 1e-9, 0.02), np.arange(gap, 1.0 + 1e-9, 0.02)])
        yy, zz = np.meshgrid(y, np.arange(0.5, 1.5 + 1e-9, 0.02), indexing="ij")
        pts = np.stack([np.full(yy.size, 0.6), yy.ravel(), zz.ravel()], axis=1)
        return MeasuredPoints(np.concatenate([m.points, pts]))

    f, g = served_answer(q, low, np.float32([[0, 0, 1]]), np.float32([0.6]), np.float32([[-1, 0, 0]]), wall(0.08))
    assert abs(f[0] - 0.6) < 1e-6
    np.testing.assert_allclose(g[0], [-1, 0, 0], atol=1e-6)  # away from the surfel
    # the same rectangle reaching 0.3 m past its pixels (nothing measured within 0.1 m of its
    # nearest point): the floor is the nearest measured point, sqrt(0.6^2 + 0.3^2)
    f, _ = served_answer(q, low, None, np.float32([0.6]), np.float32([[-1, 0, 0]]), wall(0.3))
    assert abs(f[0] - np.hypot(0.6, 0.3)) < 1e-6
    # behind its nearest surfel (inside a solid whose face was seen): not raised
    f, _ = served_answer(q, low, None, np.float32([-1.5]), np.float32([[1, 0, 0]]), m)
    assert f[0] == low[0]
    # a predicted wall point 0.7 m away holds it at 0.7
    layout = MeasuredPoints(np.array([[0.7, 0.0, 1.0]]))
    f, g = served_answer(q, low, np.float32([[0, 0, 1]]), None, None, m, layout=layout)
    assert abs(f[0] - 0.7) < 1e-6
    np.testing.assert_allclose(g[0], [-1, 0, 0], atol=1e-6)


def test_the_gradient_is_the_derivative_of_the_values():
    rng = np.random.default_rng(3)
    m = MeasuredPoints(rng.uniform([-2, -2, 0], [2, 2, 0.02], (4000, 3)))
    q = rng.uniform([-1, -1, 0.05], [1, 1, 1.2], (300, 3))

    def net(p):  # a smooth network answer, too low far away
        return (0.5 * p[:, 2] + 0.05 * np.sin(3 * p[:, 0])).astype(np.float64)

    def net_g(p):
        return np.stack([0.15 * np.cos(3 * p[:, 0]), np.zeros(len(p)), np.full(len(p), 0.5)], axis=1)

    d_m, g_m = m.nearest(q, within=2.0)
    inf = np.full(len(q), np.inf)
    f, g = far_floor(net(q), net_g(q), d_m, g_m, inf, None)
    h = 1e-5
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        dp, gp = m.nearest(q + e, within=2.0)
        dn, gn = m.nearest(q - e, within=2.0)
        fp, _ = far_floor(net(q + e), net_g(q + e), dp, gp, inf, None)
        fn, _ = far_floor(net(q - e), net_g(q - e), dn, gn, inf, None)
        fd = (fp - fn) / (2 * h)
        ok = np.abs(fd - g[:, axis]) < 1e-3
        assert ok.mean() > 0.97, axis  # (points where the nearest measured point switches have kinks)
    raised = f > net(q) + 1e-9
    assert 0.2 < raised.mean() < 1.0  # both regimes are exercised
