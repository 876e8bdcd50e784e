"""rmw_zenoh's wire conventions, so that a Python process speaks to ROS 2 nodes that use the
Zenoh middleware (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``) without ROS installed.

Written against ros2/rmw_zenoh ``docs/design.md`` (the 2025 revision: zenoh 1.x, advanced
publishers) and its sources (``liveliness_utils.cpp``, ``attachment_helpers.cpp``,
``qos.cpp``, ``rmw_publisher_data.cpp``, ``rmw_subscription_data.cpp``):

* **Data keys** ``<domain_id>/<fully qualified name>/<DDS type name>/<type hash>``, the name
  without its leading/trailing ``/``, e.g.
  ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...``. The type hash is REP-2016's
  ``RIHS01_<sha256>`` from Iron/Jazzy on; Humble's rmw_zenoh writes ``TypeHashNotSupported``.
  :class:`Subscription` listens with ``*`` in the hash's place by default (both work).
* **Payload**: CDR with its 4-byte encapsulation header, as ``rosbags``' ``serialize_cdr``.
* **Attachment** of every message: sequence number (int64 LE), source timestamp (int64 LE,
  ns since the epoch), GID length (1 byte, 16) and the 16-byte GID (zenoh-ext's serializer of
  ``(int64, int64, array<uint8,16>)``; 33 bytes).
* **Liveliness tokens** (discovery, the ROS graph), in the hermetic ``@ros2_lv`` space:
  ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>`` for a
  node and ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS|SS|SC>/<enclave>/<namespace>/
  <node name>/<topic>/<type>/<hash>/<qos>`` for publishers, subscriptions, services and clients;
  names mangled (``/`` -> ``%``, an empty namespace or enclave is ``%``); QoS in rmw_zenoh's
  compact form (``qos_to_keyexpr``: only fields that differ from its defaults, RELIABLE,
  VOLATILE, KEEP_LAST 42, infinite durations, AUTOMATIC liveliness).
* **QoS**: a TRANSIENT_LOCAL publisher is a zenoh-ext advanced publisher with a cache of
  ``depth`` samples and publisher detection (and sporadic heartbeats for sample-miss detection
  when RELIABLE); a TRANSIENT_LOCAL subscription an advanced subscriber that detects late
  publishers and queries their caches (``/tf_static``). RELIABLE maps to Zenoh's reliable
  reliability, BEST_EFFORT to best effort.

The entity GID: rmw_zenoh takes XXH3-128 of the liveliness key expression. With the
``xxhash`` package installed this module does the same; otherwise BLAKE2b-128 of the same
string (still unique and stable per entity; the GID is opaque to every receiver).
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import os
import re
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

log = logging.getLogger("aisdf.ros.rmw_zenoh")

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
DEFAULT_ROUTER = "tcp/localhost:7447"

# rmw/types.h enums
RELIABILITY_SYSTEM_DEFAULT, RELIABLE, BEST_EFFORT = 0, 1, 2
DURABILITY_SYSTEM_DEFAULT, TRANSIENT_LOCAL, VOLATILE = 0, 1, 2
HISTORY_SYSTEM_DEFAULT, KEEP_LAST, KEEP_ALL = 0, 1, 2
LIVELINESS_SYSTEM_DEFAULT, LIVELINESS_AUTOMATIC = 0, 1
INFINITE = (0x7FFFFFFFFFFFFFFF // 1_000_000_000, 0x7FFFFFFFFFFFFFFF % 1_000_000_000)  # RMW_DURATION_INFINITE

DISTROS_WITH_HASH = ("iron", "jazzy", "kilted", "lyrical", "rolling")
TYPESTORES = {"humble": "ROS2_HUMBLE", "iron": "ROS2_IRON", "jazzy": "ROS2_JAZZY", "kilted": "ROS2_KILTED",
              "lyrical": "ROS2_LYRICAL", "rolling": "LATEST"}


# ----------------------------------------------------------------------------- names


def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the DDS name in CDR)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"ROS type name {msgtype!r} is not of the form package/msg/Name")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image``."""
    m = re.fullmatch(r"([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_", dds)
    if not m:
        raise ValueError(f"{dds!r} is not a DDS type name of the form pkg::msg::dds_::Name_")
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}"


def qualify(topic: str, namespace: str = "/") -> str:
    """A fully qualified topic name: ``chatter`` in ``/robot1`` -> ``/robot1/chatter``."""
    if not topic:
        raise ValueError("empty topic name")
    if topic.startswith("~"):
        raise ValueError(f"private topic names ({topic!r}) are not supported; give the full name")
    if topic.startswith("/"):
        return topic
    ns = namespace.rstrip("/")
    return f"{ns}/{topic}" if ns else f"/{topic}"


def type_hash(typestore, msgtype: str, distro: str) -> str:
    """The key expressions' type hash: RIHS01 from Iron on, Humble's placeholder before."""
    if distro.lower() == "humble":
        return HUMBLE_TYPE_HASH
    return typestore.hash_rihs01(msgtype)


