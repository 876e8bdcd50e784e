"""Rooms extruded from real layouts (Atlanta layout corners, ZInD) and the L-shaped room: the
mesh, the trajectory through the rooms, the rendered frames, and the Kinect noise model on a
rendered room."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from aisdf.datasets import open_dataset, require_data
from aisdf.datasets.base import reprojection_residual, subsampled_K
from aisdf.datasets.layout import extrude_room, room_trajectory, triangulate_polygon
from aisdf.datasets.raycast import MeshScene
from aisdf.geometry import backproject, transform
from helpers.frame_checks import assert_rigid


def _wall_angles(mesh: trimesh.Trimesh) -> np.ndarray:
    """Wall directions in degrees [0, 180): perpendicular to the walls' normals."""
    n = mesh.face_normals[np.abs(mesh.face_normals[:, 2]) < 1e-6]
    return np.unique(np.round(np.rad2deg(np.arctan2(n[:, 1], n[:, 0])) + 90) % 180)


def test_atlanta_layout_rooms():
    root = require_data("atlantalayout-corners")
    ds = open_dataset("layout", root, room="2t7WUuJeko7")
    mesh = ds.gt_mesh()
    assert mesh.is_watertight and len(ds.layout["polygon"]) == 7
    assert ds.layout["ceiling"] == pytest.approx(3.4, abs=0.1)  # SOURCE.md
    # Genuine Atlanta world: wall directions 16, 60/62, 110, 147/155 degrees.
    angles = _wall_angles(mesh)
    for a in (16, 61, 110, 147, 155):
        assert np.min(np.abs((angles - a + 90) % 180 - 90)) <= 2, (a, angles)
    _check_rendered_room(ds)
    square = open_dataset("layout", root, room="7y3sRwLe3Va")
    assert np.ptp(square.layout["polygon"], axis=0) == pytest.approx([2.55, 2.55], abs=0.1)


def test_zind_room_06():
    ds = open_dataset("layout", require_data("zind-sample-tour"))
    lay = ds.layout
    assert ds.name == "complete_room_06" and len(lay["polygon"]) == 24
    x, y = lay["polygon"].T
    assert 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)) == pytest.approx(44, abs=1)
    assert lay["ceiling"] == pytest.approx(2.36, abs=0.01)
    assert ds.gt_mesh().is_watertight
    T = ds.poses()
    assert len(T) > 500 and np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).max() < 0.05
    _check_rendered_room(ds)


def _check_rendered_room(ds) -> None:
    """Every pixel sees the closed room; back-projected points lie on its surface; poses
    are inside with the free side positive."""
    scene = MeshScene.from_trimesh(ds.gt_mesh())
    T = ds.poses()
    assert_rigid(T)
    assert np.all(scene.distance(T[:, :3, 3]) > 0.2)  # cameras inside, away from walls
    for i in (0, len(ds) // 2):
        f = ds[i]
        assert (f["depth"] > 0).all()
        pts = transform(f["T_WC"], backproject(f["depth"][::16, ::16], subsampled_K(f["K"], 16)).reshape(-1, 3))
        assert np.abs(scene.distance(pts)).max() < 1e-4
    assert reprojection_residual(ds[0], ds[1]) < 1e-3


def test_extrusion_and_trajectory_on_an_l_shaped_room():
    L = np.array([[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]], dtype=float)
    assert len(triangulate_polygon(L)) == 4
    mesh = extrude_room(L[::-1], ceiling=2.5)  # clockwise input is reoriented
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(-12 * 2.5)  # normals face into the room
    scene = MeshScene.from_trimesh(mesh)
    np.testing.assert_allclose(
        scene.distance(np.array([[1, 1, 1], [3, 1, 0.5], [4.5, 1, 1], [3, 3, 1]])), [1, 0.5, -0.5, -1]
    )
    # Through (1, 1), every waypoint inside is reached; (3.5, 3.5) lies outside the L.
    T = room_trajectory(L, [[1, 3], [3, 1], [1, 1], [3.5, 3.5]], height=1.5)
    assert np.all(scene.distance(T[:, :3, 3]) >= 0.25 - 1e-9)
    near = lambda T, w: np.min(np.linalg.norm(T[:, :2, 3] - w, axis=1))  # noqa: E731
    assert near(T, [1, 3]) < 0.31 and near(T, [1, 1]) < 0.31 and near(T, [3, 1]) < 0.31
    assert near(T, [3.5, 3.5]) > 1.0
    # The straight walk from (1, 3) to (3, 1) grazes the corner (2, 2): (3, 1) is left out.
    T = room_trajectory(L, [[1, 3], [3, 1]], height=1.5)
    assert near(T, [3, 1]) > 1.0


def test_kinect_noise_model_on_a_rendered_room():
    from aisdf.synthetic.render import KinectNoise

    root = require_data("atlantalayout-corners")
    clean = open_dataset("layout", root, room="7y3sRwLe3Va")
    noisy = open_dataset("layout", root, room="7y3sRwLe3Va", noise=KinectNoise(seed=1))
    a, b = clean[5]["depth"], noisy[5]["depth"]
    np.testing.assert_array_equal(b, noisy[5]["depth"])  # reproducible
    both = (a > 0) & (b > 0)
    assert 0.5 < both.mean() < 1.0 and 0.0005 < np.median(np.abs(a - b)[both]) < 0.02
