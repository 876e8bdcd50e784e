"""rmw_zenoh's wire conventions (names, keys, QoS, attachments, liveliness tokens), without a
session: ``rmw_zenoh`` uses them to speak to ROS 2 nodes that use the Zenoh middleware
(``RMW_IMPLEMENTATION=rmw_zenoh_cpp``) without ROS installed.

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
import os
import re
import struct
from dataclasses import dataclass

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
SERVICES_QOS = QoS(depth=10)  # rmw_qos_profile_services_default


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