def topic_key(domain_id: int, topic: str, dds_type: str, hash_: str) -> str:
    """``<domain_id>/<fully qualified name without the outer slashes>/<type>/<hash>``."""
    name = topic.strip("/")
    if not name or "//" in name:
        raise ValueError(f"invalid topic name {topic!r}")
    return f"{int(domain_id)}/{name}/{dds_type}/{hash_}"


def parse_topic_key(key: str) -> tuple[int, str, str, str]:
    """Inverse of :func:`topic_key`: (domain id, fully qualified name, DDS type, hash)."""
    parts = str(key).split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise ValueError(f"{key!r} is not an rmw_zenoh data key")
    return int(parts[0]), "/" + "/".join(parts[1:-2]), parts[-2], parts[-1]


def domain_from_env(default: int = 0) -> int:
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(raw) if raw.isdigit() else default


# ----------------------------------------------------------------------------- QoS


@dataclass(frozen=True)
class QoS:
    """An rmw QoS profile (the fields rmw_zenoh writes into liveliness tokens)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = LIVELINESS_AUTOMATIC
    liveliness_lease: tuple[int, int] = INFINITE

    @property
    def transient_local(self) -> bool:
        return self.durability == TRANSIENT_LOCAL


DEFAULT_QOS = QoS()  # rmw_zenoh's defaults (qos.cpp)
SENSOR_QOS = QoS(reliability=BEST_EFFORT, depth=5)  # rclcpp::SensorDataQoS
TF_QOS = QoS(depth=100)  # tf2_ros::DynamicListenerQoS / TransformBroadcaster
TF_STATIC_QOS = QoS(durability=TRANSIENT_LOCAL, depth=1)  # tf2_ros::StaticBroadcasterQoS
TF_STATIC_LISTENER_QOS = QoS(durability=TRANSIENT_LOCAL, depth=100)  # tf2_ros::StaticListenerQoS


def qos_to_keyexpr(q: QoS) -> str:
    """rmw_zenoh's ``qos_to_keyexpr``: ``rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:liv,lease_s,lease_ns``,
    each field empty when it equals the default."""
    d = DEFAULT_QOS

    def f(v, dv) -> str:
        return "" if v == dv else str(v)

    return (f"{f(q.reliability, d.reliability)}:{f(q.durability, d.durability)}:"
            f"{f(q.history, d.history)},{f(q.depth, d.depth)}:"
            f"{f(q.deadline[0], d.deadline[0])},{f(q.deadline[1], d.deadline[1])}:"
            f"{f(q.lifespan[0], d.lifespan[0])},{f(q.lifespan[1], d.lifespan[1])}:"
            f"{f(q.liveliness, d.liveliness)},{f(q.liveliness_lease[0], d.liveliness_lease[0])},"
            f"{f(q.liveliness_lease[1], d.liveliness_lease[1])}")


def keyexpr_to_qos(text: str) -> QoS:
    """Inverse of :func:`qos_to_keyexpr`; ``ValueError`` when malformed."""
    parts = text.split(":")
    if len(parts) < 6:
        raise ValueError(f"QoS {text!r} has {len(parts)} ':'-separated parts, 6 expected")
    hist, dl, ls, liv = (p.split(",") for p in parts[2:6])
    if len(hist) < 2 or len(dl) < 2 or len(ls) < 2 or len(liv) < 3:
        raise ValueError(f"QoS {text!r} is malformed")
    d = DEFAULT_QOS

    def n(s: str, dv: int) -> int:
        if not s:
            return dv
        if not s.isdigit():
            raise ValueError(f"QoS {text!r}: {s!r} is not a number")
        return int(s)

    return QoS(reliability=n(parts[0], d.reliability), durability=n(parts[1], d.durability),
               history=n(hist[0], d.history), depth=n(hist[1], d.depth),
               deadline=(n(dl[0], d.deadline[0]), n(dl[1], d.deadline[1])),
               lifespan=(n(ls[0], d.lifespan[0]), n(ls[1], d.lifespan[1])),
               liveliness=n(liv[0], d.liveliness),
               liveliness_lease=(n(liv[1], d.liveliness_lease[0]), n(liv[2], d.liveliness_lease[1])))


# ----------------------------------------------------------------------------- attachment


@dataclass(frozen=True)
class Attachment:
    """The per-message attachment: sequence number, source timestamp (ns), publisher GID."""

    sequence_number: int
    source_timestamp: int
    gid: bytes

    def to_bytes(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        return struct.pack("<qqB", self.sequence_number, self.source_timestamp, GID_SIZE) + bytes(self.gid)

    @classmethod
    def from_bytes(cls, raw: bytes) -> "Attachment":
        raw = bytes(raw)
        if len(raw) != ATTACHMENT_SIZE:
            raise ValueError(f"rmw_zenoh attachment has {len(raw)} bytes, {ATTACHMENT_SIZE} expected")
        seq, ts, n = struct.unpack_from("<qqB", raw)
        if n != GID_SIZE:
            raise ValueError(f"rmw_zenoh attachment GID length is {n}, {GID_SIZE} expected")
        return cls(seq, ts, raw[17:])


def entity_gid(liveliness_key: str) -> bytes:
    """The entity's GID from its liveliness key expression (rmw_zenoh: XXH3-128, low 64 bits
    then high 64 bits, little-endian)."""
    try:
        import xxhash  # type: ignore[import-not-found]

        h = xxhash.xxh3_128_intdigest(liveliness_key.encode())
        return struct.pack("<QQ", h & 0xFFFFFFFFFFFFFFFF, h >> 64)
    except ImportError:
        return hashlib.blake2b(liveliness_key.encode(), digest_size=GID_SIZE).digest()


# ----------------------------------------------------------------------------- liveliness


@dataclass(frozen=True)
class Entity:
    """One ROS graph entity as its liveliness token describes it."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    enclave: str = "/"
    namespace: str = "/"
    node_name: str = ""
    topic: str | None = None  # fully qualified
    dds_type: str | None = None
    type_hash: str | None = None
    qos: QoS | None = None

    @property
    def msgtype(self) -> str | None:
        return ros_type_name(self.dds_type) if self.dds_type else None

    def key(self) -> str:
        """The liveliness key expression (``Entity`` constructor of liveliness_utils.cpp)."""
        if self.kind not in ENTITY_KINDS:
            raise ValueError(f"entity kind {self.kind!r} is not one of {ENTITY_KINDS}")
        if not self.node_name:
            raise ValueError("an entity needs a node name")
        parts = [ADMIN_SPACE, str(self.domain_id), self.zid, self.node_id, self.entity_id, self.kind,
                 mangle(self.enclave or "/"), mangle(self.namespace or "/"), mangle(self.node_name)]
        if self.kind != NODE:
            if not (self.topic and self.dds_type and self.type_hash and self.qos):
                raise ValueError(f"a {self.kind} token needs a topic, a type, a type hash and a QoS")
            parts += [mangle(self.topic), mangle(self.dds_type), mangle(self.type_hash), qos_to_keyexpr(self.qos)]
        return "/".join(parts)

    @classmethod
    def parse(cls, key: str) -> "Entity":
        """A liveliness key expression -> Entity; ``ValueError`` with a sentence when malformed."""
        parts = str(key).split("/")
        if len(parts) < 9:
            raise ValueError(f"liveliness token {key!r} has {len(parts)} parts, at least 9 expected")
        if any(not p for p in parts):
            raise ValueError(f"liveliness token {key!r} has empty parts")
        if parts[0] != ADMIN_SPACE:
            raise ValueError(f"liveliness token {key!r} is not under {ADMIN_SPACE}")
        if not parts[1].isdigit():
            raise ValueError(f"liveliness token {key!r}: domain id {parts[1]!r} is not a number")
        kind = parts[5]
        if kind not in ENTITY_KINDS:
            raise ValueError(f"liveliness token {key!r}: unknown entity kind {kind!r}")
        base = dict(domain_id=int(parts[1]), zid=parts[2], node_id=parts[3], entity_id=parts[4], kind=kind,
                    enclave=demangle(parts[6]), namespace=demangle(parts[7]), node_name=demangle(parts[8]))
        if kind == NODE:
            return cls(**base)
        if len(parts) < 13:
            raise ValueError(f"liveliness token {key!r} of a {kind} lacks topic, type, hash or QoS")
        return cls(**base, topic=demangle(parts[9]), dds_type=demangle(parts[10]), type_hash=demangle(parts[11]),
                   qos=keyexpr_to_qos(parts[12]))


def graph_key(domain_id: int | None = None) -> str:
    """Key expression matching every liveliness token of a domain (all domains with None)."""
    return f"{ADMIN_SPACE}/{'*' if domain_id is None else int(domain_id)}/**"


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

    def _topic_entity(self, kind: str, topic: str, msgtype: str, qos: QoS) -> Entity:
        return Entity(self.domain_id, self.zid, self.node_id, str(next(self._ids)), kind, self.enclave,
                      self.namespace, self.name, qualify(topic, self.namespace), dds_type_name(msgtype),
                      type_hash(self.typestore, msgtype, self.distro), qos)

    def create_publisher(self, topic: str, msgtype: str, qos: QoS = DEFAULT_QOS) -> "Publisher":
        p = Publisher(self, self._topic_entity(PUBLISHER, topic, msgtype, qos), msgtype)
        self._entities.append(p)
        return p

    def create_subscription(self, topic: str, msgtype: str, callback: Callable[[Any, MessageInfo], None],
                            qos: QoS = DEFAULT_QOS, any_hash: bool = True) -> "Subscription":
        s = Subscription(self, self._topic_entity(SUBSCRIPTION, topic, msgtype, qos), msgtype, callback, any_hash)
        self._entities.append(s)
        return s

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
