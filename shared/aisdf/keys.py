"""Key expressions of the wire protocol (protocol.md, "Keys"), all under a namespace."""

from __future__ import annotations

DEFAULT_NAMESPACE = "aisdf"

KEYFRAMES = "keyframes"
KEYFRAMES_ACK = "keyframes/ack"  # protocol 1.2: mapper -> front ends, KeyframeAck
MAP_WEIGHTS = "map/weights"
MAP_SURFELS = "map/surfels"
MAP_SUBMAPS = "map/submaps"  # protocol 1.3: map/submaps/<id>, one WeightSnapshot (with "submap") per submap
MAP_INDEX = "map/index"  # protocol 1.3: SubmapIndex, which submaps exist at which version
CONTROL_POSES = "control/mapper/poses"  # protocol 1.11: PoseCorrections -> PosesApplied (a get)
QUERY_SDF = "query/sdf"
QUERY_MESH = "query/mesh"
STATUS = "status"


def validate_namespace(namespace: str) -> str:
    """Return the namespace without surrounding slashes; reject wildcards and empty chunks."""
    ns = namespace.strip("/")
    if not ns or any(c in ns for c in "*$?#") or "//" in ns:
        raise ValueError(f"invalid namespace {namespace!r}: non-empty key chunks, no wildcards")
    return ns


def key(namespace: str, name: str) -> str:
    """`key("aisdf/robot2", MAP_SURFELS)` -> `"aisdf/robot2/map/surfels"`."""
    return f"{validate_namespace(namespace)}/{name}"


def status_key(namespace: str, service: str, instance_id: str) -> str:
    """Liveliness token key `<ns>/status/<service>/<id>`."""
    return f"{validate_namespace(namespace)}/{STATUS}/{service}/{instance_id}"
