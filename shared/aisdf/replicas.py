"""Query replicas (protocol 1.12) as a planner sees them: which are alive, which to ask next,
and one request to one replica.

Every 1.12 query service declares the liveliness token ``<ns>/query/replica/<id>`` and answers
``<ns>/query/replica/<id>/sdf`` and ``.../mesh``. :class:`Replicas` follows the tokens (a
liveliness subscriber with history, so the replicas already up are seen at once, and a
liveliness ``get`` at the start so the first request knows them) and picks, for each request,
the live replica this client has the fewest requests in flight to, the least recently asked
on a tie, skipping for ``no_map_retry_s`` one that answered ``no_map``. :func:`ask` sends one
request to one replica and gives up early when its token goes. ``SdfClient``
(``aisdf.client``) puts them together: failover to another replica on ``busy``, ``no_map``, a
timeout or a replica gone, within the client's timeout.
"""

from __future__ import annotations

import random
import threading
import time

import zenoh

from . import keys, protocol, transport


class ReplicaGone(TimeoutError):
    """The replica asked vanished (its token went, or Zenoh closed the query without a reply)."""


class Replicas:
    """The live query replicas of ``namespace``, from their liveliness tokens."""

    def __init__(self, session: zenoh.Session, namespace: str, no_map_retry_s: float = 2.0):
        self.namespace = namespace
        self.no_map_retry_s = no_map_retry_s
        self._cond = threading.Condition()
        self._live: dict[str, dict] = {}  # id -> {"in_flight", "last", "no_map_until"}
        self._gone: dict[str, set[threading.Event]] = {}  # id -> events of requests waiting on it
        self._rng = random.Random()
        key = keys.replica_key(namespace, "*")
        # The get first: with a history subscriber already declared on the key, a liveliness get
        # came back empty at once (12 of 12 tries, through a router). Then the subscriber, which
        # also replays the history, so a token that appears in between is not missed.
        try:
            for reply in session.liveliness().get(key, timeout=1.0):
                if reply.ok is not None:
                    self._add(str(reply.ok.key_expr))
        except Exception:  # noqa: BLE001 - the subscriber sees them anyway
            pass
        self._sub = session.liveliness().declare_subscriber(key, self._on_token, history=True)

    def _id(self, key: str) -> str | None:
        rid = key.rsplit("/", 1)[-1]
        try:
            return keys.validate_replica_id(rid) if key == keys.replica_key(self.namespace, rid) else None
        except ValueError:
            return None

    def _add(self, key: str) -> None:
        rid = self._id(key)
        if rid is None:
            return
        with self._cond:
            # a random "last asked" time, so clients started together do not all begin on one replica
            self._live.setdefault(rid, {"in_flight": 0, "last": -self._rng.random(), "no_map_until": 0.0})

    def _on_token(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._add(str(sample.key_expr))
            return
        rid = self._id(str(sample.key_expr))
        with self._cond:
            self._live.pop(rid, None)
            for ev in self._gone.get(rid, ()):
                ev.set()

    def ids(self) -> list[str]:
        with self._cond:
            return sorted(self._live)

    def pick(self, exclude=()) -> str | None:
        """The replica to ask next (None when every live one is in ``exclude``); counts a request
        in flight to it until :meth:`done`."""
        now = time.monotonic()
        with self._cond:
            cand = [r for r in self._live if r not in exclude]
            if not cand:
                return None
            mapped = [r for r in cand if self._live[r]["no_map_until"] <= now]
            rid = min(mapped or cand, key=lambda r: (self._live[r]["in_flight"], self._live[r]["last"], r))
            st = self._live[rid]
            st["in_flight"] += 1
            st["last"] = now
            return rid

    def done(self, rid: str, no_map: bool = False) -> None:
        with self._cond:
            st = self._live.get(rid)
            if st is not None:
                st["in_flight"] = max(0, st["in_flight"] - 1)
                st["no_map_until"] = time.monotonic() + self.no_map_retry_s if no_map else 0.0

    def watch(self, rid: str, ev: threading.Event) -> None:
        """Set ``ev`` when ``rid``'s token goes (at once if it is gone already)."""
        with self._cond:
            if rid not in self._live:
                ev.set()
            self._gone.setdefault(rid, set()).add(ev)

    def unwatch(self, rid: str, ev: threading.Event) -> None:
        with self._cond:
            evs = self._gone.get(rid)
            if evs is not None:
                evs.discard(ev)
                if not evs:
                    del self._gone[rid]

    def alive(self, rid: str) -> bool:
        with self._cond:
            return rid in self._live

    def close(self) -> None:
        self._sub.undeclare()


def ask(session: zenoh.Session, replicas: Replicas, rid: str, name: str, payload: bytes, timeout: float) -> dict:
    """One request to replica ``rid`` on ``query/replica/<rid>/<name>``: the reply's message;
    ``ProtocolError`` for a protocol error reply; ``ReplicaGone`` when its token goes or Zenoh
    ends the query without a reply (the replica's link closed); ``TimeoutError`` after
    ``timeout`` or on a transport error."""
    key = keys.replica_key(replicas.namespace, rid, name)
    done = threading.Event()
    replies: list = []

    def on_reply(reply) -> None:
        replies.append(reply)
        done.set()

    cancel = zenoh.CancellationToken()
    replicas.watch(rid, done)
    try:
        session.get(key, zenoh.handlers.Callback(on_reply, done.set), payload=payload,
                    encoding=transport.ENCODING, timeout=timeout, cancellation_token=cancel)
        done.wait(timeout + 1.0)
        got = list(replies)
    finally:
        replicas.unwatch(rid, done)
        if not replies:
            cancel.cancel()
    for reply in got:
        if reply.ok is not None:
            return protocol.unpack(transport.payload_bytes(reply.ok.payload))
        raw = transport.payload_bytes(reply.err.payload)
        try:
            err = protocol.unpack(raw)
        except protocol.ProtocolError:
            raise TimeoutError(f"no answer from replica {rid} on {key}: {raw.decode('utf-8', 'replace')[:200]}") \
                from None
        raise protocol.decode_error(protocol.pack(err))
    if not replicas.alive(rid):
        raise ReplicaGone(f"replica {rid} went while answering {key}")
    if done.is_set():
        raise ReplicaGone(f"replica {rid} closed the query on {key} without a reply")
    raise TimeoutError(f"no reply from replica {rid} on {key} within {timeout:.1f} s")


def replica_infos(session: zenoh.Session, namespace: str, timeout: float = 3.0) -> dict[str, dict]:
    """Every query replica's ``info/query`` (an extension), by replica id: a ``get`` with
    consolidation off, one reply each (a service before 1.12 has no ``replica``: ``"?"``)."""
    out = {}
    for r in session.get(keys.key(namespace, "info/query"), payload=protocol.pack({"v": protocol.VERSION}),
                         encoding=transport.ENCODING, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE):
        if r.ok is not None:
            try:
                m = protocol.unpack(transport.payload_bytes(r.ok.payload))
            except protocol.ProtocolError:
                continue
            out[str(m.get("replica", "?"))] = m
    return out
