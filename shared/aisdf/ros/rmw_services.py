"""ROS 2 services over rmw_zenoh in Python: :class:`ServiceServer` and :class:`ServiceClient`,
made by ``Node.create_service`` / ``Node.create_client`` of :mod:`aisdf.ros.rmw_zenoh`.

As ros2/rmw_zenoh's ``rmw_service_data.cpp`` and ``rmw_client_data.cpp`` (jazzy/rolling, zenoh 1.x):

* the service's key is a topic key, ``<domain>/<service name>/<pkg>::srv::dds_::<Name>_/<hash>``,
  the hash being the *service* type's RIHS01 (:func:`aisdf.ros.interfaces.service_type_hash`);
  the server declares it as a Zenoh queryable with ``complete=True`` and an ``SS`` liveliness
  token, the client an ``SC`` token (QoS of both: rmw's services default, depth 10);
* a request is a Zenoh query on that key (target ALL_COMPLETE, consolidation NONE) whose payload
  is the CDR of ``<pkg>/srv/<Name>_Request`` and whose attachment is the client's (sequence
  number from 1, source timestamp, client GID);
* the reply, on the service key, carries the CDR of ``_Response`` and the attachment (the
  request's sequence number, the server's send time, the request's client GID).

A request rmw_zenoh would refuse (no payload or attachment, bad attachment, bad CDR) or whose
handler raises is logged, counted and answered with a Zenoh error reply (rmw_zenoh drops such
a query unanswered; a C++ client logs an error reply and drops it too, so it sees the same
thing, while :class:`ServiceClient` raises at once with the reason). Nothing stops the server.
"""
from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .interfaces import ensure_service, request_type, response_type
from .rmw_names import ADMIN_SPACE, Attachment, Entity, entity_gid, mangle, topic_key

log = logging.getLogger("aisdf.ros.rmw_services")


@dataclass
class ServiceCounts:
    requests: int = 0
    answered: int = 0
    malformed: int = 0  # no payload or attachment, bad attachment, bad CDR
    failed: int = 0  # the handler raised or returned something that does not serialise
    errors: list = field(default_factory=list)


