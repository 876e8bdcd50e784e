"""A ROS 2 node over rmw_zenoh in Python: discovery of the ROS graph, nodes, publishers,
subscriptions, service servers and clients (:mod:`aisdf.ros.rmw_services`) that ROS 2 nodes
using the Zenoh middleware (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``) see as their own, without
ROS installed. The wire conventions (keys, QoS, attachments, liveliness tokens; see that
module's docstring for their sources) live in :mod:`aisdf.ros.rmw_names` and are re-exported
here.
"""

from __future__ import annotations

import itertools
import logging
import re
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

from .rmw_names import (  # noqa: F401 - the conventions, re-exported: callers use rmw_zenoh.X
    ADMIN_SPACE, NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT, ENTITY_KINDS, HUMBLE_TYPE_HASH, GID_SIZE,
    ATTACHMENT_SIZE, DEFAULT_ROUTER, RELIABILITY_SYSTEM_DEFAULT, RELIABLE, BEST_EFFORT,
    DURABILITY_SYSTEM_DEFAULT, TRANSIENT_LOCAL, VOLATILE, HISTORY_SYSTEM_DEFAULT, KEEP_LAST, KEEP_ALL,
    LIVELINESS_SYSTEM_DEFAULT, LIVELINESS_AUTOMATIC, INFINITE, DISTROS_WITH_HASH, TYPESTORES, mangle,
    demangle, dds_type_name, ros_type_name, qualify, type_hash, topic_key, parse_topic_key, domain_from_env,
    QoS, DEFAULT_QOS, SENSOR_QOS, TF_QOS, TF_STATIC_QOS, TF_STATIC_LISTENER_QOS, SERVICES_QOS, qos_to_keyexpr,
    keyexpr_to_qos, Attachment, entity_gid, Entity, graph_key,
)

if TYPE_CHECKING:
    from .rmw_services import ServiceClient, ServiceServer

log = logging.getLogger("aisdf.ros.rmw_zenoh")


def discover(session, domain_id: int | None = None, timeout: float = 2.0) -> list[Entity]:
    """The ROS graph: every entity whose liveliness token is alive, as a graph cache builds it
    (a liveliness get, and a liveliness subscriber with history for ``timeout`` seconds, so
    tokens that reach this session late are counted too; unparsable tokens skipped)."""
    import zenoh

    alive: dict[str, bool] = {}
    lock = threading.Lock()

    def on_token(sample) -> None:
        with lock:
            alive[str(sample.key_expr)] = sample.kind == zenoh.SampleKind.PUT

    key = graph_key(domain_id)
    sub = session.liveliness().declare_subscriber(key, on_token, history=True)
    try:
        for reply in session.liveliness().get(key, timeout=timeout):
            if reply.ok is not None:
                with lock:
                    alive.setdefault(str(reply.ok.key_expr), True)
        time.sleep(0.2)
    finally:
        sub.undeclare()
    out = []
    for k, up in sorted(alive.items()):
        if not up:
            continue
        try:
            out.append(Entity.parse(k))
        except ValueError as e:
            log.debug("skipping liveliness token: %s", e)
    return out


# ----------------------------------------------------------------------------- nodes


def open_typestore(distro: str):
    from rosbags.typesys import Stores, get_typestore

    d = distro.lower()
    if d not in TYPESTORES:
        raise ValueError(f"unknown ROS 2 distribution {distro!r}; choose one of {sorted(TYPESTORES)}")
    return get_typestore(getattr(Stores, TYPESTORES[d]))


@dataclass
class MessageInfo:
    """What a subscription callback gets beside the message."""

    key: str
    attachment: Attachment | None
    received_ns: int


