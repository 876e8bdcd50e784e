"""Key expressions of the wire protocol (protocol.md, "Keys"), all under a namespace."""

from __future__ import annotations

import re
import socket

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
QUERY_REPLICA = "query/replica"  # protocol 1.12: query/replica/<id> (liveliness token), .../sdf, .../mesh
STATUS = "status"
_REPLICA_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def validate_namespace(namespace: str) -> str:
    """Return the namespace without surrounding slashes; reject wildcards and empty chunks."""
    ns = namespace.strip("/")
    if not ns or any(c in ns for c in "*$?#") or "//" in ns:
        raise ValueError(f"invalid namespace {namespace!r}: non-empty key chunks, no wildcards")
    return ns


def key(namespace: str, name: str) -> str:
    """`key("aisdf/robot2", MAP_SURFELS)` -> `"aisdf/robot2/map/surfels"`."""
    return f"{validate_namespace(namespace)}/{name}"


def validate_replica_id(replica_id: str) -> str:
    """A replica id is one key chunk: letters, digits, ``-``, ``_`` and ``.``, at most 64."""
    if not isinstance(replica_id, str) or not _REPLICA_ID.fullmatch(replica_id):
        raise ValueError(f"invalid replica id {replica_id!r}: 1-64 letters, digits, '-', '_' or '.'")
    return replica_id


def host_chunk() -> str:
    """This host's name as one key chunk (its first label, other characters than letters, digits,
    ``_``, ``.``, ``-`` as ``-``, at most 48): the start of a query replica's default id
    ``<host_chunk()>-<6 hex digits>``; in a container, the container's hostname."""
    return re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname().split(".")[0])[:48] or "query"


def replica_key(namespace: str, replica_id: str, name: str | None = None) -> str:
    """Protocol 1.12: `<ns>/query/replica/<id>` (the replica's liveliness token; ``"*"`` for
    every replica) or, with ``name`` (``"sdf"``, ``"mesh"``), `<ns>/query/replica/<id>/<name>`."""
    rid = replica_id if replica_id == "*" else validate_replica_id(replica_id)
    k = f"{validate_namespace(namespace)}/{QUERY_REPLICA}/{rid}"
    return k if name is None else f"{k}/{name}"


def status_key(namespace: str, service: str, instance_id: str) -> str:
    """Liveliness token key `<ns>/status/<service>/<id>`."""
    return f"{validate_namespace(namespace)}/{STATUS}/{service}/{instance_id}"
