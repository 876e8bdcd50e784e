"""Keyframes and the loss-weighted replay window (isdf-reference.md, "Sampling").

The frontend sends only keyframes, so iSDF's "current frame" and "latest keyframe" are
the newest two keyframes here. Every step trains on those two plus ``window_size - 2``
older keyframes drawn without replacement with probability proportional to their loss
estimate. A keyframe's estimate is the mean per-point loss of its samples the last time
it was in a window (overwritten each time, as iSDF does); a keyframe not yet trained
on has the mean estimate of the others (1.0 when there is none).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import geometry
from ..geometry import decode_depth
from ..structure.surfel_types import FIELDS as SURFEL_FIELDS
from ..structure.surfel_types import Surfels


@dataclass
class Frame:
    """A posed depth keyframe. depth (H, W) float32 metres, 0 = invalid; K (3, 3); T_WC (4, 4)
    camera-to-world; surfels / surfel_mask (H, W) bool are filled by the Atlanta module.

    ``depth_raw`` / ``depth_scale``: the depth as the sensor sent it (``<u2``, metres =
    ``depth_raw / depth_scale``), when it came so (``frame_from_keyframe``). A stored
    keyframe's frame holds only those (``depth`` None) and ``metres()`` decodes them."""

    frame_id: int
    stamp: float
    depth: np.ndarray
    K: np.ndarray
    T_WC: np.ndarray
    surfels: Surfels | None = None
    surfel_mask: np.ndarray | None = None
    sensor: str = "depth"  # with frame_id, the keyframe's identity in a map several robots build
    depth_raw: np.ndarray | None = None
    depth_scale: float | None = None
    # the surfels it gave on directions published after it arrived (the global map's only,
    # not training's: aisdf.structure.process, late surfels), kept to move with a correction
    late_surfels: Surfels | None = None

    @property
    def key(self) -> tuple[str, int]:
        return (self.sensor, int(self.frame_id))

    def metres(self) -> np.ndarray:
        """(H, W) float32 depth in metres: ``depth``, or ``depth_raw`` decoded when only it is held."""
        return self.depth if self.depth is not None else decode_depth(self.depth_raw, self.depth_scale)

    def nbytes(self) -> int:
        """Bytes held by the frame's arrays (depth, raw depth, mask, surfels)."""
        n = sum(a.nbytes for a in (self.depth, self.depth_raw, self.surfel_mask) if a is not None)
        for S in (self.surfels, self.late_surfels):
            if S is not None:
                n += sum(np.asarray(getattr(S, f)).nbytes for f in SURFEL_FIELDS)
        return int(n)

    def to_dict(self) -> dict:
        """Plain types and arrays (for checkpoints)."""
        return {
            "frame_id": int(self.frame_id), "stamp": float(self.stamp),
            "depth": None if self.depth is None else np.asarray(self.depth, np.float32),
            "depth_raw": None if self.depth_raw is None else np.asarray(self.depth_raw, np.uint16),
            "depth_scale": None if self.depth_scale is None else float(self.depth_scale),
            "K": np.asarray(self.K, np.float64),
            "T_WC": np.asarray(self.T_WC, np.float64),
            "surfels": None if self.surfels is None else {f: getattr(self.surfels, f) for f in SURFEL_FIELDS},
            "surfel_mask": None if self.surfel_mask is None else np.asarray(self.surfel_mask, bool),
            "sensor": str(self.sensor),
            "late_surfels": None if self.late_surfels is None else {f: getattr(self.late_surfels, f)
                                                                    for f in SURFEL_FIELDS},
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Frame":
        """``to_dict``'s frame; one held as raw depth comes back with its metres decoded too
        (as it arrived), so ``StoredFrame.make`` stores it raw again."""
        s = d.get("surfels")
        m = d.get("surfel_mask")
        raw, scale = d.get("depth_raw"), d.get("depth_scale")
        if raw is not None:
            raw, scale = np.asarray(raw, np.uint16), float(scale)
        depth = np.asarray(d["depth"], np.float32) if d.get("depth") is not None else decode_depth(raw, scale)
        return cls(
            int(d["frame_id"]), float(d["stamp"]), depth, np.asarray(d["K"], np.float64),
            np.asarray(d["T_WC"], np.float64), None if s is None else Surfels(**s),
            None if m is None else np.asarray(m, bool), str(d.get("sensor", "depth")), raw, scale,
            None if d.get("late_surfels") is None else Surfels(**d["late_surfels"]),  # absent before 1.18
        )


def clean_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """float32 copy with 0 wherever the depth is non-finite, <= 0 or > max_depth."""
    d = np.array(depth, dtype=np.float32)
    d[~geometry.valid_depth(d, max_depth)] = 0.0
    return d


@dataclass
class StoredFrame:
    """A stored frame with what sampling needs: its cleaned depth (normals are computed at
    the sampled pixels, ``geometry.normals_at``) and its surfel mask as packed bits (the
    stored frame holds neither a copy of the depth nor a byte-per-pixel mask).

    The depth is held as it came: float32 metres (``raw``, ``scale`` None), or for a
    keyframe sent as ``<u2`` its raw values (``scale``: metres = raw / scale; half the bytes,
    the same metres to the bit). ``depth`` decodes the whole image; sampling reads ``raw``
    with ``valid()`` and ``depth_at()``, decoding only the pixels it takes."""

    frame: Frame
    raw: np.ndarray
    loss: float | None = None
    # Submaps: rays only from the pixels of ``pixel_mask`` (those whose ray meets the
    # submap; held as packed bits, one per pixel), and samples only where
    # ``region(points, grow) -> bool`` (the submap's box grown by ``grow``).
    pixel_bits: np.ndarray | None = None
    region: object = None
    surfel_bits: np.ndarray | None = None  # ``Frame.surfel_mask``, one bit a pixel (``surfel_mask``)
    scale: float | None = None  # raw depth's scale; None: ``raw`` is metres

    def view(self, pixel_mask: np.ndarray | None, region) -> "StoredFrame":
        """The same keyframe (arrays shared, not copied) for a submap's store."""
        return StoredFrame(self.frame, self.raw, None, _pack(pixel_mask), region, self.surfel_bits, self.scale)

    @property
    def depth(self) -> np.ndarray:
        """(H, W) float32 metres, 0 where invalid (decoded when held raw)."""
        return self.raw if self.scale is None else decode_depth(self.raw, self.scale)

    @property
    def shape(self) -> tuple[int, int]:
        return self.raw.shape

    def valid(self) -> np.ndarray:
        """(H, W) bool: the pixels with a depth."""
        return self.raw > 0

    def depth_at(self, flat: np.ndarray) -> np.ndarray:
        """float32 metres at flat pixel indices (those of ``depth``, decoded alone)."""
        d = self.raw.reshape(-1)[flat]
        return d if self.scale is None else decode_depth(d, self.scale)

    def _unpack(self, bits: np.ndarray | None) -> np.ndarray | None:
        if bits is None:
            return None
        H, W = self.raw.shape
        return np.unpackbits(bits, count=H * W).reshape(H, W).view(bool)

    @property
    def pixel_mask(self) -> np.ndarray | None:
        """(H, W) bool: the pixels a submap's rays may come from (None: all of them)."""
        return self._unpack(self.pixel_bits)

    @property
    def surfel_mask(self) -> np.ndarray | None:
        """(H, W) bool: the frame's surfel pixels (``Frame.surfel_mask``; None: no mask)."""
        return self._unpack(self.surfel_bits)

    def frame_dict(self) -> dict:
        """The frame as ``Frame.to_dict`` gives it (surfel mask unpacked), for checkpoints."""
        d = self.frame.to_dict()
        d["surfel_mask"] = self.surfel_mask
        return d

    @classmethod
    def make(cls, frame: Frame, max_depth: float) -> "StoredFrame":
        """The keyframe of ``frame``: its depth cleaned (``clean_depth``). The
        stored frame is a copy of ``frame`` holding the cleaned depth (one array, not two:
        every reader of a keyframe's depth, checkpoints included, takes 0 as invalid and
        applies the same ``max_depth``); ``frame`` itself is left as it was. A frame that
        came as ``<u2`` (``depth_raw``, which decodes to its ``depth``) is held raw, with 0
        where the cleaned depth is invalid. The surfel mask moves into ``surfel_bits`` (the
        stored frame's ``surfel_mask`` is None)."""
        depth = clean_depth(frame.depth, max_depth)
        if frame.surfel_mask is not None and frame.surfel_mask.shape != depth.shape:
            raise ValueError(f"surfel_mask shape {frame.surfel_mask.shape} != depth shape {depth.shape}")
        bits = _pack(frame.surfel_mask)
        raw, scale = frame.depth_raw, frame.depth_scale
        if (raw is not None and scale is not None and raw.dtype == np.uint16 and raw.shape == depth.shape
                and np.array_equal(decode_depth(raw, scale), np.asarray(frame.depth, np.float32))):
            raw = np.where(depth > 0, raw, np.uint16(0))
            stored = replace(frame, depth=None, depth_raw=raw, depth_scale=float(scale), surfel_mask=None)
            return cls(stored, raw, surfel_bits=bits, scale=float(scale))
        return cls(replace(frame, depth=depth, depth_raw=None, depth_scale=None, surfel_mask=None), depth,
                   surfel_bits=bits)

    def nbytes(self) -> int:
        """Bytes held: the frame's arrays, the depth once when shared, the packed surfel mask."""
        n = self.frame.nbytes() + (0 if self.surfel_bits is None else self.surfel_bits.nbytes)
        shared = self.raw is self.frame.depth or self.raw is self.frame.depth_raw
        return int(n if shared else n + self.raw.nbytes)


def _pack(mask: np.ndarray | None) -> np.ndarray | None:
    return None if mask is None else np.packbits(np.asarray(mask, bool).reshape(-1))


class KeyframeStore:
    """Keyframes in arrival order, their loss estimates, the replay window and the memory bound."""

    def __init__(self, window_size: int = 5, max_keyframes: int = 200, max_depth: float = 12.0):
        self.window_size = window_size
        self.max_keyframes = max_keyframes
        self.max_depth = max_depth
        self.keyframes: list[StoredFrame] = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self.keyframes)

    def add(self, frame: Frame) -> list[int]:
        """Store a frame; returns the frame_ids dropped to respect ``max_keyframes``."""
        return self.add_prepared(StoredFrame.make(frame, self.max_depth))

    def add_prepared(self, kf: StoredFrame) -> list[int]:
        """Store a prepared keyframe (``add``'s, or a submap's view); returns the frame_ids
        dropped to respect ``max_keyframes`` (the lowest loss, never the newest two)."""
        self.keyframes.append(kf)
        dropped = []
        while len(self.keyframes) > self.max_keyframes:
            old = self.keyframes[:-2]
            i = int(np.argmin([self._loss(k) for k in old]))
            dropped.append(self.keyframes.pop(i).frame.frame_id)
            self.dropped += 1
        return dropped

    def _loss(self, kf: StoredFrame) -> float:
        if kf.loss is not None:
            return kf.loss
        known = [k.loss for k in self.keyframes if k.loss is not None]
        return float(np.mean(known)) if known else 1.0

    def losses(self) -> np.ndarray:
        return np.array([self._loss(k) for k in self.keyframes])

    def window(self, rng: np.random.Generator, uniform: int = 0) -> list[int]:
        """Indices into ``keyframes``: [newest, second newest, replayed...] (fewer when fewer are
        stored). Of the replayed, ``uniform`` are drawn uniformly, the rest by loss."""
        n = len(self.keyframes)
        newest = list(range(n - 1, max(n - 3, -1), -1))[: self.window_size]
        n_replay = min(self.window_size - len(newest), n - len(newest))
        if n_replay <= 0:
            return newest
        n_uni = min(uniform, n_replay)
        uni = rng.choice(n - 2, size=n_uni, replace=False) if n_uni else np.zeros(0, np.int64)
        w = np.maximum(self.losses()[: n - 2], 0.0) + 1e-12
        w[uni] = 0.0
        replay = rng.choice(n - 2, size=n_replay - n_uni, replace=False, p=w / w.sum()) if n_replay > n_uni else []
        return newest + [int(i) for i in uni] + [int(i) for i in replay]

    def update_losses(self, indices: list[int], losses: np.ndarray) -> None:
        """Overwrite the loss estimate of each keyframe in the window (NaN = frame had no samples)."""
        for i, v in zip(indices, np.asarray(losses, dtype=np.float64)):
            if np.isfinite(v):
                self.keyframes[i].loss = float(v)
