"""Dataset readers: the real files in ../shared/data (AISDF_DATA), tiny files written
here for the formats without sample data, and the mesh / layout renderers."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh
from aisdf.datasets import (
    READERS,
    DataMissingError,
    data_root,
    detect,
    open_dataset,
    require_data,
    write_generic,
)
from aisdf.datasets.base import reprojection_residual, subsampled_K
from aisdf.datasets.layout import extrude_room, room_trajectory, triangulate_polygon
from aisdf.datasets.raycast import MeshScene, open3d_available
from aisdf.datasets.redwood import write_log
from aisdf.geometry import backproject, intrinsics, transform

BACKENDS = ["numpy"] + (["open3d"] if open3d_available() else [])


def assert_rigid(T: np.ndarray) -> None:
    T = np.asarray(T).reshape(-1, 4, 4)
    R = T[:, :3, :3]
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-3
    )  # 7-Scenes: 1e-4
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-3)
    np.testing.assert_allclose(T[:, 3], np.broadcast_to([0, 0, 0, 1], (len(T), 4)), atol=1e-9)


def assert_frame(f: dict, H: int, W: int) -> None:
    assert set(f) == {"frame_id", "stamp", "depth", "K", "T_WC"}
    assert f["depth"].dtype == np.float32 and f["depth"].shape == (H, W)
    assert f["K"].dtype == np.float64 and f["K"].shape == (3, 3)
    assert f["T_WC"].dtype == np.float64 and f["T_WC"].shape == (4, 4)
    assert isinstance(f["frame_id"], int) and isinstance(f["stamp"], float)
    assert np.all(np.isfinite(f["depth"])) and f["depth"].min() >= 0
    assert_rigid(f["T_WC"])


# --- where the data lives ----------------------------------------------------------------


def test_data_root_env_set_but_empty_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv("AISDF_DATA", str(tmp_path))
    with pytest.raises(DataMissingError):
        data_root()
    monkeypatch.setenv("AISDF_DATA", str(tmp_path / "nope"))
    with pytest.raises(DataMissingError):
        data_root()
    (tmp_path / "x").mkdir()
    monkeypatch.setenv("AISDF_DATA", str(tmp_path))
    assert data_root() == tmp_path.resolve()


def test_data_root_unset_skips_only_without_the_default_folder(tmp_path, monkeypatch):
    import aisdf.datasets.base as base

    monkeypatch.delenv("AISDF_DATA", raising=False)
    monkeypatch.setattr(base, "_REPO_ROOT", tmp_path / "repo")
    assert data_root() is None
    with pytest.raises(pytest.skip.Exception):
        require_data("7scenes-redkitchen")
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert data_root() == tmp_path / "shared" / "data"
    with pytest.raises(pytest.fail.Exception):  # the default exists but lacks the folder
        require_data("7scenes-redkitchen")
    # CI's relative AISDF_DATA=../shared/data is read from the repository root too.
    monkeypatch.setenv("AISDF_DATA", "../shared/data")
    (tmp_path / "shared" / "data" / "x").mkdir()
    (tmp_path / "repo").mkdir()
    monkeypatch.chdir(tmp_path)
    assert data_root() == (tmp_path / "shared" / "data").resolve()


def test_detect_every_shared_folder():
    root = require_data()
    expect = {
        "3dmatch-sun3d-studyroom-nvblox/3dmatch": "7scenes",
        "7scenes-redkitchen/data": "7scenes",
        "icl-nuim-livingroom1-micro/livingroom1_clean_micro": "redwood",
        "icl-nuim-livingroom1-micro/open3d_TestData_RGBD": "redwood",
        "replica-office0-nvblox/replica/office0": "replica",
        "replica-office0-nvblox": "mesh",
        "atlantalayout-corners": "layout",
        "zind-sample-tour": "layout",
    }
    for sub, kind in expect.items():
        assert detect(root / sub) == kind, sub
    with pytest.raises(ValueError):
        open_dataset("nonsense", root)


# --- real sequences ----------------------------------------------------------------------


def test_7scenes_redkitchen():
    ds = open_dataset("7scenes", require_data("7scenes-redkitchen/data"))
    assert len(ds) == 250 and (ds.H, ds.W) == (480, 640) and ds.mesh_path is None
    np.testing.assert_allclose(ds.K, intrinsics(585, 585, 320, 240))
    f0, f1 = ds[0], ds[1]
    assert_frame(f0, 480, 640)
    assert (f1["frame_id"], f1["stamp"]) == (4, pytest.approx(4 / 30))
    d = f0["depth"][f0["depth"] > 0]
    assert 0.5 < d.min() and d.max() < 4.0  # SOURCE.md: 0.8 to 3.6 m
    # Consecutive frames agree: 6 mm in SOURCE.md for frames 0-20 (our 0-5).
    assert reprojection_residual(f0, f1) < 0.01
    assert reprojection_residual(ds[100], ds[101]) < 0.02
    assert_rigid(ds.poses())


def test_3dmatch_studyroom():
    ds = open_dataset("3dmatch", require_data("3dmatch-sun3d-studyroom-nvblox/3dmatch"))
    assert [ds[i]["frame_id"] for i in range(len(ds))] == [0, 1, 2, 116, 422]
    np.testing.assert_allclose(ds.K[0, 0], 570.342205)
    f = ds[0]
    assert_frame(f, 480, 640)
    assert 0.3 < f["depth"][f["depth"] > 0].min() and f["depth"].max() < 10
    assert reprojection_residual(ds[0], ds[1]) < 0.03  # SfM poses: 2 cm


def test_icl_nuim_micro_estimated_trajectory():
    ds = open_dataset("icl-nuim", require_data("icl-nuim-livingroom1-micro/livingroom1_clean_micro"))
    assert len(ds) == 211
    np.testing.assert_allclose(ds.K, intrinsics(525, 525, 319.5, 239.5))
    np.testing.assert_allclose(ds[0]["T_WC"], np.eye(4), atol=1e-7)  # .log frame 0
    assert_frame(ds[50], 480, 640)
    assert reprojection_residual(ds[0], ds[1]) < 0.005
    assert reprojection_residual(ds[150], ds[151]) < 0.005
    assert_rigid(ds.poses())


def test_icl_nuim_gt_frames_with_open3d_intrinsics_file():
    ds = open_dataset("redwood", require_data("icl-nuim-livingroom1-micro/open3d_TestData_RGBD"))
    assert len(ds) == 5
    np.testing.assert_allclose(ds.K, intrinsics(525, 525, 319.5, 239.5))
    assert reprojection_residual(ds[0], ds[1]) < 0.02  # noisy depth, 7 mm median noise


def test_replica_office_depth_frames_match_the_mesh():
    root = require_data("replica-office0-nvblox/replica")
    ds = open_dataset("replica", root / "office0")
    assert len(ds) == 4 and (ds.H, ds.W) == (680, 1200) and ds.depth_scale == 6553.5
    np.testing.assert_allclose(ds.K, intrinsics(600, 600, 599.5, 339.5))
    assert ds.mesh_path == root / "office0_mesh.ply"
    f = ds[0]
    assert_frame(f, 680, 1200)
    assert reprojection_residual(ds[3], ds[0]) < 0.002  # SOURCE.md: 0.6 mm
    # Back-projected depth lies on the mesh (SOURCE.md: median 1.3 mm).
    pts = transform(f["T_WC"], backproject(f["depth"][::8, ::8], subsampled_K(f["K"], 8)).reshape(-1, 3))
    d = MeshScene.from_file(ds.mesh_path).distance(pts[np.isfinite(pts[:, 0])], sign="unsigned")
    assert np.median(d) < 0.003


@pytest.mark.parametrize("backend", BACKENDS)
def test_replica_office_rendered_along_its_trajectory(backend):
    root = require_data("replica-office0-nvblox")
    ds = open_dataset("mesh", root, backend=backend)
    assert len(ds) == 2000 and (ds.H, ds.W) == (680, 1200)
    real = open_dataset("replica", root / "replica" / "office0")[0]
    f = ds[0]
    assert_frame(f, 680, 1200)
    np.testing.assert_array_equal(f["T_WC"], real["T_WC"])
    both = (f["depth"] > 0) & (real["depth"] > 0)
    assert both.mean() > 0.99
    assert np.median(np.abs(f["depth"] - real["depth"])[both]) < 0.003  # decimated mesh
    g = ds[1000]
    assert (g["depth"] > 0).mean() > 0.9 and g["depth"].max() < 8
    assert reprojection_residual(ds[1000], ds[1003]) < 0.002


def test_render_backends_agree():
    assert len(BACKENDS) == 2, "open3d (a dev dependency) does not import: only the numpy backend"
    root = require_data("replica-office0-nvblox/replica")
    T = np.loadtxt(root / "office0" / "traj.txt")[500].reshape(4, 4)
    K = intrinsics(600, 600, 599.5, 339.5)
    a, b = (MeshScene.from_file(root / "office0_mesh.ply", backend=be).render_depth(K, T, 170, 300) for be in BACKENDS)
    assert ((a > 0) != (b > 0)).mean() < 1e-3
    both = (a > 0) & (b > 0)
    assert np.quantile(np.abs(a - b)[both], 0.999) < 1e-4


def test_noise_hook_is_reproducible():
    root = require_data("replica-office0-nvblox")

    def noise(depth, rng):
        return depth + rng.normal(0, 0.01, depth.shape).astype(np.float32) * (depth > 0)

    ds = open_dataset("mesh", root, noise=noise, seed=3, stride=100, size=(68, 120), K=intrinsics(60, 60, 59.5, 33.95))
    assert len(ds) == 20 and ds[1]["frame_id"] == 100
    a, b = ds[2]["depth"], ds[2]["depth"]
    np.testing.assert_array_equal(a, b)
    clean = ds.render(ds.poses()[2])
    assert 0.005 < np.std((a - clean)[clean > 0]) < 0.015


# --- rooms extruded from real layouts ----------------------------------------------------


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


# --- formats with no sample data: tiny files written here --------------------------------


def _tiny_frames(n=3, H=6, W=8):
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        T = np.eye(4)
        c, s = np.cos(0.1 * i), np.sin(0.1 * i)
        T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[:3, 3] = [0.1 * i, -0.2 * i, 1.0]
        depth = np.round(rng.uniform(0.5, 4.0, (H, W)) * 1000) / 1000
        depth[0, 0] = 0
        frames.append({"depth": depth.astype(np.float32), "T_WC": T, "frame_id": i, "stamp": i / 30})
    return frames


def test_generic_roundtrip(tmp_path):
    K = intrinsics(10, 11, 3.5, 2.5)
    frames = _tiny_frames()
    root = write_generic(tmp_path / "seq", frames, K)
    assert detect(root) == "generic"
    ds = open_dataset("generic", root)
    assert len(ds) == 3 and ds.depth_scale == 1000 and ds.mesh_path is None
    np.testing.assert_allclose(ds.K, K)
    for f, g in zip(frames, ds, strict=True):
        assert_frame(g, 6, 8)
        np.testing.assert_allclose(g["depth"], f["depth"], atol=1e-6)
        np.testing.assert_allclose(g["T_WC"], f["T_WC"], atol=1e-15)
        assert g["stamp"] == pytest.approx(f["stamp"])


def test_generic_single_poses_file_and_meta(tmp_path):
    root = tmp_path / "g"
    (root / "depth").mkdir(parents=True)
    (root / "intrinsics.txt").write_text("500 0 320\n0 500 240\n0 0 1\n")
    (root / "meta.yaml").write_text("depth_scale: 5000\nfps: 10\nname: hall\n")
    for i in (3, 7):
        cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), np.full((4, 5), 5000 * (i + 1), np.uint16) // 4)
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, :3, 3] = [1, 2, 3]
    np.savetxt(root / "poses.txt", poses.reshape(2, 16))
    trimesh.creation.box().export(root / "mesh.ply")
    ds = open_dataset(None, root)
    assert ds.name == "hall" and ds.mesh_path == root / "mesh.ply"
    f = ds[1]
    assert f["frame_id"] == 7 and f["stamp"] == pytest.approx(0.7)
    assert f["depth"][0, 0] == pytest.approx(8 / 4)
    np.testing.assert_array_equal(f["T_WC"][:3, 3], [1, 2, 3])
    assert ds.gt_mesh().is_watertight


def test_generic_export_of_a_real_sequence(tmp_path):
    src = open_dataset("7scenes", require_data("7scenes-redkitchen/data"))
    frames = [src[i] for i in range(3)]
    ds = open_dataset("generic", write_generic(tmp_path / "rk", frames, src.K))
    for f, g in zip(frames, ds, strict=True):
        np.testing.assert_array_equal(g["depth"], f["depth"])  # millimetres survive exactly
        np.testing.assert_allclose(g["T_WC"], f["T_WC"], atol=1e-15)
        assert g["frame_id"] == f["frame_id"]


def test_scannet_sensreader_export(tmp_path):
    root = tmp_path / "scene0000_00"
    for d in ("depth", "pose", "intrinsic"):
        (root / "frames" / d).mkdir(parents=True)
    np.savetxt(
        root / "frames/intrinsic/intrinsic_depth.txt",
        [[577.6, 0, 319.5, 0], [0, 578.7, 239.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    )
    for i in range(12):  # unpadded names: 10 sorts after 9
        cv2.imwrite(str(root / f"frames/depth/{i}.png"), np.full((3, 4), 1000 + i, np.uint16))
        T = np.eye(4)
        T[0, 3] = i
        if i == 5:
            T[:] = -np.inf  # lost tracking
        np.savetxt(root / f"frames/pose/{i}.txt", T)
    assert detect(root) == "scannet"
    ds = open_dataset("scannet", root)
    assert len(ds) == 11
    np.testing.assert_allclose(ds.K, intrinsics(577.6, 578.7, 319.5, 239.5))
    f = ds[9]
    assert f["frame_id"] == 10 and f["T_WC"][0, 3] == 10 and f["depth"][0, 0] == pytest.approx(1.010)
    assert f["stamp"] == pytest.approx(10 / 30)


def test_replicacad_isdf_layout(tmp_path):
    root = tmp_path / "apt_2_nav"
    (root / "results").mkdir(parents=True)
    T = np.stack([np.eye(4)] * 3)
    T[:, 2, 3] = [0, 1, 2]
    np.savetxt(root / "traj.txt", T.reshape(3, 16))
    for i in range(3):
        cv2.imwrite(str(root / f"results/depth{i:06d}.png"), np.full((680, 1200), 3277 * (i + 1), np.uint16))
        cv2.imwrite(str(root / f"results/ndepth{i:06d}.png"), np.full((680, 1200), 6553, np.uint16))
    assert detect(root) == "replicacad"
    ds = open_dataset("replicacad", root)
    np.testing.assert_allclose(ds.K, intrinsics(600, 600, 599.5, 339.5))
    f = ds[2]
    assert f["depth"][0, 0] == pytest.approx(3 * 3277 / 3276.75) and f["T_WC"][2, 3] == 2
    assert open_dataset("replicacad", root, noisy=True)[0]["depth"][5, 5] == pytest.approx(6553 / 3276.75)


def test_tum_association_by_timestamp(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    (root / "depth").mkdir(parents=True)
    stamps = [1.000, 1.033, 1.500, 2.000]
    lines = ["# depth maps", "# file: 'x'", "# timestamp filename"]
    for t in stamps:
        cv2.imwrite(str(root / f"depth/{t:.6f}.png"), np.full((3, 4), 10000, np.uint16))
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    q90 = [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # 90 degrees about z
    gt = [[0.99, 0, 0, 0, 0, 0, 0, 1], [1.01, 1, 0, 0, 0, 0, 0, 1], [1.04, 1.3, 0, 0, *q90], [1.51, 2, 0, 0, *q90]]
    (root / "groundtruth.txt").write_text("# ground truth\n" + "\n".join(" ".join(map(str, r)) for r in gt) + "\n")
    assert detect(root) == "tum"
    ds = open_dataset("tum", root)
    # 1.5 is 0.01 s from a sample; 2.0 lies after the last one: dropped.
    assert len(ds) == 3 and [f["stamp"] for f in ds] == pytest.approx([1.0, 1.033, 1.5])
    np.testing.assert_allclose(ds.K, intrinsics(517.3, 516.5, 318.6, 255.3))
    f0, f1 = ds[0], ds[1]
    assert f0["depth"][0, 0] == pytest.approx(2.0)
    np.testing.assert_allclose(f0["T_WC"][:3, 3], [0.5, 0, 0], atol=1e-9)  # halfway 0.99..1.01
    np.testing.assert_allclose(f1["T_WC"][0, 3], 1.0 + 0.3 * 23 / 30, atol=1e-9)
    ang = np.rad2deg(np.arctan2(f1["T_WC"][1, 0], f1["T_WC"][0, 0]))
    assert ang == pytest.approx(90 * 23 / 30, abs=1e-6)  # slerp


def test_redwood_log_written_here(tmp_path):
    root = tmp_path / "seq"
    (root / "depth").mkdir(parents=True)
    T = np.stack([np.eye(4)] * 3)
    T[:, 1, 3] = [0.0, 0.5, 1.0]
    write_log(root / "trajectory.log", T)
    for i in range(3):
        cv2.imwrite(str(root / f"depth/{i:05d}.png"), np.full((2, 2), 1500, np.uint16))
    (root / "camera_primesense.json").write_text(
        json.dumps({"width": 2, "height": 2, "intrinsic_matrix": [1, 0, 0, 0, 2, 0, 0.5, 0.25, 1]})
    )
    ds = open_dataset(None, root)
    np.testing.assert_allclose(ds.K, intrinsics(1, 2, 0.5, 0.25))
    assert ds[2]["T_WC"][1, 3] == 1.0 and ds[2]["depth"][1, 1] == pytest.approx(1.5)


def test_registry_is_complete():
    assert set(READERS) >= {
        "generic",
        "scannet",
        "replicacad",
        "replica",
        "7scenes",
        "redwood",
        "tum",
        "mesh",
        "layout",
    }


def test_kinect_noise_model_on_a_rendered_room():
    from aisdf.synthetic.render import KinectNoise

    root = require_data("atlantalayout-corners")
    clean = open_dataset("layout", root, room="7y3sRwLe3Va")
    noisy = open_dataset("layout", root, room="7y3sRwLe3Va", noise=KinectNoise(seed=1))
    a, b = clean[5]["depth"], noisy[5]["depth"]
    np.testing.assert_array_equal(b, noisy[5]["depth"])  # reproducible
    both = (a > 0) & (b > 0)
    assert 0.5 < both.mean() < 1.0 and 0.0005 < np.median(np.abs(a - b)[both]) < 0.02
