"""The fused SDF rule (paper Sec. IV-D) on hand-made values."""

import numpy as np

from aisdf.structure.fusion import fuse


def test_fuse_takes_the_smaller_distance_near_a_surfel():
    sdf_i = np.array([0.30, 0.30, -0.05, 2.0, 0.10])
    grad_i = np.tile([0.0, 0.0, 1.0], (5, 1))
    sdf_e = np.array([0.10, -0.20, 0.01, 0.90, 0.40])  # signed, as explicit_sdf returns
    grad_e = np.tile([1.0, 0.0, 0.0], (5, 1))
    sdf, grad, use = fuse(sdf_i, grad_i, sdf_e, grad_e, radius=0.5)
    # 0: explicit 0.10 < 0.30 wins; 1: behind a surfel counts as 0.20 away (unsigned), wins,
    # gradient flipped; 2: the network says inside (-0.05), stays; 3: surfel beyond the
    # radius, ignored; 4: network nearer, stays.
    np.testing.assert_allclose(sdf, [0.10, 0.20, -0.05, 2.0, 0.10])
    assert use.tolist() == [True, True, False, False, False]
    np.testing.assert_allclose(grad[0], [1, 0, 0])
    np.testing.assert_allclose(grad[1], [-1, 0, 0])
    np.testing.assert_allclose(grad[2:], grad_i[2:])


def test_fuse_without_gradients():
    sdf, grad, use = fuse(np.array([1.0]), None, np.array([0.2]), None)
    assert grad is None and sdf.tolist() == [0.2] and use.tolist() == [True]


def test_a_far_surfel_still_bounds_the_answer_by_default_and_everywhere_without_a_radius():
    # A surfel 1.5 m away bounds the distance to the nearest surface (it is observed surface):
    # the default radius (2 m) lets it correct a network that says 1.9 m; beyond the radius
    # only radius=None (the paper's rule, the smaller at every point) uses it.
    sdf_i = np.array([1.9, 3.0, 1.0])
    sdf_e = np.array([1.5, 2.5, 1.2])
    sdf, _, use = fuse(sdf_i, None, sdf_e, None)
    np.testing.assert_allclose(sdf, [1.5, 3.0, 1.0])
    assert use.tolist() == [True, False, False]
    sdf, _, use = fuse(sdf_i, None, sdf_e, None, radius=None)
    np.testing.assert_allclose(sdf, [1.5, 2.5, 1.0])
    assert use.tolist() == [True, True, False]
