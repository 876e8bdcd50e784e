"""Camera geometry (OpenCV convention: x right, y down, z forward). Pure numpy.

Names state the frame: ``points_C`` in the camera frame, ``points_W`` in the world
frame, ``T_WC`` maps camera to world.
"""

from __future__ import annotations

import numpy as np


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole intrinsic matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def pixel_grid(H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v), each (H, W) float64, at pixel centres' integer indices."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return u, v


def ray_dirs_C(K: np.ndarray, H: int, W: int) -> np.ndarray:
    """Un-normalised ray directions with z = 1, (H, W, 3): depth * dir is the 3D point."""
    u, v = pixel_grid(H, W)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def valid_depth(depth: np.ndarray, max_depth: float = np.inf) -> np.ndarray:
    """Boolean mask of the usable depth pixels: finite, > 0 and <= ``max_depth`` (metres).
    The one rule every consumer of a keyframe's depth applies (training, the observed
    space, the measured surface, the checks on arrival)."""
    d = np.asarray(depth)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & (d > 0) & (d <= max_depth)


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth (H, W) in metres -> points_C (H, W, 3); invalid pixels (depth <= 0) give NaN."""
    depth = np.asarray(depth, dtype=np.float64)
    pts = ray_dirs_C(K, *depth.shape) * depth[..., None]
    pts[~(depth > 0)] = np.nan
    return pts


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (..., 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotate(T: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Apply the rotation of a 4x4 transform to (..., 3) vectors."""
    return vectors @ T[:3, :3].T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def normals_from_depth(depth: np.ndarray, K: np.ndarray, max_jump: float = 0.1) -> np.ndarray:
    """Surface normals in the camera frame from the depth image's x and y gradients.

    The normal is the cross product of the central-difference tangents along image x and
    y (the paper's footnote), unit length, oriented towards the camera. Pixels whose
    neighbours are invalid, or where depth jumps by more than ``max_jump`` times the depth
    (occlusion boundaries), get NaN. Returns (H, W, 3).
    """
    P = backproject(depth, K)
    H, W = depth.shape
    n = np.full((H, W, 3), np.nan)
    if H < 3 or W < 3:
        return n
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = c / norm
    d = np.asarray(depth, dtype=np.float64)
    dc = d[1:-1, 1:-1]
    jump = np.maximum.reduce(
        [np.abs(d[1:-1, 2:] - dc), np.abs(d[1:-1, :-2] - dc), np.abs(d[2:, 1:-1] - dc), np.abs(d[:-2, 1:-1] - dc)]
    )
    bad = ~(norm[..., 0] > 0) | (jump > max_jump * np.maximum(dc, 1e-6)) | ~(dc > 0)
    # Orient towards the camera: n . p < 0.
    pc = P[1:-1, 1:-1]
    flip = np.einsum("hwc,hwc->hw", c, pc) > 0
    c[flip] *= -1
    c[bad] = np.nan
    n[1:-1, 1:-1] = c
    return n


def decode_depth(raw: np.ndarray, scale: float) -> np.ndarray:
    """float32 metres of raw ``<u2`` depth (metres = raw / scale): the one decoding of the wire's
    integer depth (``protocol.Keyframe.depth_m``, stored keyframes, ``normals_at``), so a value is
    the same float whether a whole image or a few pixels are decoded."""
    return np.asarray(raw).astype(np.float32) / np.float32(scale)


def normals_at(depth: np.ndarray, K: np.ndarray, v: np.ndarray, u: np.ndarray, max_jump: float = 0.1,
               scale: float | None = None) -> np.ndarray:
    """``normals_from_depth(depth, K, max_jump)[v, u]`` for a few pixels (N,), computed from
    their four neighbours only: (N, 3) camera-frame normals, NaN where that gives NaN
    (the image's border, invalid neighbours, occlusion boundaries). What training needs of a
    keyframe's normals, at the pixels it samples, without holding an image of them.
    ``scale``: ``depth`` is raw ``<u2`` (``decode_depth``, stencil pixels only)."""
    d = np.asarray(depth)  # only the stencils' pixels are converted to float64
    H, W = d.shape
    v, u = np.asarray(v, np.int64).reshape(-1), np.asarray(u, np.int64).reshape(-1)
    n = np.full((len(v), 3), np.nan)
    inner = (v >= 1) & (v <= H - 2) & (u >= 1) & (u <= W - 2)
    if not inner.any():
        return n
    vi, ui = v[inner], u[inner]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # the pixel and its right, left, lower and upper neighbours, back-projected as backproject does
    vv = np.stack([vi, vi, vi, vi + 1, vi - 1])
    uu = np.stack([ui, ui + 1, ui - 1, ui, ui])
    z = d[vv, uu] if scale is None else decode_depth(d[vv, uu], scale)
    z = z.astype(np.float64)  # (5, M)
    x, y = (uu - cx) / fx * z, (vv - cy) / fy * z
    none = ~(z > 0)
    x[none], y[none] = np.nan, np.nan
    zn = np.where(none, np.nan, z)
    # tangents along x and y, their cross product and its length, with np.cross's and
    # np.linalg.norm's arithmetic (the same bits as normals_from_depth)
    ax, ay, az = x[1] - x[2], y[1] - y[2], zn[1] - zn[2]
    bx, by, bz = x[3] - x[4], y[3] - y[4], zn[3] - zn[4]
    c = np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)
    norm = np.sqrt(c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1] + c[:, 2] * c[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        c = c / norm[:, None]
    dc = z[0]
    jump = np.abs(z[1:] - dc).max(axis=0)
    bad = ~(norm > 0) | (jump > max_jump * np.maximum(dc, 1e-6)) | ~(dc > 0)
    flip = (c[:, 0] * x[0] + c[:, 1] * y[0]) + c[:, 2] * zn[0] > 0
    c[flip] *= -1
    c[bad] = np.nan
    n[inner] = c
    return n


def kdtree(points: np.ndarray, leafsize: int = 16):
    """A ``scipy.spatial.cKDTree`` of (N, k) points, built with the sliding-midpoint rule
    (``balanced_tree=False``). Why: ``aisdf.network`` turns on flush-to-zero / denormals-
    are-zero (``torch.set_flush_denormal``) in every process that imports it, and threads
    inherit it; with that on, scipy's default median-balanced build (scipy 1.17) crashes
    the process (SIGSEGV) on grid-like points, e.g. a 0.1 m lattice of a floor and a box,
    as measured points, surfel centres and marching-cubes vertices can be (found
    2026-12-03; 300 such random point sets in a row crash it at once, none with this
    build, and none with the default build when flush-to-zero is off). The sliding
    midpoint also builds faster; queries answer the same."""
    from scipy.spatial import cKDTree

    return cKDTree(points, leafsize=leafsize, balanced_tree=False)
