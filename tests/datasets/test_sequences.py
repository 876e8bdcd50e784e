"""Dataset readers on the real files in ../shared/data (AISDF_DATA): where the data lives, the
real sequences, the mesh renderer along a trajectory and the noise hook."""

from __future__ import annotations

import numpy as np
import pytest
from aisdf.datasets import DataMissingError, data_root, detect, open_dataset, require_data
from aisdf.datasets.base import reprojection_residual, subsampled_K
from aisdf.datasets.raycast import MeshScene, open3d_available
from aisdf.geometry import backproject, intrinsics, transform
from helpers.frame_checks import assert_frame, assert_rigid

BACKENDS = ["numpy"] + (["open3d"] if open3d_available() else [])


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

