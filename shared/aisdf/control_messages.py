"""Wire protocol v1 (docs/protocol.md), the mapper's control messages: keyframe
acknowledgements (1.2, ``keyframes/ack``) and pose corrections (1.11: ``PoseCorrections`` ->
``PosesApplied`` on ``control/mapper/poses``). Re-exported by :mod:`aisdf.protocol`, the public
entry point. Every decoding problem raises :class:`aisdf.codec.ProtocolError`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from .codec import VERSION, ProtocolError, _bad, _get, _number, decode_array, encode_array, is_rigid


def _int_list(msg: Mapping, name: str) -> list[int]:
    vals = _get(msg, name, (list, tuple), [], "a list of integers")
    if not all(isinstance(x, int) and not isinstance(x, bool) for x in vals):
        raise _bad(f"'{name}' must be a list of integers")
    return [int(x) for x in vals]


@dataclass
class KeyframeAck:
    """Mapper -> front ends on ``keyframes/ack`` (protocol 1.2). The keyframes ``frame_ids``
    of ``sensor`` are in the map (added now or before: a resend is acknowledged again and
    not added twice) and, with a checkpoint directory, on disk; ``rejected`` ones were
    refused for good (invalid). Neither is worth resending. A keyframe the mapper dropped
    from its queue is not acknowledged. ``epoch`` is the mapper incarnation's."""

    epoch: int
    sensor: str
    frame_ids: list[int] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)

    def to_msg(self) -> dict:
        return {"v": VERSION, "epoch": int(self.epoch), "sensor": self.sensor,
                "frame_ids": [int(i) for i in self.frame_ids], "rejected": [int(i) for i in self.rejected]}

    @classmethod
    def from_msg(cls, msg: Mapping) -> "KeyframeAck":
        epoch = _get(msg, "epoch", int, 0, "an integer")
        sensor = _get(msg, "sensor", str, "depth", "a string")
        return cls(epoch, sensor, _int_list(msg, "frame_ids"), _int_list(msg, "rejected"))


MAX_POSE_CORRECTIONS = 100_000  # keyframes one PoseCorrections may re-pose (12.8 MB of poses)


@dataclass
class PoseCorrections:
    """Protocol 1.11 (``control/mapper/poses``, a get): new camera-to-world poses ``T_WC``
    (N, 4, 4) for the keyframes ``frame_ids`` (N,) of ``sensor`` already sent, e.g. after a
    SLAM system's loop closure. Validated as a whole: a malformed request changes nothing."""

    sensor: str
    frame_ids: list[int]
    T_WC: np.ndarray  # (N, 4, 4) float64

    def to_msg(self) -> dict:
        return {"v": VERSION, "sensor": self.sensor, "frame_ids": [int(i) for i in self.frame_ids],
                "T_WC": encode_array(np.asarray(self.T_WC, np.float64).reshape(-1, 4, 4), "<f8")}

    def as_dict(self) -> dict[int, np.ndarray]:
        return {int(i): self.T_WC[k] for k, i in enumerate(self.frame_ids)}

    @classmethod
    def from_msg(cls, msg: Mapping) -> "PoseCorrections":
        """Decode and check: ``sensor`` a string, ``frame_ids`` distinct integers, ``T_WC``
        an Nx4x4 ``<f8`` array of rigid transforms, one per id, at most ``MAX_POSE_CORRECTIONS``."""
        sensor = _get(msg, "sensor", str, "depth", "a string")
        if "frame_ids" not in msg:
            raise _bad("missing field 'frame_ids'")
        ids = _int_list(msg, "frame_ids")
        if len(ids) > MAX_POSE_CORRECTIONS:
            raise ProtocolError("too_large", f"{len(ids)} poses in one request; at most {MAX_POSE_CORRECTIONS}")
        if len(set(ids)) != len(ids):
            dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
            raise _bad(f"'frame_ids' must be distinct; repeated: {dup}")
        T = decode_array(msg.get("T_WC"), "T_WC", ("<f8",), (None, 4, 4))
        if len(T) != len(ids):
            raise _bad(f"'T_WC' holds {len(T)} poses for {len(ids)} frame ids")
        for k, i in enumerate(ids):
            if not is_rigid(T[k]):
                raise _bad(f"T_WC of frame {i} is not a rigid 4x4 camera-to-world transform")
        return cls(sensor, ids, T.copy())


@dataclass
class PosesApplied:
    """The mapper's reply to a PoseCorrections (protocol 1.11): ``reposed`` keyframes of
    ``sensor`` moved to their new pose (the map that carries them is ``version`` in ``epoch``);
    ``unknown``: frame ids the map does not hold (never sent, not stored because they added
    nothing new, evicted), left as they are; ``unchanged``: ids already at the pose sent;
    ``submaps``: submaps retrained (0 for one network); ``seconds``: the mapper's time."""

    sensor: str
    reposed: int
    unknown: list[int]
    unchanged: int = 0
    submaps: int = 0
    version: int = 0
    epoch: int = 0
    seconds: float = 0.0

    def to_msg(self) -> dict:
        return {"v": VERSION, "sensor": self.sensor, "reposed": int(self.reposed),
                "unknown": [int(i) for i in self.unknown], "unchanged": int(self.unchanged),
                "submaps": int(self.submaps), "version": int(self.version), "epoch": int(self.epoch),
                "seconds": float(self.seconds)}

    @classmethod
    def from_msg(cls, msg: Mapping) -> "PosesApplied":
        return cls(_get(msg, "sensor", str, "depth", "a string"), _get(msg, "reposed", int, what="an integer"),
                   _int_list(msg, "unknown"), _get(msg, "unchanged", int, 0, "an integer"),
                   _get(msg, "submaps", int, 0, "an integer"), _get(msg, "version", int, 0, "an integer"),
                   _get(msg, "epoch", int, 0, "an integer"), _number(msg, "seconds", 0.0))
