"""The mapper's state on disk (``services/mapper/main.py``'s ``MapperNode`` mixes it in): the
checkpoint, the keyframe journal written after it, and the incarnation (epoch and version) a
restart resumes above."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from aisdf import protocol
from aisdf.mapper.factory import restore_mapper

log = logging.getLogger("aisdf.mapper")
CHECKPOINT_NAME = "mapper-checkpoint.pt"
JOURNAL_NAME = "mapper-journal.bin"
INCARNATION_NAME = "mapper-incarnation.json"


class CheckpointMixin:
    """Needs the node's ``cfg``, ``pipeline``, ``version``, ``epoch``, ``seen``, ``_seen_ids``,
    ``journal`` and ``incarnation``."""

    def _ckpt_path(self) -> Path | None:
        return Path(self.cfg.checkpoint_dir) / CHECKPOINT_NAME if self.cfg.checkpoint_dir else None

    def _restore(self) -> None:
        """Resume: the checkpoint, then the keyframes journaled after it; a fresh epoch."""
        path = self._ckpt_path()
        last_epoch = 0
        if path is not None and path.exists():
            ck = torch.load(path, map_location="cpu", weights_only=False)
            self.pipeline = restore_mapper(ck["pipeline"])
            self.version = int(ck["version"])
            last_epoch = int(ck.get("epoch", 0))
            if "seen" in ck:
                self.seen = {(str(s), int(i)) for s, i in ck["seen"]}
            else:
                self._seen_ids = {int(i) for _, i in self.pipeline.keyframe_keys()}
            log.info("resumed from %s: version %d, %d steps, %d keyframes", path, self.version, self.pipeline.steps,
                     self.pipeline.n_keyframes)
        if self.incarnation is not None:
            last = self.incarnation.load()
            last_epoch = max(last_epoch, last["epoch"])
            self.version = max(self.version, last["version"])
        self.epoch = max(int(time.time() * 1000), last_epoch + 1)
        if self.incarnation is not None:
            self.incarnation.save(self.epoch, self.version)
        self._replay_journal()
        log.info("epoch %d, next map version %d", self.epoch, self.version + 1)

    def _replay_journal(self) -> None:
        if self.journal is None:
            return
        n = 0
        for payload in self.journal.read():
            try:
                kf = protocol.Keyframe.from_msg(protocol.unpack(payload))
            except protocol.ProtocolError as e:
                log.warning("journal: skipping an unreadable keyframe: %s", e.message)
                continue
            if self.is_seen(kf.sensor, kf.frame_id):
                continue
            try:
                self.pipeline.add_keyframe(kf)
            except ValueError as e:
                log.warning("journal: keyframe %d not added again: %s", kf.frame_id, e)
                continue
            self.seen.add((kf.sensor, kf.frame_id))
            n += 1
        if n:
            log.info("replayed %d keyframes from the journal %s", n, self.journal.path)

    def is_seen(self, sensor: str, frame_id: int) -> bool:
        return (sensor, frame_id) in self.seen or frame_id in self._seen_ids

    def checkpoint(self) -> dict:
        return {"pipeline": self.pipeline.checkpoint(), "version": self.version, "epoch": self.epoch,
                "seen": sorted(self.seen)}

    def save_checkpoint(self) -> None:
        path = self._ckpt_path()
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save(self.checkpoint(), tmp)
        tmp.replace(path)
        if self.journal is not None:
            self.journal.clear()  # the checkpoint holds its keyframes now
