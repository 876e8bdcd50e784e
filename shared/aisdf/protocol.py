"""Wire protocol v1 (docs/protocol.md), the map's side: keyframes, acknowledgements, weight
snapshots, submap indexes, surfel maps and pose corrections (1.11: ``PoseCorrections`` ->
``PosesApplied`` on ``control/mapper/poses``; the acknowledgements and corrections are
:mod:`aisdf.control_messages`, re-exported here), one MessagePack map per payload, arrays as
``{"dtype", "shape", "data"}`` maps (``codec``, whose ``pack``/``unpack`` and errors are
re-exported here). Pure: bytes in, typed messages out. The planners' requests and replies
(``SdfRequest``, ``SdfReply``, ``MeshRequest``, ``MeshReply``) are :mod:`aisdf.query_messages`.

Every decoding problem raises :class:`ProtocolError` with a protocol error code
(``bad_request`` for anything malformed); nothing here ever raises anything else on
untrusted input.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from .codec import (  # noqa: F401 - re-exported: protocol is the public entry point
    ALLOWED_DTYPES,
    ENCODING,
    ERROR_CODES,
    SDF_SOURCES,
    VERSION,
    ProtocolError,
    _bad,
    _get,
    _number,
    decode_array,
    decode_error,
    encode_array,
    error_message,
    is_rigid,
    pack,
    unpack,
)
from .control_messages import (  # noqa: F401 - re-exported
    MAX_POSE_CORRECTIONS,
    KeyframeAck,
    PoseCorrections,
    PosesApplied,
)
from .geometry import decode_depth


# ----------------------------------------------------------------------------- messages


@dataclass
class Keyframe:
    """A posed depth image. ``depth`` is as sent (``<u2`` raw or ``<f4`` metres). ``mask``
    (1.10, optional): (H, W) uint8, 1 = a pixel to ignore (a dynamic object), treated as
    no measurement; None = nothing masked."""

    frame_id: int
    stamp: float
    depth: np.ndarray
    K: np.ndarray
    T_WC: np.ndarray
    depth_scale: float | None = None
    sensor: str = "depth"
    mask: np.ndarray | None = None

    def depth_m(self) -> np.ndarray:
        """Depth in metres as float32 (H, W); 0 where there is no measurement or ``mask`` is 1."""
        if self.depth.dtype == np.uint16:
            d = decode_depth(self.depth, self.depth_scale)
        else:
            d = self.depth.astype(np.float32, copy=True)
            d[~np.isfinite(d)] = 0.0
        d[d < 0] = 0.0
        if self.mask is not None:
            d[self.mask.astype(bool)] = 0.0
        return d

    def to_msg(self) -> dict:
        msg = {
            "v": VERSION,
            "frame_id": int(self.frame_id),
            "stamp": float(self.stamp),
            "depth": encode_array(self.depth),
            "K": encode_array(self.K, "<f8"),
            "T_WC": encode_array(self.T_WC, "<f8"),
            "sensor": self.sensor,
        }
        if self.depth.dtype == np.uint16:
            msg["depth_scale"] = float(self.depth_scale)
        if self.mask is not None:
            msg["mask"] = encode_array(self.mask, "|u1")
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "Keyframe":
        """Decode and validate: dtype, depth shape against K, finite values, rigid pose, the
        mask's dtype, shape (the depth's) and values (0 or 1)."""
        frame_id = _get(msg, "frame_id", int, what="an integer")
        stamp = _number(msg, "stamp")
        depth = decode_array(msg.get("depth"), "depth", ("<u2", "<f4"), (None, None))
        H, W = depth.shape
        if H < 2 or W < 2:
            raise _bad(f"depth image {H}x{W} is too small")
        depth_scale = None
        if depth.dtype == np.uint16:
            depth_scale = _number(msg, "depth_scale")
            if depth_scale <= 0:
                raise _bad(f"'depth_scale' must be positive, got {depth_scale}")
        else:
            fin = depth[np.isfinite(depth)]
            if fin.size and fin.min() < 0:
                raise _bad("depth has negative values")
        K = decode_array(msg.get("K"), "K", ("<f8",), (3, 3))
        if not np.all(np.isfinite(K)):
            raise _bad("K has non-finite values")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if fx <= 0 or fy <= 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise _bad(f"K is not a pinhole intrinsic matrix: {K.tolist()}")
        # The principal point must fall within (a margin around) the image.
        if not (-0.5 * W <= cx <= 1.5 * W and -0.5 * H <= cy <= 1.5 * H):
            raise _bad(f"depth shape {H}x{W} does not match K (principal point {cx:.1f},{cy:.1f})")
        T_WC = decode_array(msg.get("T_WC"), "T_WC", ("<f8",), (4, 4))
        if not is_rigid(T_WC):
            raise _bad("T_WC is not a rigid 4x4 camera-to-world transform")
        sensor = _get(msg, "sensor", str, "depth", "a string")
        mask = None
        if msg.get("mask") is not None:  # 1.10: pixels to ignore, the depth's shape
            mask = decode_array(msg["mask"], "mask", ("|u1",))
            if mask.shape != (H, W):
                raise _bad(f"'mask' shape {list(mask.shape)} does not match depth's {[H, W]}")
            if mask.size and mask.max() > 1:
                raise _bad("'mask' values must be 0 (keep) or 1 (ignore)")
            mask = mask.copy()
        return cls(frame_id, stamp, depth.copy(), K.copy(), T_WC.copy(), depth_scale, sensor, mask)


@dataclass
class WeightSnapshot:
    version: int
    step: int
    stamp: float
    model: dict
    state: dict[str, np.ndarray]
    epoch: int = 0  # protocol 1.2: the mapper incarnation; maps order by (epoch, version)
    observed: dict | None = None  # protocol 1.1: the observed-space grid (aisdf.observed)
    submap: dict | None = None  # protocol 1.3: {"id": "i_j_k", "grid": SubmapGrid message} (map/submaps/<id>)
    measured: dict | None = None  # protocol 1.4: {"voxel": float, "points": (M, 3) float32} (measured_msg)

    def to_msg(self) -> dict:
        msg = {
            "v": VERSION,
            "version": int(self.version),
            "step": int(self.step),
            "stamp": float(self.stamp),
            "model": self.model,
            "state": {k: encode_array(np.asarray(v, dtype=np.float32)) for k, v in self.state.items()},
        }
        if self.epoch:
            msg["epoch"] = int(self.epoch)
        if self.observed is not None:
            msg["observed"] = self.observed
        if self.submap is not None:
            msg["submap"] = self.submap
        if self.measured is not None:
            msg["measured"] = {"voxel": float(self.measured["voxel"]),
                               "points": encode_array(np.asarray(self.measured["points"], np.float32))}
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "WeightSnapshot":
        version = _get(msg, "version", int, what="an integer")
        step = _get(msg, "step", int, what="an integer")
        stamp = _number(msg, "stamp")
        model = _get(msg, "model", dict, what="a map")
        state_raw = _get(msg, "state", dict, what="a map")
        state = {}
        for k, v in state_raw.items():
            if not isinstance(k, str):
                raise _bad("state keys must be strings")
            state[k] = decode_array(v, f"state.{k}", ("<f4", "<f8"))
        epoch = _get(msg, "epoch", int, 0, "an integer")
        observed = _get(msg, "observed", dict, None, "a map")
        submap = _get(msg, "submap", dict, None, "a map")
        if submap is not None:
            _submap_header(submap)
        measured = _get(msg, "measured", dict, None, "a map")
        if measured is not None:
            measured = _measured(measured)
        return cls(version, step, stamp, model, state, epoch, observed, submap, measured)


def _measured(m: Mapping) -> dict:
    """Validate a snapshot's ``measured`` map (1.4): {"voxel": float, "points": (M, 3) float32}."""
    voxel = _number(m, "voxel")
    if not voxel > 0:
        raise _bad(f"'measured.voxel' must be positive, got {voxel}")
    pts = decode_array(m.get("points"), "measured.points", ("<f4",), (None, 3))
    if not np.all(np.isfinite(pts)):
        raise _bad("'measured.points' has non-finite values")
    return {"voxel": voxel, "points": pts}


