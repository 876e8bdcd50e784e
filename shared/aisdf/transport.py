"""The one place that turns configuration into a Zenoh session, plus small helpers to
publish and query protocol messages. Services, the client and the demo use it.
"""

from __future__ import annotations

import json
import logging
from typing import Any, Callable, Mapping

import zenoh

from . import protocol
from .config import ZenohOptions

log = logging.getLogger(__name__)
ENCODING = zenoh.Encoding(protocol.ENCODING)


def zenoh_config(opts: ZenohOptions) -> zenoh.Config:
    """Build a ``zenoh.Config`` from options (file first, then the explicit settings)."""
    conf = zenoh.Config.from_file(str(opts.config_file)) if opts.config_file else zenoh.Config()
    if opts.mode:
        conf.insert_json5("mode", json.dumps(opts.mode))
    if opts.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(opts.connect)))
    if opts.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(opts.listen)))
    if opts.multicast_scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(opts.multicast_scouting)))
    return conf


def open_session(opts: ZenohOptions) -> zenoh.Session:
    """Open a Zenoh session; close it (or use ``with``) so its threads end."""
    return zenoh.open(zenoh_config(opts))


def put(session: zenoh.Session, key: str, msg: Mapping[str, Any]) -> None:
    """Publish one protocol message."""
    session.put(key, protocol.pack(msg), encoding=ENCODING)


def payload_bytes(payload) -> bytes:
    return b"" if payload is None else payload.to_bytes()


def get_latest(session: zenoh.Session, key: str, timeout: float = 2.0) -> dict | None:
    """``get`` a latest-value key (map/weights, map/surfels); None when nobody answers."""
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            try:
                return protocol.unpack(payload_bytes(reply.ok.payload))
            except protocol.ProtocolError as e:
                log.warning("ignoring malformed reply on %s: %s", key, e.message)
    return None


def query(session: zenoh.Session, key: str, msg: Mapping[str, Any], timeout: float = 10.0) -> dict:
    """Send a request, return the first reply's message; raise ProtocolError on a protocol
    error reply, TimeoutError when no service answers. Error replies that are not protocol
    messages (Zenoh's own, e.g. a timeout) are reported only if nothing else arrives."""
    other = None
    for reply in session.get(key, payload=protocol.pack(msg), encoding=ENCODING, timeout=timeout):
        if reply.ok is not None:
            return protocol.unpack(payload_bytes(reply.ok.payload))
        raw = payload_bytes(reply.err.payload)
        try:
            err = protocol.unpack(raw)
        except protocol.ProtocolError:
            other = raw
            continue
        raise protocol.decode_error(protocol.pack(err))
    if other is not None:
        text = other.decode("utf-8", "replace")[:200]
        if "timeout" in text.lower():
            raise TimeoutError(f"no reply on {key} within {timeout:.1f} s ({text})")
        raise protocol.ProtocolError("internal", f"transport error on {key}: {text}")
    raise TimeoutError(f"no reply on {key} within {timeout:.1f} s (is a query service running?)")


def serve(session: zenoh.Session, key: str, handler: Callable[[dict], Mapping[str, Any]], allow_empty: bool = False):
    """Declare a queryable whose ``handler(request_msg) -> reply_msg`` may raise
    ProtocolError (sent as that error) or anything else (sent as ``internal``).
    The service never stops on a bad request. ``allow_empty``: a query without payload
    counts as ``{"v": 1}`` (for read-only endpoints)."""

    def on_query(q: zenoh.Query) -> None:
        try:
            raw = payload_bytes(q.payload)
            req = {"v": protocol.VERSION} if allow_empty and not raw else protocol.unpack(raw)
            reply = handler(req)
            q.reply(q.key_expr, protocol.pack(reply), encoding=ENCODING)
        except protocol.ProtocolError as e:
            log.info("%s: %s", key, e)
            q.reply_err(protocol.pack(protocol.error_message(e.code, e.message)), encoding=ENCODING)
        except Exception as e:  # noqa: BLE001 - a request must never stop the service
            log.exception("internal error answering %s", key)
            q.reply_err(protocol.pack(protocol.error_message("internal", f"{type(e).__name__}: {e}")),
                        encoding=ENCODING)

    return session.declare_queryable(key, on_query)
