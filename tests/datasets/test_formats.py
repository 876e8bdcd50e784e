"""Dataset readers of the formats without sample data (generic, ScanNet, ReplicaCAD, TUM,
Redwood): tiny files written here; the generic export of a real sequence; the registry."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh
from aisdf.datasets import READERS, detect, open_dataset, require_data, write_generic
from aisdf.datasets.redwood import write_log
from aisdf.geometry import intrinsics
from helpers.frame_checks import assert_frame


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

