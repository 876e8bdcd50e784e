"""ROS 2 service interfaces for a ``rosbags`` typestore: AiSDF's own ``aisdf/srv/
GetDistanceWindow`` and the standard services the middleware serves or calls (``std_srvs``'
Trigger, SetBool and Empty; ``example_interfaces/srv/AddTwoInts``), and the service type
hash rmw_zenoh puts in its key expressions and liveliness tokens.

rosbags ships message types only; a service ``pkg/srv/Name`` is registered here as the three
messages rosidl generates for it: ``Name_Request``, ``Name_Response`` and ``Name_Event``
(``service_msgs/msg/ServiceEventInfo info``, ``Name_Request[<=1] request``,
``Name_Response[<=1] response``), so a ROS 2 user's rosbags decodes them
(:func:`register_interfaces`).

The service type hash (REP-2016, RIHS01, Iron/Jazzy on) is not a message's: it is the SHA-256
of the JSON type description of the *service* type, a struct with the fields
``request_message``, ``response_message`` and ``event_message`` (nested ``Name_Request``,
``Name_Response``, ``Name_Event``), whose referenced type descriptions are every type those
reach, sorted by name (:func:`service_type_hash`). As rosidl does, a ``.msg`` ``char`` is a
``uint8`` in the description (rosidl_adapter maps it so; ServiceEventInfo's ``char[16]
client_gid`` is ``FIELD_TYPE_UINT8_ARRAY`` in the generated code) and an empty struct has
the member ``uint8 structure_needs_at_least_one_member``.
"""
from __future__ import annotations

import hashlib
import json

from .rmw_names import HUMBLE_TYPE_HASH

GET_DISTANCE_WINDOW = "aisdf/srv/GetDistanceWindow"
TRIGGER = "std_srvs/srv/Trigger"

GET_DISTANCE_WINDOW_SRV = """\
# Request
geometry_msgs/Point aabb_min_m       # the box's lowest corner, in the map's fixed frame
geometry_msgs/Vector3 aabb_size_m    # its size along x, y, z
float32 voxel_size_m                 # the spacing of the samples
bool gradient                        # also the distance's gradient
---
# Response
bool success
string message                       # why not, when success is false
std_msgs/Header header               # frame_id: the map's fixed frame; stamp: when the map was made
geometry_msgs/Point origin_m         # the first sample's position (the box's lowest corner)
std_msgs/Float32MultiArray esdf_and_gradients  # dims x, y, z[, channel]: distance (m), then gradient x y z
uint64 map_version
"""

SERVICES = {  # service type -> its .srv text
    GET_DISTANCE_WINDOW: GET_DISTANCE_WINDOW_SRV,
    TRIGGER: "---\nbool success   # indicate successful run of triggered service\nstring message # informational\n",
    "std_srvs/srv/SetBool": "bool data\n---\nbool success\nstring message\n",
    "std_srvs/srv/Empty": "---\n",
    "example_interfaces/srv/AddTwoInts": "int64 a\nint64 b\n---\nint64 sum\n",
}

# REP-2016 / type_description_interfaces/msg/FieldType ids
_TYPE_IDS = {"nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8,
             "uint64": 9, "float32": 10, "float64": 11, "float128": 12, "char": 3, "bool": 15, "byte": 16,
             "string": 17, "bounded_string": 21}
_ARRAY, _BOUNDED_SEQUENCE, _SEQUENCE = 48, 96, 144
_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"
_PLACEHOLDER = "structure_needs_at_least_one_member"


# ----------------------------------------------------------------------------- names


def _split(srvtype: str) -> tuple[str, str]:
    parts = srvtype.split("/")
    if len(parts) != 3 or parts[1] != "srv" or not all(parts):
        raise ValueError(f"ROS service type {srvtype!r} is not of the form package/srv/Name")
    return parts[0], parts[2]


def request_type(srvtype: str) -> str:
    """``std_srvs/srv/Trigger`` -> ``std_srvs/srv/Trigger_Request``."""
    _split(srvtype)
    return f"{srvtype}_Request"


def response_type(srvtype: str) -> str:
    _split(srvtype)
    return f"{srvtype}_Response"


def event_type(srvtype: str) -> str:
    _split(srvtype)
    return f"{srvtype}_Event"


def split_srv(text: str) -> tuple[str, str]:
    """A ``.srv`` text -> (request, response) ``.msg`` texts (split at the ``---`` line)."""
    lines = text.splitlines()
    cut = [i for i, line in enumerate(lines) if line.strip() == "---"]
    if len(cut) != 1:
        raise ValueError(f"a .srv definition has exactly one '---' line, this one has {len(cut)}")
    return "\n".join(lines[:cut[0]]) + "\n", "\n".join(lines[cut[0] + 1:]) + "\n"


# ----------------------------------------------------------------------------- registration


