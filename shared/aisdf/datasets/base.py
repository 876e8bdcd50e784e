"""What every dataset reader shares: the ``Dataset`` interface, file helpers, and where
the data lives.

A frame is a plain dict::

    {"frame_id": int, "stamp": float (s), "depth": float32 (H, W) metres, 0 = invalid,
     "K": float64 (3, 3), "T_WC": float64 (4, 4) camera-to-world, OpenCV camera}
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image

from ..geometry import intrinsics

ENV_DATA = "AISDF_DATA"
_REPO_ROOT = Path(__file__).resolve().parents[3]


class DataMissingError(FileNotFoundError):
    """The data a caller asked for is not where the configuration says it is."""


class Dataset:
    """A posed depth sequence. Subclasses set ``K``, ``name``, ``H``, ``W`` and implement
    ``__len__`` and ``_load(i) -> (depth float32 metres, T_WC, frame_id, stamp)``."""

    kind: str = ""
    K: np.ndarray
    name: str
    H: int
    W: int
    mesh_path: Path | None = None

    @classmethod
    def sniff(cls, path: Path) -> bool:
        """Whether ``path`` looks like this reader's layout (used by ``detect``)."""
        return False

    def __len__(self) -> int:
        raise NotImplementedError

    def _load(self, i: int) -> tuple[np.ndarray, np.ndarray, int, float]:
        raise NotImplementedError

    def frame(self, i: int) -> dict:
        """Frame ``i`` (0 <= i < len) as the dict described in the module docstring."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        i = i % len(self)
        depth, T_WC, frame_id, stamp = self._load(i)
        depth = np.asarray(depth, dtype=np.float32)
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        return {
            "frame_id": int(frame_id),
            "stamp": float(stamp),
            "depth": depth,
            "K": np.array(self.K, dtype=np.float64),
            "T_WC": np.asarray(T_WC, dtype=np.float64),
        }

    def __getitem__(self, i: int) -> dict:
        return self.frame(i)

    def __iter__(self) -> Iterator[dict]:
        return (self.frame(i) for i in range(len(self)))

    def poses(self) -> np.ndarray:
        """All camera-to-world poses, (N, 4, 4). Readers override this when it is cheap."""
        return np.stack([self.frame(i)["T_WC"] for i in range(len(self))])

    def gt_mesh(self):
        """The ground-truth mesh (trimesh.Trimesh) or None when the dataset has none."""
        if self.mesh_path is None:
            return None
        import trimesh

        return trimesh.load(self.mesh_path, force="mesh", process=False)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)}, size={self.W}x{self.H})"


# --- where the data lives ----------------------------------------------------------------


def data_root() -> Path | None:
    """The shared data folder.

    ``AISDF_DATA`` when set (relative paths are tried from the working directory, then
    from the repository root); it must exist and be non-empty, else ``DataMissingError``.
    Unset: ``../shared/data`` beside the repository when it exists, else None.
    """
    env = os.environ.get(ENV_DATA)
    if env:
        p = Path(env).expanduser()
        for cand in [p] if p.is_absolute() else [Path.cwd() / p, _REPO_ROOT / p]:
            if cand.is_dir() and any(cand.iterdir()):
                return cand.resolve()
        raise DataMissingError(f"{ENV_DATA}={env} is set but is not a non-empty folder")
    default = _REPO_ROOT.parent / "shared" / "data"
    return default if default.is_dir() else None


def require_data(sub: str = "") -> Path:
    """For tests: the path ``data_root()/sub``. Fails the test when ``AISDF_DATA`` is set
    and the folder is missing or empty; skips only when ``AISDF_DATA`` is unset and the
    default folder does not exist."""
    import pytest

    try:
        root = data_root()
    except DataMissingError as e:
        pytest.fail(str(e))
    if root is None:
        pytest.skip(f"{ENV_DATA} unset and no ../shared/data beside the repository")
    p = root / sub
    if not p.exists() or (p.is_dir() and not any(p.iterdir())):
        pytest.fail(f"data folder {p} is missing or empty")
    return p


# --- small file helpers ------------------------------------------------------------------


def read_depth_png(path: Path | str, scale: float, invalid: tuple[int, ...] = ()) -> np.ndarray:
    """16-bit depth PNG -> float32 metres (value / scale); 0 and ``invalid`` values -> 0."""
    try:
        with Image.open(path) as img:
            raw = np.asarray(img)
    except (OSError, ValueError):  # missing, unreadable or not an image
        raise DataMissingError(f"cannot read depth image {path}") from None
    if raw.ndim != 2:
        raise ValueError(f"{path}: expected a single-channel depth image, got shape {raw.shape}")
    depth = raw.astype(np.float32) / np.float32(scale)
    for v in invalid:
        depth[raw == v] = 0.0
    return depth


def write_depth_png(path: Path | str, depth_m: np.ndarray, scale: float) -> None:
    """float metres -> 16-bit PNG (round(depth * scale)); invalid (<= 0, non-finite) -> 0."""
    d = np.asarray(depth_m, dtype=np.float64)
    raw = np.where(np.isfinite(d) & (d > 0), np.round(d * scale), 0.0)
    if raw.max(initial=0) > 65535:
        raise ValueError(f"depth {d[np.isfinite(d)].max():.2f} m overflows 16 bits at scale {scale}")
    Image.fromarray(raw.astype(np.uint16)).save(str(path), format="PNG")


def read_matrix(path: Path | str) -> np.ndarray:
    """A whitespace-separated matrix file (e.g. a 4x4 pose) as float64."""
    return np.loadtxt(path, dtype=np.float64, ndmin=2)


def read_intrinsics(path: Path | str) -> np.ndarray:
    """``fx fy cx cy`` (4 numbers) or a 3x3 / 4x4 matrix -> 3x3 K."""
    vals = np.loadtxt(path, dtype=np.float64).ravel()
    if vals.size == 4:
        return intrinsics(*vals)
    if vals.size in (9, 16):
        n = 3 if vals.size == 9 else 4
        return vals.reshape(n, n)[:3, :3].copy()
    raise ValueError(f"{path}: expected 4 numbers or a 3x3/4x4 matrix, got {vals.size} numbers")


def numbered(files, pattern: str) -> list[tuple[int, Path]]:
    """``[(number, path)]`` sorted by number for the files whose name matches ``pattern``
    (a regex with one group of digits)."""
    rx = re.compile(pattern)
    out = []
    for f in files:
        m = rx.fullmatch(Path(f).name)
        if m:
            out.append((int(m.group(1)), Path(f)))
    return sorted(out)


def load_trajectory(path: Path | str) -> np.ndarray:
    """``traj.txt`` (one row-major 4x4 per line, 16 numbers) -> (N, 4, 4)."""
    rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if rows.shape[1] != 16:
        raise ValueError(f"{path}: expected 16 numbers per line, got {rows.shape[1]}")
    return rows.reshape(-1, 4, 4)


def reprojection_residual(src: dict, dst: dict, stride: int = 4) -> float:
    """Median |z_projected - depth_dst| (metres) of ``src``'s valid pixels moved into
    ``dst``'s camera (both frame dicts), over pixels that land on valid ``dst`` depth.
    A sanity check of depth units, intrinsics and pose conventions: a few mm to cm for
    consistent frames, tens of cm or more when something is misread."""
    from ..geometry import backproject, invert, transform

    pts_C = backproject(src["depth"][::stride, ::stride], subsampled_K(src["K"], stride)).reshape(-1, 3)
    pts_C = pts_C[np.isfinite(pts_C[:, 0])]
    p = transform(invert(dst["T_WC"]) @ src["T_WC"], pts_C)
    p = p[p[:, 2] > 1e-3]
    K = dst["K"]
    u = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    H, W = dst["depth"].shape
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    d = dst["depth"][v[inside], u[inside]]
    ok = d > 0
    if not ok.any():
        return float("inf")
    return float(np.median(np.abs(p[inside][ok, 2] - d[ok])))


def subsampled_K(K: np.ndarray, s: int) -> np.ndarray:
    """Intrinsics of the image sub-sampled as ``image[::s, ::s]``."""
    Ks = np.array(K, dtype=np.float64)
    Ks[:2] /= s
    return Ks
