"""Per-instance state for scaled mapper shards (``docker compose up --scale mapper=3``): every
replica mounts the same volume, so each claims a *slot*, a subdirectory ``slot-<n>`` of the
checkpoint directory holding its own checkpoint, journal and incarnation, locked with an
exclusive ``flock`` for as long as the process lives (the lock goes with the process, however
it dies). The slot also names the mapper (``mapper-<n>``), so a re-created container takes
its predecessor's state and id: the same regions, no two writers on one journal. (flock
needs the replicas on one host, as compose's scaling is; across hosts, give each mapper its
own directory and ``cluster.mapper_id``.)

A mapper without slots locks its checkpoint directory itself (``lock_dir``): a second mapper
given the same directory (``docker compose up --scale mapper=3`` without shards) stops at once
with a clear error instead of writing the first one's journal."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

MAX_SLOTS = 64


class Slot:
    def __init__(self, root: Path, n: int, fd: int):
        self.root, self.n, self._fd = root, n, fd

    @property
    def dir(self) -> Path:
        return self.root / f"slot-{self.n}"

    @property
    def mapper_id(self) -> str:
        return f"mapper-{self.n}"

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:  # a node that failed to start holds nothing
        self.release()


def _try_lock(d: Path) -> int | None:
    """``d/lock`` (``d`` created when needed) held with an exclusive flock: its descriptor, or
    None when another process holds it."""
    d.mkdir(parents=True, exist_ok=True)
    fd = os.open(d / "lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def claim(root: str | Path, max_slots: int = MAX_SLOTS) -> Slot:
    """The lowest free slot under ``root`` (created when needed), locked; RuntimeError when all
    ``max_slots`` are taken."""
    root = Path(root)
    for n in range(1, max_slots + 1):
        fd = _try_lock(root / f"slot-{n}")
        if fd is not None:
            return Slot(root, n, fd)
    raise RuntimeError(f"all {max_slots} mapper slots under {root} are taken")


def lock_dir(root: str | Path) -> Slot:
    """The whole checkpoint directory ``root``, locked for one mapper (``root/lock``, released
    with the process); RuntimeError naming the fix when another process holds it."""
    root = Path(root)
    fd = _try_lock(root)
    if fd is None:
        raise RuntimeError(
            f"another mapper holds the checkpoint directory {root}: two mappers must not write one checkpoint "
            "and journal. Give each its own --checkpoint-dir, or run them as shards with a slot each "
            "(cluster.enabled and cluster.slots; in docker compose: AISDF_MAPPER_SHARDS=true)")
    return Slot(root, 0, fd)
