"""ROS message contents -> AiSDF arrays, for messages deserialised by ``rosbags`` (ROS 1 or
ROS 2 type stores; the field names differ only in ``CameraInfo``: ``K`` vs ``k``).

- :func:`depth_from_image`: ``sensor_msgs/Image`` with encoding ``16UC1``/``mono16``
  (millimetres) or ``32FC1`` (metres), either byte order (``is_bigendian``), rows padded to
  ``step`` -> float32 metres, 0 = invalid (NaN, inf, negative and 0 all become 0).
- :func:`depth_from_compressed`: ``sensor_msgs/CompressedImage`` holding a 16-bit PNG
  (millimetres), plain (``format`` "png", "16UC1; png") or image_transport's
  ``compressedDepth`` (a 12-byte header before the PNG; 16UC1, and 32FC1 with its inverse-depth
  quantisation).
- :func:`K_from_camera_info`: the 3x3 intrinsic matrix.
- :func:`stamp_ns` / :func:`stamp_s`: a header stamp in integer nanoseconds / float seconds.

Every function raises ``ValueError`` with a sentence when the message cannot be read."""

from __future__ import annotations

import io
import struct

import numpy as np

DEPTH_ENCODINGS = {"16UC1", "mono16", "32FC1"}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def stamp_ns(stamp) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_s(stamp) -> float:
    return stamp_ns(stamp) * 1e-9


def header_stamp_ns(msg) -> int:
    return stamp_ns(msg.header.stamp)


def _clean(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def check_image_encoding(msg) -> None:
    """Raise ``ValueError`` unless ``msg`` (sensor_msgs/Image) is a depth encoding we read."""
    if msg.encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"depth image encoding {msg.encoding!r} is not supported (use 16UC1 millimetres or "
                         f"32FC1 metres)")


def depth_from_image(msg) -> np.ndarray:
    """``sensor_msgs/Image`` (16UC1/mono16 mm or 32FC1 m) -> (H, W) float32 metres."""
    check_image_encoding(msg)
    H, W, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = 4 if msg.encoding == "32FC1" else 2
    if H <= 0 or W <= 0:
        raise ValueError(f"depth image has no pixels ({W}x{H})")
    if step < W * itemsize:
        raise ValueError(f"depth image step {step} is shorter than a row ({W} x {itemsize} bytes)")
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if data.size < step * (H - 1) + W * itemsize:
        raise ValueError(f"depth image data has {data.size} bytes, {W}x{H} with step {step} needs "
                         f"{step * (H - 1) + W * itemsize}")
    if data.size < step * H:  # a last row without its padding
        data = np.concatenate([data, np.zeros(step * H - data.size, np.uint8)])
    rows = data[: step * H].reshape(H, step)[:, : W * itemsize]
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype(order + ("f4" if itemsize == 4 else "u2"))
    values = np.ascontiguousarray(rows).view(dtype).reshape(H, W)
    if itemsize == 2:
        return _clean(values.astype(np.float32) / 1000.0)
    return _clean(values.astype(np.float32))


def _png_to_array(data: bytes) -> np.ndarray:
    from PIL import Image

    img = Image.open(io.BytesIO(data))
    arr = np.asarray(img)
    if arr.ndim != 2 or img.mode not in ("I", "I;16", "I;16B", "I;16L"):
        raise ValueError(f"compressed depth PNG is mode {img.mode!r} {arr.shape}; a 16-bit single-channel PNG "
                         f"(millimetres) is expected")
    return arr.astype(np.float64)


def depth_from_compressed(msg) -> np.ndarray:
    """``sensor_msgs/CompressedImage`` holding a 16-bit depth PNG -> (H, W) float32 metres."""
    fmt = str(msg.format).lower()
    data = bytes(memoryview(msg.data))
    if "png" not in fmt and not data.startswith(PNG_SIGNATURE) and PNG_SIGNATURE not in data[:64]:
        raise ValueError(f"compressed depth format {msg.format!r} is not supported (PNG depth only)")
    at = data.find(PNG_SIGNATURE, 0, 64)
    if at < 0:
        raise ValueError("compressed depth holds no PNG image")
    values = _png_to_array(data[at:])
    if "compresseddepth" in fmt and "32fc1" in fmt:
        # image_transport compressedDepth, 32FC1: a header (int32 format, float A, float B)
        # then PNG of inverse depth quantised as value = A / depth + B; 0 = invalid.
        if at < 12:
            raise ValueError("compressedDepth 32FC1 message lacks its 12-byte quantisation header")
        _fmt, qa, qb = struct.unpack("<iff", data[:12])
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(values > 0, qa / (values - qb), 0.0)
        return _clean(depth.astype(np.float32))
    return _clean((values / 1000.0).astype(np.float32))


def depth_from_msg(msgtype: str, msg) -> np.ndarray:
    if msgtype.endswith("CompressedImage"):
        return depth_from_compressed(msg)
    if msgtype.endswith("Image"):
        return depth_from_image(msg)
    raise ValueError(f"{msgtype} is not a depth image type (sensor_msgs/Image or CompressedImage)")


def K_from_camera_info(msg) -> np.ndarray:
    """``sensor_msgs/CameraInfo`` -> (3, 3) float64 (``k`` in ROS 2, ``K`` in ROS 1)."""
    k = getattr(msg, "k", None)
    if k is None:
        k = getattr(msg, "K", None)
    if k is None:
        raise ValueError("camera info has no K/k field")
    K = np.asarray(k, dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise ValueError(f"camera info K has {K.size} values, 9 expected")
    K = K.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.all(np.isfinite(K)):
        raise ValueError(f"camera info K has no valid focal lengths: {K.tolist()}")
    return K


def transform_to_matrix(t) -> np.ndarray:
    """``geometry_msgs/Transform`` (translation, rotation) -> 4x4."""
    from scipy.spatial.transform import Rotation

    q = t.rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [t.translation.x, t.translation.y, t.translation.z]
    return T


def pose_to_matrix(p) -> np.ndarray:
    """``geometry_msgs/Pose`` (position, orientation) -> 4x4."""
    from scipy.spatial.transform import Rotation

    q = p.orientation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [p.position.x, p.position.y, p.position.z]
    return T
