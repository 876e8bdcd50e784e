"""Wire protocol v1, the planners' side: ``query/sdf`` and ``query/mesh`` requests and
replies (docs/protocol.md). The map's messages (keyframes, weights, submaps, surfels, acks)
are :mod:`aisdf.protocol`.

Every decoding problem raises :class:`~aisdf.codec.ProtocolError` (``bad_request`` for
anything malformed); nothing here ever raises anything else on untrusted input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .codec import SDF_SOURCES, VERSION, ProtocolError, _bad, _get, _number, decode_array, encode_array


@dataclass(frozen=True)
class Box:
    """A dense lattice of samples (protocol 1.9): ``shape`` = (nx, ny, nz) samples spaced
    ``resolution`` metres from ``origin`` (the box's lowest corner) along the world axes,
    every sample inside ``[min, min + size]``; sample (i, j, k) is ``origin + resolution *
    (i, j, k)`` and the reply's arrays list them in C order over (i, j, k) (k fastest)."""

    origin: tuple[float, float, float]
    resolution: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, min_corner, size, resolution: float) -> "Box":
        """The lattice of a box ``[min_corner, min_corner + size]`` (size >= 0 on each axis)."""
        lo = np.asarray(min_corner, dtype=np.float64).reshape(3)
        sz = np.asarray(size, dtype=np.float64).reshape(3)
        r = float(resolution)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(sz)) and math.isfinite(r)):
            raise _bad("the box's corner, size and resolution must be finite")
        if r <= 0 or np.any(sz < 0):
            raise _bad(f"a box needs a positive resolution and non-negative sizes, got {r} and {sz.tolist()}")
        with np.errstate(over="ignore"):
            far = lo + sz
        if not np.all(np.isfinite(far)):
            raise _bad("the box's far corner is not finite")
        nf = np.floor(sz / r * (1 + 1e-9) + 1e-6) + 1
        if not np.all(np.isfinite(nf)) or float(np.prod(nf)) > 2**40:
            raise ProtocolError("too_large", f"a box of {nf.tolist()} samples")
        n = nf.astype(np.int64)
        return cls(tuple(float(x) for x in lo), r, tuple(int(x) for x in n))

    @property
    def count(self) -> int:
        return int(np.prod(self.shape))

    def points(self) -> np.ndarray:
        """(count, 3) float64 sample positions, C order over (i, j, k)."""
        axes = [self.origin[a] + self.resolution * np.arange(self.shape[a], dtype=np.float64) for a in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        return g.reshape(-1, 3)

    def to_msg(self) -> dict:
        return {"origin": list(self.origin), "resolution": self.resolution, "shape": list(self.shape)}

    @classmethod
    def request_msg(cls, min_corner, size, resolution: float) -> dict:
        return {"min": [float(x) for x in min_corner], "size": [float(x) for x in size],
                "resolution": float(resolution)}

    @classmethod
    def from_request(cls, obj, max_points: int | None) -> "Box":
        """A request's ``box`` (``{"min", "size", "resolution"}``) -> its lattice."""
        if not isinstance(obj, Mapping):
            raise _bad("'box' must be a map {min: [x, y, z], size: [sx, sy, sz], resolution: r}")
        vals = []
        for name in ("min", "size"):
            v = obj.get(name)
            if (not isinstance(v, (list, tuple)) or len(v) != 3
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
                raise _bad(f"'box.{name}' must be 3 numbers, got {v!r}")
            vals.append(v)
        r = obj.get("resolution")
        if not isinstance(r, (int, float)) or isinstance(r, bool):
            raise _bad(f"'box.resolution' must be a number, got {r!r}")
        box = cls.around(vals[0], vals[1], r)
        if max_points is not None and box.count > max_points:
            raise ProtocolError("too_large", f"a box of {list(box.shape)} = {box.count} samples exceeds this "
                                f"service's limit of {max_points} points; ask for a smaller box or a coarser resolution")
        return box

    @classmethod
    def from_reply(cls, obj) -> "Box":
        if not isinstance(obj, Mapping):
            raise _bad("'box' must be a map")
        try:
            o = [float(x) for x in obj["origin"]]
            r = float(obj["resolution"])
            n = [int(x) for x in obj["shape"]]
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise _bad(f"malformed 'box' in a reply: {e}") from None
        if len(o) != 3 or len(n) != 3 or min(n) < 1:
            raise _bad("a reply's 'box' needs 3 origin values and 3 positive sizes")
        return cls(tuple(o), r, tuple(n))


@dataclass
class SdfRequest:
    points: np.ndarray  # (N, 3) float32 or float64, world frame
    gradient: bool = False
    collision_epsilon: float | None = None
    source: str = "fused"
    # protocol 1.1 (optional; a 1.0 service ignores them):
    radii: np.ndarray | None = None  # (N,) sphere radii: distances are to the sphere's surface
    observed: bool = False  # also answer, per point, whether any keyframe has seen that space
    exact: bool = False  # evaluate the network now instead of the baked field
    unknown: bool = False  # protocol 1.6: also answer each point's distance to unobserved space
    box: Box | None = None  # protocol 1.9: the points are this lattice (sent as the box, not the points)
    fresh: bool = True  # protocol 1.10: False = the bake answers even when it trails (no answer from the newest map)
    predicted: bool = False  # protocol 1.13: also answer, per point, whether the distance rests on a predicted surface

    def to_msg(self) -> dict:
        msg = {"v": VERSION, "gradient": bool(self.gradient), "source": self.source}
        if self.box is not None:
            b = self.box
            size = [b.resolution * (n - 1) for n in b.shape]
            msg["box"] = Box.request_msg(b.origin, size, b.resolution)
        else:
            pts = np.asarray(self.points)
            if pts.dtype != np.float64:
                pts = pts.astype(np.float32)
            msg["points"] = encode_array(pts)
        if self.collision_epsilon is not None:
            msg["collision_epsilon"] = float(self.collision_epsilon)
        if self.radii is not None:
            r = np.asarray(self.radii)
            msg["radii"] = encode_array(r if r.dtype == np.float64 else r.astype(np.float32))
        if self.observed:
            msg["observed"] = True
        if self.exact:
            msg["exact"] = True
        if self.unknown:
            msg["unknown"] = True
        if not self.fresh:
            msg["fresh"] = False
        if self.predicted:
            msg["predicted"] = True
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping, max_points: int | None = None) -> "SdfRequest":
        box = None
        if msg.get("box") is not None:
            if msg.get("points") is not None:
                raise _bad("a request has 'points' or 'box', not both")
            if msg.get("radii") is not None:
                raise _bad("'radii' go with 'points', not with a 'box'")
            box = Box.from_request(msg["box"], max_points)
            points = box.points()
        else:
            pts_obj = msg.get("points")
            if isinstance(pts_obj, Mapping) and max_points is not None:
                shp = pts_obj.get("shape")
                if isinstance(shp, (list, tuple)) and shp and isinstance(shp[0], int) and shp[0] > max_points:
                    raise ProtocolError("too_large", f"{shp[0]} points exceed this service's limit of {max_points}")
            points = decode_array(pts_obj, "points", ("<f4", "<f8"), (None, 3))
            if not np.all(np.isfinite(points)):
                raise _bad("points contain non-finite values")
        gradient = _get(msg, "gradient", bool, False, "a boolean")
        eps = _number(msg, "collision_epsilon", None)
        if eps is not None and eps <= 0:
            raise _bad(f"'collision_epsilon' must be positive, got {eps}")
        source = _get(msg, "source", str, "fused", "a string")
        if source not in SDF_SOURCES:
            raise _bad(f"'source' must be one of {list(SDF_SOURCES)}, got {source!r}")
        radii = None
        if msg.get("radii") is not None:
            radii = decode_array(msg.get("radii"), "radii", ("<f4", "<f8"), (len(points),))
            if not np.all(np.isfinite(radii)) or (len(radii) and radii.min() < 0):
                raise _bad("'radii' must be finite and non-negative")
        observed = _get(msg, "observed", bool, False, "a boolean")
        exact = _get(msg, "exact", bool, False, "a boolean")
        unknown = _get(msg, "unknown", bool, False, "a boolean")
        fresh = _get(msg, "fresh", bool, True, "a boolean")
        predicted = _get(msg, "predicted", bool, False, "a boolean")
        return cls(points, gradient, eps, source, radii, observed, exact, unknown, box, fresh, predicted)


@dataclass
class SdfReply:
    map_version: int
    sdf: np.ndarray
    gradient: np.ndarray | None = None
    collision: np.ndarray | None = None
    # protocol 1.1 / 1.2 (a 1.0 client ignores them):
    observed: np.ndarray | None = None  # (N,) bool, when asked
    baked: bool = False  # True when the baked field answered (points outside it: the network of the same map)
    map_epoch: int = 0  # the mapper incarnation of map_version (1.2)
    unknown: np.ndarray | None = None  # (N,) metres to unobserved space, when asked (1.6)
    map_age_s: float | None = None  # seconds since the map state behind the values arrived (1.7)
    box: Box | None = None  # the request's lattice (1.9); the arrays are its samples in C order
    predicted: np.ndarray | None = None  # (N,) bool, when asked (1.13): the distance is to a predicted surface
    surfel_version: int | None = None  # the surfel map behind the values (1.19; -1: none; None: not said)

    def grid(self, name: str = "sdf") -> np.ndarray:
        """A box reply's array as a grid: (nx, ny, nz) (gradient: (nx, ny, nz, 3))."""
        if self.box is None:
            raise ValueError("not the reply to a box request")
        a = getattr(self, name)
        return None if a is None else a.reshape(*self.box.shape, *a.shape[1:])

    def to_msg(self) -> dict:
        msg = {"v": VERSION, "map_version": int(self.map_version), "sdf": encode_array(self.sdf, "<f4"),
               "map_epoch": int(self.map_epoch), "baked": bool(self.baked)}
        if self.gradient is not None:
            msg["gradient"] = encode_array(self.gradient, "<f4")
        if self.collision is not None:
            msg["collision"] = encode_array(self.collision, "<f4")
        if self.observed is not None:
            msg["observed"] = encode_array(np.asarray(self.observed, dtype=np.uint8), "|u1")
        if self.unknown is not None:
            msg["unknown"] = encode_array(self.unknown, "<f4")
        if self.map_age_s is not None:
            msg["map_age_s"] = float(self.map_age_s)
        if self.box is not None:
            msg["box"] = self.box.to_msg()
        if self.predicted is not None:
            msg["predicted"] = encode_array(np.asarray(self.predicted, dtype=np.uint8), "|u1")
        if self.surfel_version is not None:
            msg["surfel_version"] = int(self.surfel_version)
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "SdfReply":
        mv = _get(msg, "map_version", int, what="an integer")
        sdf = decode_array(msg.get("sdf"), "sdf", ("<f4",), (None,))
        n = len(sdf)
        grad = decode_array(msg["gradient"], "gradient", ("<f4",), (n, 3)) if "gradient" in msg else None
        coll = decode_array(msg["collision"], "collision", ("<f4",), (n,)) if "collision" in msg else None
        obs = decode_array(msg["observed"], "observed", ("|u1",), (n,)).astype(bool) if "observed" in msg else None
        baked = _get(msg, "baked", bool, False, "a boolean")
        epoch = _get(msg, "map_epoch", int, 0, "an integer")
        unk = decode_array(msg["unknown"], "unknown", ("<f4",), (n,)) if "unknown" in msg else None
        age = _get(msg, "map_age_s", (int, float), None, "a number") if "map_age_s" in msg else None
        box = Box.from_reply(msg["box"]) if msg.get("box") is not None else None
        if box is not None and box.count != n:
            raise _bad(f"a reply's box of {list(box.shape)} samples carries {n} distances")
        pred = (decode_array(msg["predicted"], "predicted", ("|u1",), (n,)).astype(bool) if "predicted" in msg
                else None)
        sv = _get(msg, "surfel_version", int, None, "an integer") if "surfel_version" in msg else None
        return cls(mv, sdf, grad, coll, obs, baked, epoch, unk, None if age is None else float(age), box, pred, sv)


@dataclass
class MeshRequest:
    resolution: float | None = None

    def to_msg(self) -> dict:
        msg = {"v": VERSION}
        if self.resolution is not None:
            msg["resolution"] = float(self.resolution)
        return msg

    @classmethod
    def from_msg(cls, msg: Mapping) -> "MeshRequest":
        res = _number(msg, "resolution", None)
        if res is not None and res <= 0:
            raise _bad(f"'resolution' must be positive, got {res}")
        return cls(res)


@dataclass
class MeshReply:
    map_version: int
    vertices: np.ndarray
    faces: np.ndarray

    def to_msg(self) -> dict:
        return {
            "v": VERSION,
            "map_version": int(self.map_version),
            "vertices": encode_array(np.asarray(self.vertices).reshape(-1, 3), "<f4"),
            "faces": encode_array(np.asarray(self.faces).reshape(-1, 3), "<i4"),
        }

    @classmethod
    def from_msg(cls, msg: Mapping) -> "MeshReply":
        mv = _get(msg, "map_version", int, what="an integer")
        v = decode_array(msg.get("vertices"), "vertices", ("<f4",), (None, 3))
        f = decode_array(msg.get("faces"), "faces", ("<i4",), (None, 3))
        return cls(mv, v, f)
