"""Durable mapper state between checkpoints (files in the checkpoint directory).

* ``KeyframeJournal``: the raw payloads of keyframes added to the map since the last
  checkpoint, appended (and fsync'd) before the keyframe is acknowledged, cleared once a
  checkpoint holds them. A restarted mapper replays it, so an acknowledged keyframe is
  never lost, whenever the mapper dies.
* ``Incarnation``: the epoch and the highest map version published, rewritten before
  each publication, so a restarted mapper continues above every version a planner saw.
"""

from __future__ import annotations

import json
import logging
import os
import struct
from pathlib import Path

log = logging.getLogger("aisdf.mapper")
_LEN = struct.Struct("<I")


class KeyframeJournal:
    def __init__(self, path: Path, fsync: bool = True):
        self.path, self.fsync = Path(path), fsync
        self._f = None

    def append(self, payload: bytes) -> None:
        if self._f is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "ab")  # noqa: SIM115 - kept open, closed in close()/clear()
        self._f.write(_LEN.pack(len(payload)) + payload)
        self._f.flush()
        if self.fsync:
            os.fsync(self._f.fileno())

    def read(self) -> list[bytes]:
        """Every complete record; a torn last record (a crash mid-write) is ignored."""
        if not self.path.exists():
            return []
        data = self.path.read_bytes()
        out, i = [], 0
        while i + _LEN.size <= len(data):
            (n,) = _LEN.unpack_from(data, i)
            if i + _LEN.size + n > len(data):
                log.warning("journal %s: ignoring a torn last record", self.path)
                break
            out.append(data[i + _LEN.size:i + _LEN.size + n])
            i += _LEN.size + n
        return out

    def clear(self) -> None:
        self.close()
        if self.path.exists():
            self.path.unlink()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None


class Incarnation:
    def __init__(self, path: Path):
        self.path = Path(path)

    def load(self) -> dict:
        try:
            d = json.loads(self.path.read_text())
            return {"epoch": int(d.get("epoch", 0)), "version": int(d.get("version", 0))}
        except (OSError, ValueError, TypeError, AttributeError):
            return {"epoch": 0, "version": 0}

    def save(self, epoch: int, version: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"epoch": int(epoch), "version": int(version)}))
        tmp.replace(self.path)
