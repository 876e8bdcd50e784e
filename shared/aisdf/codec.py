"""Wire protocol v1, the envelope (protocol.md, "Encoding"): one MessagePack map per
payload with ``"v": 1``, arrays as ``{"dtype", "shape", "data"}`` maps, typed field
access and error replies. Every decoding problem raises :class:`ProtocolError`
(``bad_request`` for anything malformed). The messages are in ``protocol.py``.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

import msgpack
import numpy as np

VERSION = 1
ENCODING = "application/msgpack"
ERROR_CODES = ("bad_request", "too_large", "no_map", "internal", "busy")  # busy: protocol 1.1
SDF_SOURCES = ("fused", "implicit", "explicit")
# numpy dtype strings with explicit byte order that the protocol allows.
ALLOWED_DTYPES = ("<f4", "<f8", "<u2", "<i4", "<i8", "|u1")


class ProtocolError(Exception):
    """A protocol-level error with its wire code (``bad_request``, ``too_large``, ...)."""

    def __init__(self, code: str, message: str):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def _bad(message: str) -> ProtocolError:
    return ProtocolError("bad_request", message)


# ----------------------------------------------------------------------------- arrays


def encode_array(a: np.ndarray, dtype: str | None = None) -> dict:
    """Encode an array as a protocol array map (C order, explicit byte order)."""
    arr = np.asarray(a)
    if dtype is not None:
        arr = arr.astype(np.dtype(dtype), copy=False)
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder not in ("|", "<") else arr.dtype
    if dt.str not in ALLOWED_DTYPES:
        raise ValueError(f"dtype {arr.dtype} is not a protocol dtype {ALLOWED_DTYPES}")
    arr = np.ascontiguousarray(arr, dtype=dt)
    return {"dtype": dt.str, "shape": [int(s) for s in arr.shape], "data": arr.tobytes()}


def decode_array(
    obj: Any,
    name: str,
    dtypes: Iterable[str] = ALLOWED_DTYPES,
    shape: tuple[int | None, ...] | None = None,
) -> np.ndarray:
    """Decode and check a protocol array map; ``shape`` entries of None match any size."""
    if not isinstance(obj, Mapping):
        raise _bad(f"'{name}' must be an array map {{dtype, shape, data}}, got {type(obj).__name__}")
    for k in ("dtype", "shape", "data"):
        if k not in obj:
            raise _bad(f"'{name}' array is missing '{k}'")
    dtype, shp, data = obj["dtype"], obj["shape"], obj["data"]
    dtypes = tuple(dtypes)
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise _bad(f"'{name}' dtype {dtype!r} is not one of {list(ALLOWED_DTYPES)}")
    if dtype not in dtypes:
        raise _bad(f"'{name}' dtype {dtype!r} not accepted here; expected one of {list(dtypes)}")
    if not isinstance(shp, (list, tuple)) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shp
    ):
        raise _bad(f"'{name}' shape must be a list of non-negative integers, got {shp!r}")
    if not isinstance(data, (bytes, bytearray)):
        raise _bad(f"'{name}' data must be binary, got {type(data).__name__}")
    dt = np.dtype(dtype)
    n = math.prod(shp) if shp else 1
    if len(data) != n * dt.itemsize:
        raise _bad(f"'{name}' data has {len(data)} bytes, shape {list(shp)} of {dtype} needs {n * dt.itemsize}")
    if shape is not None:
        if len(shp) != len(shape) or any(e is not None and e != s for e, s in zip(shape, shp)):
            want = "x".join("N" if e is None else str(e) for e in shape)
            raise _bad(f"'{name}' must have shape {want}, got {list(shp)}")
    return np.frombuffer(bytes(data), dtype=dt).reshape(shp)


# ----------------------------------------------------------------------------- maps


def pack(msg: Mapping[str, Any]) -> bytes:
    """Serialise a message map (adds ``"v": 1`` when missing)."""
    m = dict(msg)
    m.setdefault("v", VERSION)
    return msgpack.packb(m, use_bin_type=True)


def unpack(payload: bytes | bytearray | memoryview | None) -> dict:
    """Parse a payload into a message map and check its version."""
    if payload is None or len(payload) == 0:
        raise _bad("empty payload: expected a MessagePack map")
    try:
        msg = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
    except Exception as e:  # msgpack raises several unrelated types
        raise _bad(f"payload is not valid MessagePack: {e}") from None
    if not isinstance(msg, dict):
        raise _bad(f"payload must be a MessagePack map, got {type(msg).__name__}")
    if "v" not in msg:
        raise _bad("message has no protocol version 'v'")
    v = msg["v"]
    if not isinstance(v, int) or isinstance(v, bool):
        raise _bad(f"'v' must be an integer, got {v!r}")
    if v != VERSION:
        raise _bad(f"unsupported protocol major version {v}; this service speaks v{VERSION}")
    return msg


def _get(msg: Mapping, name: str, types: type | tuple, default: Any = ..., what: str = "") -> Any:
    if name not in msg:
        if default is ...:
            raise _bad(f"missing field '{name}'")
        return default
    val = msg[name]
    if isinstance(val, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise _bad(f"'{name}' must be {what or types}, got a boolean")
    if not isinstance(val, types):
        raise _bad(f"'{name}' must be {what or types}, got {type(val).__name__}")
    return val


def _number(msg: Mapping, name: str, default: Any = ...) -> float:
    val = _get(msg, name, (int, float), default, "a number")
    if val is None:
        return val
    val = float(val)
    if not math.isfinite(val):
        raise _bad(f"'{name}' must be finite, got {val}")
    return val


def error_message(code: str, message: str) -> dict:
    if code not in ERROR_CODES:
        raise ValueError(f"unknown error code {code!r}")
    return {"v": VERSION, "error": code, "message": str(message)}


def decode_error(payload: bytes) -> ProtocolError:
    """Turn an error reply's payload into a ProtocolError (``internal`` if unreadable)."""
    try:
        msg = unpack(payload)
        code = msg.get("error")
        return ProtocolError(code if code in ERROR_CODES else "internal", str(msg.get("message", "")))
    except ProtocolError as e:
        return ProtocolError("internal", f"unreadable error reply: {e.message}")


# ----------------------------------------------------------------------------- geometry checks


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """True for a finite 4x4 homogeneous rigid transform (rotation with det +1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(T[3], [0, 0, 0, 1], atol=tol)
        and np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
    )