def _submap_header(m: Mapping) -> tuple[str, "object"]:
    """Validate a snapshot's ``submap`` map: (id, SubmapGrid)."""
    from .submaps.grid import SubmapGrid, parse_cell_id

    sid = _get(m, "id", str, what="a string")
    try:
        parse_cell_id(sid)
        grid = SubmapGrid.from_msg(_get(m, "grid", dict, what="a map"))
    except ValueError as e:
        raise _bad(str(e)) from None
    return sid, grid


@dataclass
class SubmapIndex:
    """Protocol 1.3 (``map/index``): the submap grid and, per submap id, the map version of
    its newest snapshot on ``map/submaps/<id>`` and its training steps."""

    version: int
    stamp: float
    grid: dict
    submaps: dict[str, dict]
    epoch: int = 0

    def to_msg(self) -> dict:
        msg = {"v": VERSION, "version": int(self.version), "stamp": float(self.stamp), "grid": self.grid,
               "submaps": {k: {"version": int(v["version"]), "step": int(v.get("step", 0))}
                           for k, v in self.submaps.items()}}
        if self.epoch:
            msg["epoch"] = int(self.epoch)
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "SubmapIndex":
        from .submaps.grid import SubmapGrid, parse_cell_id

        version = _get(msg, "version", int, what="an integer")
        stamp = _number(msg, "stamp")
        grid = _get(msg, "grid", dict, what="a map")
        try:
            SubmapGrid.from_msg(grid)
        except ValueError as e:
            raise _bad(str(e)) from None
        raw = _get(msg, "submaps", dict, what="a map")
        submaps = {}
        for k, v in raw.items():
            if not isinstance(k, str) or not isinstance(v, dict):
                raise _bad("submaps must map 'i_j_k' ids to maps")
            try:
                parse_cell_id(k)
            except ValueError as e:
                raise _bad(str(e)) from None
            submaps[k] = {"version": _get(v, "version", int, what="an integer"), "step": _get(v, "step", int, 0, "an integer")}
        epoch = _get(msg, "epoch", int, 0, "an integer")
        return cls(version, stamp, grid, submaps, epoch)