class ServiceServer:
    """A ROS 2 service server: ``handler(request) -> response`` (rosbags message objects) runs
    on the server's own thread, one request at a time, in arrival order; at most ``qos.depth``
    requests wait (the oldest is dropped, unanswered, as rmw_zenoh does)."""

    def __init__(self, node, entity: Entity, srvtype: str, handler: Callable[[Any], Any]):
        import zenoh

        ensure_service(node.typestore, srvtype)
        self.node, self.entity, self.srvtype, self.handler = node, entity, srvtype, handler
        self.request_type, self.response_type = request_type(srvtype), response_type(srvtype)
        self.key = topic_key(entity.domain_id, entity.topic, entity.dds_type, entity.type_hash)
        self.counts = ServiceCounts()
        self._queryable = node.session.declare_queryable(
            self.key, zenoh.handlers.RingChannel(max(1, entity.qos.depth)), complete=True)
        self._channel = self._queryable.handler  # recv() on it, not on the queryable: undeclare() may then run
        self._token = node.session.liveliness().declare_token(entity.key())
        self._thread = threading.Thread(target=self._serve, name=f"service {entity.topic}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                query = self._channel.recv()
            except Exception:  # noqa: BLE001 - the channel closes when the queryable is undeclared
                return
            try:
                self._answer(query)
            except Exception:  # never let one request stop the server
                log.exception("error answering a %s request on %s", self.srvtype, self.key)
            finally:
                query.drop()

    def _error(self, query, kind: str, text: str) -> None:
        setattr(self.counts, kind, getattr(self.counts, kind) + 1)
        if len(self.counts.errors) < 20:
            self.counts.errors.append(text)
        log.warning("service %s: %s", self.entity.topic, text)
        try:
            query.reply_err(text.encode())
        except Exception as e:  # noqa: BLE001
            log.debug("could not send the error reply: %s", e)

    def _answer(self, query) -> None:
        self.counts.requests += 1
        try:
            if query.attachment is None:
                raise ValueError("the request has no attachment (sequence number, timestamp, client GID)")
            att = Attachment.from_bytes(query.attachment.to_bytes())
            if att.sequence_number < 0 or att.source_timestamp < 0:
                raise ValueError(f"the request's attachment has a negative sequence number or timestamp: {att}")
            if query.payload is None:
                raise ValueError("the request has no payload")
            request = self.node.typestore.deserialize_cdr(query.payload.to_bytes(), self.request_type)
        except Exception as e:  # noqa: BLE001
            self._error(query, "malformed", f"malformed {self.request_type}: {type(e).__name__}: {e}")
            return
        try:
            response = self.handler(request)
            cdr = self.node.typestore.serialize_cdr(response, self.response_type)
        except Exception as e:
            log.exception("service %s: the handler failed on request %d", self.entity.topic, att.sequence_number)
            self._error(query, "failed", f"the {self.srvtype} handler failed: {type(e).__name__}: {e}")
            return
        reply_att = Attachment(att.sequence_number, time.time_ns(), att.gid)
        self.counts.answered += 1  # before the reply: a caller that has it sees it counted
        query.reply(self.key, bytes(cdr), attachment=reply_att.to_bytes())

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._queryable.undeclare()
            self._token = None
            self._thread.join(timeout=5)


class ServiceClient:
    """A ROS 2 service client: ``call(request, timeout)`` -> the response (rosbags objects)."""

    def __init__(self, node, entity: Entity, srvtype: str):
        ensure_service(node.typestore, srvtype)
        self.node, self.entity, self.srvtype = node, entity, srvtype
        self.request_type, self.response_type = request_type(srvtype), response_type(srvtype)
        self.key = topic_key(entity.domain_id, entity.topic, entity.dds_type, entity.type_hash)
        self.gid = entity_gid(entity.key())
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        self._token = node.session.liveliness().declare_token(entity.key())

    def request_class(self):
        return self.node.typestore.types[self.request_type]

    def service_is_ready(self, timeout: float = 1.0) -> bool:
        """Whether a server of this service (same name, type and hash) is in the graph."""
        e = self.entity
        key = "/".join([ADMIN_SPACE, str(e.domain_id), "*", "*", "*", "SS", "*", "*", "*", mangle(e.topic),
                        mangle(e.dds_type), mangle(e.type_hash), "*"])
        return any(r.ok is not None for r in self.node.session.liveliness().get(key, timeout=timeout))

    def wait_for_service(self, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            if self.service_is_ready(min(1.0, max(0.1, deadline - time.monotonic()))):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.1)

    def call(self, request, timeout: float = 10.0):
        """Send ``request``, wait at most ``timeout`` seconds for the response. ``TimeoutError``
        when none comes (no server, or a slow one); ``RuntimeError`` when the server answers
        with an error (a malformed request, a failed handler) or a malformed response."""
        import zenoh

        cdr = bytes(self.node.typestore.serialize_cdr(request, self.request_type))
        with self._lock:
            seq = next(self._seq)
        att = Attachment(seq, time.time_ns(), self.gid)
        replies = self.node.session.get(self.key, target=zenoh.QueryTarget.ALL_COMPLETE,
                                        consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout,
                                        payload=cdr, attachment=att.to_bytes())
        t0, errors = time.monotonic(), []
        for reply in replies:
            if reply.ok is None:
                err = reply.err
                errors.append(err.payload.to_bytes().decode("utf-8", "replace") if err is not None else "?")
                continue
            sample = reply.ok
            try:
                got = Attachment.from_bytes(sample.attachment.to_bytes()) if sample.attachment is not None else None
                if got is None or got.sequence_number != seq or got.gid != self.gid:
                    log.warning("service %s: ignoring a reply for another request (%s)", self.entity.topic, got)
                    continue
                return self.node.typestore.deserialize_cdr(sample.payload.to_bytes(), self.response_type)
            except Exception as e:  # noqa: BLE001
                errors.append(f"malformed {self.response_type}: {type(e).__name__}: {e}")
        if errors:
            raise RuntimeError(f"service {self.entity.topic} ({self.srvtype}) answered request {seq} with an error: "
                               + "; ".join(errors))
        waited = time.monotonic() - t0
        raise TimeoutError(f"no response from service {self.entity.topic} ({self.srvtype}, key {self.key}) "
                           f"to request {seq} within {timeout:g} s"
                           + ("" if waited > 0.9 * timeout else f" (no server answered; the query ended after "
                                                                  f"{waited:.2f} s)"))

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._token = None

