"""The frontend's outbox: keyframes selected but not yet acknowledged by a mapper
(protocol 1.2, ``keyframes/ack``). Pure: no Zenoh, no threads; the caller locks.

* While no mapper is there, nothing is sent; at most ``hold_max`` keyframes are held and
  beyond that the oldest is dropped (logged, counted).
* With a mapper, at most ``window`` keyframes are in flight (sent, not acknowledged), so
  one frontend never overflows the mapper's queue; one unacknowledged for
  ``resend_period_s`` is sent again. When a mapper (re)appears, everything in flight is
  sent again at once: the mapper acknowledges a keyframe it already has without adding it
  twice.
* An acknowledgement (in the map, or rejected for good) removes a keyframe. With mapper
  shards (protocol 1.14) acknowledgements name their mapper and the regions it holds the
  keyframe for: a keyframe goes once every live owner it needs has acknowledged it
  (``aisdf.cluster.ownership.satisfied``; ranks 1 and 2 of every region it touches) and is
  resent until then; one without a mapper id (a 1.11 mapper) removes it at once, as before.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Callable

from aisdf.cluster import ownership

log = logging.getLogger("aisdf.frontend")


@dataclass
class _Held:
    payload: bytes
    sent_at: float | None = None  # None: not in flight (never sent, or to send again now)
    sends: int = 0
    touched: list | None = None  # 1.14: the regions it touches, as a shard said (None: not known)
    acks: dict = field(default_factory=dict)  # 1.14: mapper id -> regions held for (a set, or ownership.ALL)


class KeyframeOutbox:
    def __init__(self, hold_max: int = 128, window: int = 8, resend_period_s: float = 3.0,
                 clock: Callable[[], float] = time.monotonic):
        self.hold_max, self.window, self.resend_period_s, self.clock = hold_max, window, resend_period_s, clock
        self.items: collections.OrderedDict[int, _Held] = collections.OrderedDict()  # frame_id -> held, oldest first
        self.mapper_present = False
        self.members: frozenset[str] = frozenset()  # 1.14: live mapper ids (their liveliness tokens)
        self.replicas = 2  # owners per region a keyframe needs
        self.counts = {"sent": 0, "resent": 0, "acked": 0, "rejected": 0, "dropped": 0}

    @property
    def pending(self) -> int:
        """Keyframes held or in flight: not acknowledged yet."""
        return len(self.items)

    def add(self, frame_id: int, payload: bytes) -> None:
        self.items.pop(frame_id, None)  # the same id again (a looping source): the newest wins
        self.items[frame_id] = _Held(payload)
        while len(self.items) > self.hold_max:
            fid, held = self.items.popitem(last=False)
            self.counts["dropped"] += 1
            log.warning("dropped keyframe %d unacknowledged (%s): %d held is the limit (dropped so far: %d)",
                        fid, "sent, no ack" if held.sends else "never sent, no mapper" if not self.mapper_present
                        else "never sent", self.hold_max, self.counts["dropped"])

    def ack(self, frame_ids, rejected=(), mapper: str = ownership.LEGACY, touched=None, held=None) -> int:
        """Record acknowledgements; remove the keyframes now safely in the map (every needed
        owner acknowledged) or rejected; returns how many were removed. ``mapper``, ``touched``
        and ``held`` (1.14, parallel to ``frame_ids``): the acknowledging shard, the regions each
        keyframe touches (None: not known) and those it holds it for (``ownership.ALL``: all)."""
        n = 0
        for k, fid in enumerate(frame_ids):
            item = self.items.get(int(fid))
            if item is None:
                continue
            h = ownership.ALL if held is None or held[k] == ownership.ALL else set(held[k])
            item.acks[mapper] = h
            if touched is not None and touched[k] is not None:
                item.touched = list(touched[k])
            if self._done(item):
                del self.items[int(fid)]
                self.counts["acked"] += 1
                n += 1
        for fid in rejected:
            if self.items.pop(int(fid), None) is not None:
                self.counts["rejected"] += 1
                n += 1
                log.warning("the mapper rejected keyframe %d", fid)
        return n

    def _done(self, item: _Held) -> bool:
        members = self.members if self.members else frozenset(m for m in item.acks)
        return ownership.satisfied(item.touched, item.acks, members, self.replicas)

    def set_members(self, members) -> int:
        """The live mapper ids changed (1.14): keyframes the remaining owners now hold all go
        (returns how many); with a new member, everything in flight is sent again now."""
        members = frozenset(members)
        joined = bool(members - self.members)
        self.members = members
        n = 0
        for fid in [f for f, h in self.items.items() if h.acks and self._done(h)]:
            del self.items[fid]
            self.counts["acked"] += 1
            n += 1
        if joined and self.mapper_present:
            for held in self.items.values():
                held.sent_at = None
        self.set_mapper_present(bool(members))
        return n

    def set_mapper_present(self, present: bool) -> None:
        """A mapper appeared (send everything in flight again) or the last one left (hold)."""
        if present and not self.mapper_present:
            for held in self.items.values():
                held.sent_at = None
        self.mapper_present = present

    def due(self) -> list[tuple[int, bytes]]:
        """Payloads to put now, oldest first: overdue ones again, then new ones up to the window."""
        if not self.mapper_present:
            return []
        now = self.clock()
        out = []
        in_flight = 0
        for fid, held in self.items.items():
            if held.sent_at is None:
                continue
            in_flight += 1
            if now - held.sent_at >= self.resend_period_s:
                held.sent_at, held.sends = now, held.sends + 1
                self.counts["resent"] += 1
                out.append((fid, held.payload))
        for fid, held in self.items.items():
            if in_flight >= self.window:
                break
            if held.sent_at is None:
                self.counts["resent" if held.sends else "sent"] += 1
                held.sent_at, held.sends = now, held.sends + 1
                in_flight += 1
                out.append((fid, held.payload))
        return out
