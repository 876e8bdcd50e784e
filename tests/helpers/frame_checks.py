"""Checks of what a dataset reader returns: rigid poses and well-formed frames."""

import numpy as np


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