SURFEL_FIELDS = {
    "center": ("<f4", (None, 3)),
    "normal": ("<f4", (None, 3)),
    "axis1": ("<f4", (None, 3)),
    "axis2": ("<f4", (None, 3)),
    "extent": ("<f4", (None, 2)),
    "direction": ("<i4", (None,)),
    "keyframe": ("<i8", (None,)),
}


@dataclass
class SurfelMap:
    """The explicit planar map: the Atlanta frame and N rectangular surfels."""

    version: int
    stamp: float
    vertical: np.ndarray  # (3,)
    horizontal: np.ndarray  # (M, 3)
    surfels: dict[str, np.ndarray] = field(default_factory=dict)
    epoch: int = 0  # protocol 1.2: the mapper incarnation; maps order by (epoch, version)

    @staticmethod
    def empty_surfels() -> dict[str, np.ndarray]:
        return {
            k: np.zeros((0,) + tuple(s for s in shp[1:]), dtype=np.dtype(dt))
            for k, (dt, shp) in SURFEL_FIELDS.items()
        }

    def __len__(self) -> int:
        return int(len(self.surfels.get("center", ())))

    def to_msg(self) -> dict:
        surfels = self.surfels or self.empty_surfels()
        msg = {
            "v": VERSION,
            "version": int(self.version),
            "stamp": float(self.stamp),
            "atlanta": {
                "vertical": encode_array(self.vertical, "<f8"),
                "horizontal": encode_array(np.asarray(self.horizontal).reshape(-1, 3), "<f8"),
            },
            "surfels": {k: encode_array(surfels[k], dt) for k, (dt, _) in SURFEL_FIELDS.items()},
        }
        if self.epoch:
            msg["epoch"] = int(self.epoch)
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "SurfelMap":
        version = _get(msg, "version", int, what="an integer")
        stamp = _number(msg, "stamp")
        atl = _get(msg, "atlanta", dict, what="a map")
        vertical = decode_array(atl.get("vertical"), "atlanta.vertical", ("<f8",), (3,))
        horizontal = decode_array(atl.get("horizontal"), "atlanta.horizontal", ("<f8",), (None, 3))
        raw = _get(msg, "surfels", dict, what="a map")
        surfels = {
            k: decode_array(raw.get(k), f"surfels.{k}", (dt,), shp) for k, (dt, shp) in SURFEL_FIELDS.items()
        }
        n = {len(v) for v in surfels.values()}
        if len(n) != 1:
            raise _bad("surfel arrays have different lengths")
        epoch = _get(msg, "epoch", int, 0, "an integer")
        return cls(version, stamp, vertical.copy(), horizontal.copy(), {k: v.copy() for k, v in surfels.items()},
                   epoch)