class Node:
    """A ROS 2 node over rmw_zenoh on an open Zenoh session: declares its ``NN`` token, and
    creates publishers and subscriptions that declare theirs. ``close()`` undeclares all
    (the session stays the caller's to close)."""

    def __init__(self, session, name: str, namespace: str = "/", domain_id: int = 0, distro: str = "jazzy",
                 enclave: str = "/", node_id: int = 0, typestore=None):
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise ValueError(f"invalid ROS node name {name!r}")
        if not namespace.startswith("/"):
            raise ValueError(f"a node namespace starts with '/': {namespace!r}")
        self.session, self.name, self.namespace = session, name, namespace
        self.domain_id, self.distro, self.enclave = int(domain_id), distro.lower(), enclave
        self.node_id = str(node_id)
        self.typestore = typestore or open_typestore(self.distro)
        self.zid = str(session.zid())
        self._ids = itertools.count(10)  # rmw_zenoh numbers a context's entities from 10 after the node
        self._entities: list = []
        self.entity = Entity(self.domain_id, self.zid, self.node_id, self.node_id, NODE, enclave, namespace, name)
        self._token = session.liveliness().declare_token(self.entity.key())

    def _topic_entity(self, kind: str, topic: str, msgtype: str, qos: QoS, hash_: str | None = None) -> Entity:
        return Entity(self.domain_id, self.zid, self.node_id, str(next(self._ids)), kind, self.enclave,
                      self.namespace, self.name, qualify(topic, self.namespace), dds_type_name(msgtype),
                      hash_ or type_hash(self.typestore, msgtype, self.distro), qos)

    def _service_entity(self, kind: str, name: str, srvtype: str, qos: QoS) -> Entity:
        from .interfaces import service_type_hash

        return self._topic_entity(kind, name, srvtype, qos, service_type_hash(self.typestore, srvtype, self.distro))

    def create_publisher(self, topic: str, msgtype: str, qos: QoS = DEFAULT_QOS) -> "Publisher":
        p = Publisher(self, self._topic_entity(PUBLISHER, topic, msgtype, qos), msgtype)
        self._entities.append(p)
        return p

    def create_subscription(self, topic: str, msgtype: str, callback: Callable[[Any, MessageInfo], None],
                            qos: QoS = DEFAULT_QOS, any_hash: bool = True) -> "Subscription":
        s = Subscription(self, self._topic_entity(SUBSCRIPTION, topic, msgtype, qos), msgtype, callback, any_hash)
        self._entities.append(s)
        return s

    def create_service(self, name: str, srvtype: str, handler: Callable[[Any], Any],
                       qos: QoS = SERVICES_QOS) -> "ServiceServer":
        """A service server: ``handler(request) -> response`` (rosbags message objects of
        ``<srvtype>_Request`` / ``_Response``; see :class:`aisdf.ros.rmw_services.ServiceServer`)."""
        from .rmw_services import ServiceServer

        s = ServiceServer(self, self._service_entity(SERVICE, name, srvtype, qos), srvtype, handler)
        self._entities.append(s)
        return s

    def create_client(self, name: str, srvtype: str, qos: QoS = SERVICES_QOS) -> "ServiceClient":
        """A service client: ``client.call(request, timeout)`` -> the response."""
        from .rmw_services import ServiceClient

        c = ServiceClient(self, self._service_entity(CLIENT, name, srvtype, qos), srvtype)
        self._entities.append(c)
        return c

    def close(self) -> None:
        for e in reversed(self._entities):
            e.close()
        self._entities.clear()
        if self._token is not None:
            self._token.undeclare()
            self._token = None

    def __enter__(self) -> "Node":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Publisher:
    """A ROS 2 publisher: ``publish(msg)`` (a rosbags message object) or ``publish_raw(cdr)``."""

    def __init__(self, node: Node, entity: Entity, msgtype: str):
        import zenoh
        import zenoh.ext as zext

        self.node, self.entity, self.msgtype = node, entity, msgtype
        self.key = topic_key(entity.domain_id, entity.topic, entity.dds_type, entity.type_hash)
        self.gid = entity_gid(entity.key())
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        q = entity.qos
        reliability = zenoh.Reliability.RELIABLE if q.reliability != BEST_EFFORT else zenoh.Reliability.BEST_EFFORT
        congestion = (zenoh.CongestionControl.BLOCK if q.reliability != BEST_EFFORT and q.history == KEEP_ALL
                      else zenoh.CongestionControl.DROP)
        kwargs: dict = dict(reliability=reliability, congestion_control=congestion)
        if q.transient_local:
            kwargs.update(cache=zext.CacheConfig(max_samples=max(1, q.depth)), publisher_detection=True)
            if q.reliability != BEST_EFFORT:
                kwargs["sample_miss_detection"] = zext.MissDetectionConfig(sporadic_heartbeat=0.5)
        self._pub = zext.declare_advanced_publisher(node.session, self.key, **kwargs)
        self._token = node.session.liveliness().declare_token(entity.key())

    def publish(self, msg) -> None:
        self.publish_raw(self.node.typestore.serialize_cdr(msg, self.msgtype))

    def publish_raw(self, cdr: bytes) -> None:
        with self._lock:
            att = Attachment(next(self._seq), time.time_ns(), self.gid)
            self._pub.put(bytes(cdr), attachment=att.to_bytes())

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._pub.undeclare()
            self._token = None


@dataclass
class SubscriptionCounts:
    received: int = 0
    delivered: int = 0
    malformed: int = 0
    no_attachment: int = 0
    errors: list = field(default_factory=list)


