"""The measured surface (``aisdf.structure.measured``): depth pixels pooled into voxels, and
the answer that moves the fused answer to the surfel distance where nothing was measured
nearer and caps it at the nearest measured point. Exact values on constructed cases."""

from __future__ import annotations

import numpy as np
import pytest

from aisdf.structure.measured import MeasuredSurface, measured_fuse

K = np.array([[40.0, 0, 20.0], [0, 40.0, 15.0], [0, 0, 1]])


def _wall(z=2.0, H=30, W=40):
    return np.full((H, W), z, np.float32)


def test_pixels_pool_into_voxel_means_and_counts():
    m = MeasuredSurface(voxel=0.1, min_hits=3)
    depth = _wall()
    depth[0, :5] = 0.0  # no return
    depth[1, :5] = np.nan
    depth[2, :5] = 50.0  # beyond max_depth
    n = m.add(depth, K, np.eye(4))
    assert n == 40 * 30 - 15 and int(m.counts.sum()) == n
    pts = m.points()
    assert len(pts) == int((m.counts >= 3).sum()) < len(m)  # voxels with fewer than 3 pixels left out
    assert np.allclose(pts[:, 2], 2.0)  # every pixel on the wall: the means are on it too
    keys, counts, means = m.keys.copy(), m.counts.copy(), m.sums / m.counts[:, None]
    assert m.add(depth, K, np.eye(4)) == n  # the same view again: same voxels, twice the pixels, same means
    assert np.array_equal(m.keys, keys) and np.array_equal(m.counts, 2 * counts)
    assert np.allclose(m.sums / m.counts[:, None], means)
    assert len(m.points()) == int((counts >= 2).sum())  # now 2 pixels were enough for 3 hits


def test_moved_camera_and_distance_to_the_nearest_point():
    m = MeasuredSurface(voxel=0.1, min_hits=1)
    T = np.eye(4)
    T[:3, 3] = [5.0, -1.0, 0.5]  # the wall at z = 2 in the camera is at z = 2.5 in the world
    m.add(_wall(), K, T)
    pts = m.points()
    assert np.allclose(pts[:, 2], 2.5)
    q = pts[7] + np.array([0.0, 0.0, 1.25])  # straight out of the wall from one voxel's point
    assert m.distance(q[None])[0] == pytest.approx(1.25, abs=1e-9)
    assert np.isinf(MeasuredSurface().distance(q[None])[0])  # nothing measured: no bound


def test_bad_input_is_refused_and_changes_nothing():
    m = MeasuredSurface()
    m.add(_wall(), K, np.eye(4))
    keys, sums = m.keys.copy(), m.sums.copy()
    with pytest.raises(ValueError):
        m.add(_wall(), np.eye(4), np.eye(4))  # K not 3x3
    with pytest.raises(ValueError):
        m.add(_wall(), K, np.full((4, 4), np.nan))
    with pytest.raises(ValueError):
        m.add(np.zeros(5), K, np.eye(4))
    with pytest.raises(ValueError):
        MeasuredSurface(voxel=0)
    assert np.array_equal(m.keys, keys) and np.array_equal(m.sums, sums)


def test_the_answer_rule_exactly():
    # Columns: a surfel 1 m away, the network (and so the fused answer) at 0.8 m ...
    fused = np.array([0.8, 0.8, 0.8, -0.1, 2.5, 0.7])
    sdf_i = np.array([0.8, 0.8, 0.8, -0.1, 2.5, 0.7])
    d_e = np.array([1.0, 1.0, 1.0, 1.0, 3.0, np.inf])
    # ... nothing measured nearer than the surfel; furniture measured at 0.5 m; a point half
    # way into the margin; inside (the network is negative); the surfel beyond 2 m; no surfel.
    d_m = np.array([1.0, 0.5, 0.975, 0.3, 2.8, np.inf])
    a = measured_fuse(fused, sdf_i, d_e, d_m, margin=0.05, slack=0.01, radius=2.0)
    assert a == pytest.approx([1.0, 0.51, 0.9, -0.1, 2.5, 0.7], abs=1e-12)
    # Signed surfel distances count as unsigned (behind a one-sided surfel is not inside).
    assert measured_fuse(fused, sdf_i, -d_e, d_m)[0] == pytest.approx(1.0)
    # Continuous in the measured distance: the weight goes linearly over the margin.
    dm = np.linspace(0.9, 1.1, 401)
    v = measured_fuse(np.full(401, 0.8), np.full(401, 0.8), np.ones(401), dm)
    assert np.max(np.abs(np.diff(v))) < 0.01