def _parse(text: str, name: str) -> dict:
    """rosbags' .msg parser, keeping ``pkg/srv/`` names (it files every non-msg name under
    ``pkg/<dir>/msg/``)."""
    from rosbags.typesys import get_types_from_msg
    from rosbags.typesys.base import Nodetype

    def fix(n: str) -> str:
        return n.replace("/srv/msg/", "/srv/")

    def fixdesc(d):
        if d[0] == Nodetype.NAME:
            return (d[0], fix(d[1]))
        if d[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return (d[0], (fixdesc(d[1][0]), d[1][1]))
        return d

    return {fix(k): (consts, [(f, fixdesc(d)) for f, d in fields])
            for k, (consts, fields) in get_types_from_msg(text, name).items()}


def _event_typesdict(srvtype: str) -> dict:
    return _parse(f"service_msgs/msg/ServiceEventInfo info\n{request_type(srvtype)}[<=1] request\n"
                  f"{response_type(srvtype)}[<=1] response\n", event_type(srvtype))


def service_typesdict(srvtype: str, definition: str, event: bool = True) -> dict:
    """The rosbags typesdict of a service's _Request, _Response and (``event``) _Event messages."""
    _split(srvtype)
    req, resp = split_srv(definition)
    types = {}
    types.update(_parse(req, request_type(srvtype)))
    types.update(_parse(resp, response_type(srvtype)))
    if event:
        types.update(_event_typesdict(srvtype))
    return types


def register_service(typestore, srvtype: str, definition: str) -> None:
    """Register a service's messages into ``typestore`` (idempotent; ``ValueError`` if one is
    already there with another definition). The _Event message only where the typestore has
    ``service_msgs`` (Iron on; Humble has no service introspection)."""
    types = service_typesdict(srvtype, definition, event=_EVENT_INFO in typestore.fielddefs)
    def same(a, b) -> bool:  # rosbags stores an empty struct with rosidl's placeholder member
        a, b = ([(n.lower(), d) for n, d in x if n != _PLACEHOLDER] for x in (a, b))
        return a == b

    for k, (_, fields) in types.items():
        have = typestore.fielddefs.get(k)
        if have and not same(have[1], fields):
            raise ValueError(f"{k} is already in the typestore with another definition")
    new = {k: v for k, v in types.items() if k not in typestore.fielddefs}
    if new:
        typestore.register(new)


def register_interfaces(typestore) -> None:
    """Register AiSDF's services and the standard ones of :data:`SERVICES` (idempotent)."""
    for srvtype, definition in SERVICES.items():
        register_service(typestore, srvtype, definition)


def ensure_service(typestore, srvtype: str) -> None:
    """Make ``srvtype``'s messages available, from :data:`SERVICES` if the typestore lacks them."""
    if all(t in typestore.fielddefs for t in (request_type(srvtype), response_type(srvtype))):
        if event_type(srvtype) not in typestore.fielddefs and _EVENT_INFO in typestore.fielddefs:
            typestore.register(_event_typesdict(srvtype))  # registered by hand: the hash needs _Event
        return
    if srvtype not in SERVICES:
        raise ValueError(f"unknown service type {srvtype!r}: register it first "
                         "(aisdf.ros.interfaces.register_service(typestore, type, srv text))")
    register_service(typestore, srvtype, SERVICES[srvtype])


# ----------------------------------------------------------------------------- hashes


def rihs01(fielddefs: dict, typename: str) -> str:
    """REP-2016's RIHS01 hash of ``typename`` from a rosbags typesdict (``typestore.fielddefs``
    plus any extra structs)."""
    from rosbags.typesys.base import Nodetype

    structs: dict[str, dict] = {}

    def field(name: str, desc) -> dict:
        increment = capacity = string_capacity = 0
        nested = ""
        if desc[0] == Nodetype.ARRAY:
            increment, capacity, desc = _ARRAY, desc[1][1], desc[1][0]
        elif desc[0] == Nodetype.SEQUENCE:
            increment, capacity = (_BOUNDED_SEQUENCE, desc[1][1]) if desc[1][1] else (_SEQUENCE, 0)
            desc = desc[1][0]
        if desc[0] == Nodetype.NAME:
            tid, nested = increment + _TYPE_IDS["nested"], desc[1]
            struct(nested)
        elif desc[1][0] == "string" and desc[1][1]:
            tid, string_capacity = increment + _TYPE_IDS["bounded_string"], desc[1][1]
        else:
            tid = increment + _TYPE_IDS[desc[1][0]]
        return {"name": name, "type": {"type_id": tid, "capacity": capacity, "string_capacity": string_capacity,
                                       "nested_type_name": nested}}

    def struct(name: str) -> dict:
        if name not in structs:
            if name not in fielddefs:
                raise KeyError(f"type {name!r} is not in the typestore")
            fields = fielddefs[name][1] or [(_PLACEHOLDER, (Nodetype.BASE, ("uint8", 0)))]
            structs[name] = {"type_name": name, "fields": []}
            structs[name]["fields"] = [field(n, d) for n, d in fields]
        return structs[name]

    top = struct(typename)
    desc = {"type_description": top,
            "referenced_type_descriptions": [s for n, s in sorted(structs.items()) if n != typename]}
    return "RIHS01_" + hashlib.sha256(json.dumps(desc).encode()).hexdigest()


def service_type_hash(typestore, srvtype: str, distro: str = "jazzy") -> str:
    """The service type hash of rmw_zenoh's keys and tokens (``TypeHashNotSupported`` on Humble)."""
    if distro.lower() == "humble":
        return HUMBLE_TYPE_HASH
    ensure_service(typestore, srvtype)
    fielddefs = dict(typestore.fielddefs)
    fielddefs[srvtype] = ([], [])
    fielddefs.update(_parse(f"{request_type(srvtype)} request_message\n{response_type(srvtype)} response_message\n"
                            f"{event_type(srvtype)} event_message\n", srvtype))
    return rihs01(fielddefs, srvtype)