class Subscription:
    """A ROS 2 subscription: deserialises each sample's CDR with the node's typestore and calls
    ``callback(msg, MessageInfo)``. Malformed samples (bad CDR, bad attachment) are logged,
    counted and dropped; a callback's exception is logged and the subscription goes on."""

    def __init__(self, node: Node, entity: Entity, msgtype: str, callback, any_hash: bool = True):
        import zenoh.ext as zext

        self.node, self.entity, self.msgtype, self.callback = node, entity, msgtype, callback
        self.key = topic_key(entity.domain_id, entity.topic, entity.dds_type, "*" if any_hash else entity.type_hash)
        self.counts = SubscriptionCounts()
        q = entity.qos
        kwargs: dict = {}
        if q.transient_local:
            kwargs.update(history=zext.HistoryConfig(detect_late_publishers=True, max_samples=max(1, q.depth)),
                          subscriber_detection=True)
            if q.reliability != BEST_EFFORT:
                kwargs["recovery"] = zext.RecoveryConfig(heartbeat=True)
        self._sub = zext.declare_advanced_subscriber(node.session, self.key, self._on_sample, **kwargs)
        self._token = node.session.liveliness().declare_token(entity.key())

    def _on_sample(self, sample) -> None:
        self.counts.received += 1
        key = str(sample.key_expr)
        att = None
        try:
            raw_att = sample.attachment
            if raw_att is None:
                self.counts.no_attachment += 1
            else:
                att = Attachment.from_bytes(raw_att.to_bytes())
            msg = self.node.typestore.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)
        except Exception as e:  # noqa: BLE001 - a malformed message never stops the source
            self.counts.malformed += 1
            if len(self.counts.errors) < 20:
                self.counts.errors.append(f"{key}: {type(e).__name__}: {e}")
            log.warning("dropping a malformed %s message on %s: %s: %s", self.msgtype, key, type(e).__name__, e)
            return
        try:
            self.callback(msg, MessageInfo(key, att, time.time_ns()))
            self.counts.delivered += 1
        except Exception:  # noqa: BLE001
            log.exception("error handling a %s message on %s", self.msgtype, key)

    def close(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._sub.undeclare()
            self._token = None


def open_ros_session(connect: list[str] | None = None, config_file: str | None = None, mode: str = "peer",
                     listen: list[str] | None = None):
    """A Zenoh session configured as rmw_zenoh's default session: peer, connected to the
    router (``tcp/localhost:7447``), listening on loopback (``tcp/localhost:0``), multicast
    scouting off (gossip scouting through the router stays on). A
    ``config_file`` (e.g. ``$ZENOH_SESSION_CONFIG_URI``) is applied first."""
    import json

    import zenoh

    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    if not config_file or mode:
        conf.insert_json5("mode", json.dumps(mode or "peer"))
    if connect or not config_file:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect or [DEFAULT_ROUTER])))
    if listen or not config_file:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen or ["tcp/localhost:0"])))
    if not config_file:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def main(argv: list[str] | None = None) -> int:
    """``python -m aisdf.ros.rmw_zenoh``: print the ROS 2 graph an rmw_zenoh router knows
    (nodes, and the topics each publishes and subscribes, with types): to find a robot's depth,
    camera info and TF topics for ``aisdf-frontend --source ros2``."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m aisdf.ros.rmw_zenoh", description=main.__doc__.split(":")[0])
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help=f"router (default {DEFAULT_ROUTER})")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh session file (as ZENOH_SESSION_CONFIG_URI)")
    p.add_argument("--domain-id", type=int, default=domain_from_env(), help="default $ROS_DOMAIN_ID or 0")
    p.add_argument("--timeout", type=float, default=3.0)
    a = p.parse_args(argv)
    with open_ros_session(a.connect, a.zenoh_config) as session:
        time.sleep(0.5)  # let the session reach the router
        graph = discover(session, a.domain_id, a.timeout)
    nodes = sorted({(e.namespace, e.node_name) for e in graph})
    if not nodes:
        print(f"no ROS 2 node seen on domain {a.domain_id} (router {a.connect or [DEFAULT_ROUTER]})")
        return 1
    for ns, name in nodes:
        print(f"{ns.rstrip('/')}/{name}")
        for e in sorted((e for e in graph if (e.namespace, e.node_name) == (ns, name) and e.kind != NODE),
                        key=lambda e: (e.kind, e.topic)):
            what = {PUBLISHER: "publishes", SUBSCRIPTION: "subscribes", SERVICE: "serves", CLIENT: "calls"}[e.kind]
            try:
                typ = e.msgtype
            except ValueError:
                typ = e.dds_type
            print(f"  {what:10s} {e.topic}  [{typ}]  qos {qos_to_keyexpr(e.qos)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
