"""Map files: save the map of a running mapper to a folder, load it back into a mapper,
export its mesh and surfels as PLY.

A map folder holds ``map.pt`` (the mapper's checkpoint dict, ``{"pipeline", "version",
"epoch", "seen"}``, written with torch.save, as the mapper's checkpoint directory holds it)
and ``map.json`` (metadata: format, kind, keyframes, submaps, map version, epoch, created
date, aisdf version).

Loading never executes code from a file: ``map.pt`` is read with torch's weights-only
unpickler, which here admits only numpy's array, dtype and scalar reconstruction. Anything
else (bad bytes, another format, a pickle naming other globals) is a ``ValueError`` that
says so in a sentence.

The mapper answers two control keys (an extension, not part of protocol v1):
``<ns>/control/mapper/save`` (``{"v": 1}`` -> ``{"v": 1, "map": BIN, "meta": {...}}``) and
``<ns>/control/mapper/load`` (``{"v": 1, "map": BIN}`` -> ``{"v": 1, "version", "epoch",
"keyframes", "kind", "submaps"}``). ``save_map``, ``load_map``, ``newest_map`` and
``export`` are their clients (the ``aisdf map`` command and the ROS 2 node use them).
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import os
import re
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, keys, protocol, query_messages, transport

SAVE_KEY = "control/mapper/save"
LOAD_KEY = "control/mapper/load"
FORMAT = "aisdf-map"
FORMAT_VERSION = 1
MAP_PT = "map.pt"
MAP_JSON = "map.json"
DEFAULT_TIMEOUT_S = 60.0


# ----------------------------------------------------------------------------- the safe loader


class _Refused(Exception):
    pass


def _bytes(*args):
    """``builtins.bytes`` for the unpickler: an empty array's data (``bytes()``) or a copy of
    bytes; never ``bytes(n)`` (n zero bytes: memory on a file's say)."""
    if not args:
        return b""
    if len(args) == 1 and isinstance(args[0], (bytes, bytearray)):
        return bytes(args[0])
    raise _Refused("bytes() of something other than bytes")


def _allowed_globals() -> list:
    import numpy.dtypes as nd

    core = getattr(np, "_core", None) or np.core  # numpy 2 (_core) or 1 (core)
    out: list = [np.ndarray, np.dtype, core.multiarray._reconstruct, core.multiarray.scalar, (_bytes, "builtins.bytes")]
    for name in dir(nd):
        obj = getattr(nd, name)
        if isinstance(obj, type) and issubclass(obj, np.dtype):
            out.append(obj)
    return out


def checkpoint_from_bytes(data: bytes) -> dict:
    """The checkpoint dict of ``map.pt`` bytes, read without executing anything from them.
    ``ValueError`` (one sentence) for anything that is not a mapper checkpoint."""
    import torch

    from .submaps.persist import CHECKPOINT_FORMAT as SUBMAPS_CHECKPOINT

    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) == 0:
        raise ValueError("the map is empty")
    try:
        with torch.serialization.safe_globals(_allowed_globals()):
            ck = torch.load(io.BytesIO(bytes(data)), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch and pickle raise many types; none may escape
        names = re.findall(r"GLOBAL:? ?([\w.]+)", str(e))
        if names or isinstance(e, _Refused):
            what = f"names {names[0]}, which loading it would call" if names else f"asks for {e}"
            raise ValueError(f"refused: the file is not a map; it {what} (nothing was run)") from None
        raise ValueError(f"not a map file: it is no checkpoint aisdf writes ({type(e).__name__})") from None
    p = ck.get("pipeline") if isinstance(ck, dict) else None
    if not isinstance(p, dict) or (p.get("format") != SUBMAPS_CHECKPOINT and "trainer" not in p):
        raise ValueError("not a map file: no mapper checkpoint in it")
    for name in ("version", "epoch"):
        if not isinstance(ck.get(name, 0), int):
            raise ValueError(f"not a map file: '{name}' is not an integer")
    return ck


def checkpoint_to_bytes(ck: dict) -> bytes:
    import torch

    buf = io.BytesIO()
    torch.save(ck, buf)
    return buf.getvalue()


@dataclass
class LoadedMap:
    """A map checked and restored: the mapper, its version and the keyframes it holds."""

    pipeline: Any
    version: int
    seen: set[tuple[str, int]]


def restore_checked(data: bytes) -> LoadedMap:
    """``map.pt`` bytes -> a restored mapper, or ``ValueError``: nothing of a bad file is used."""
    from .mapper.factory import restore_mapper

    ck = checkpoint_from_bytes(data)
    try:
        pipe = restore_mapper(ck["pipeline"])
        seen = {(str(s), int(i)) for s, i in ck.get("seen", [])} | set(pipe.keyframe_keys())
    except Exception as e:  # noqa: BLE001 - a malformed checkpoint fails in many places
        raise ValueError(f"not a usable map: its mapper checkpoint does not restore ({type(e).__name__}: {e})") from None
    if not pipe.n_keyframes:
        raise ValueError("the map has no keyframes")
    return LoadedMap(pipe, int(ck.get("version", 0)), seen)


def metadata(ck: dict, pipeline) -> dict:
    """``map.json`` of a checkpoint dict and the mapper it was taken from."""
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": pipeline.kind,
            "keyframes": pipeline.n_keyframes, "submaps": len(getattr(pipeline, "submaps", None) or {}),
            "map_version": int(ck.get("version", 0)), "epoch": int(ck.get("epoch", 0)),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
            "aisdf": __version__}


# ----------------------------------------------------------------------------- the mapper's side


def save_reply(ck: dict, pipeline) -> dict:
    """The ``control/mapper/save`` reply: the mapper's checkpoint dict as map.pt bytes, and map.json."""
    return {"v": protocol.VERSION, "map": checkpoint_to_bytes(ck), "meta": metadata(ck, pipeline)}


def read_load_request(req: dict) -> LoadedMap:
    """A ``control/mapper/load`` request's map, restored; ``ProtocolError`` (bad_request)."""
    data = req.get("map")
    if not isinstance(data, (bytes, bytearray)):
        raise protocol.ProtocolError("bad_request", "'map' must be the bytes of a map.pt")
    try:
        return restore_checked(bytes(data))
    except ValueError as e:
        raise protocol.ProtocolError("bad_request", str(e)) from None


def load_reply(pipeline, version: int, epoch: int) -> dict:
    return {"v": protocol.VERSION, "version": int(version), "epoch": int(epoch), "keyframes": pipeline.n_keyframes,
            "kind": pipeline.kind, "submaps": len(getattr(pipeline, "submaps", None) or {})}


# ----------------------------------------------------------------------------- folders


def read_meta(folder: str | Path) -> dict | None:
    """``map.json`` of a map folder; None when ``folder`` is not one."""
    try:
        meta = json.loads((Path(folder) / MAP_JSON).read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and meta.get("format") == FORMAT else None


def read_map_folder(folder: str | Path) -> tuple[bytes, dict]:
    """(``map.pt`` bytes, ``map.json``) of a map folder, or ``ValueError`` saying what is wrong."""
    d = Path(folder)
    if not d.is_dir():
        raise ValueError(f"{d} is not a folder")
    meta = read_meta(d)
    if meta is None:
        raise ValueError(f"{d} is not a map folder (no {MAP_JSON} of format {FORMAT})")
    if int(meta.get("format_version", 0)) > FORMAT_VERSION:
        raise ValueError(f"{d}: map format {meta.get('format_version')} is newer than this aisdf's {FORMAT_VERSION}")
    try:
        data = (d / MAP_PT).read_bytes()
    except OSError as e:
        raise ValueError(f"{d}: cannot read {MAP_PT} ({e.strerror or e})") from None
    return data, meta


def write_map_folder(folder: str | Path, data: bytes, meta: dict) -> Path:
    """Write a map folder atomically (a temporary folder renamed into place). An existing map
    folder is replaced; any other non-empty folder (or a file) is refused."""
    d = Path(folder).absolute()
    if d.exists() and not d.is_dir():
        raise ValueError(f"{d} exists and is not a folder")
    if d.is_dir() and any(d.iterdir()) and read_meta(d) is None:
        raise ValueError(f"{d} is not empty and not a map folder: refusing to overwrite it")
    d.parent.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:8]
    tmp = d.parent / f".{d.name}.tmp-{tag}"
    tmp.mkdir()
    try:
        for name, blob in ((MAP_PT, data), (MAP_JSON, (json.dumps(meta, indent=2) + "\n").encode())):
            with open(tmp / name, "wb") as f:
                f.write(blob)
                f.flush()
                os.fsync(f.fileno())
        old = None
        if d.is_dir() and any(d.iterdir()):  # an older map: moved aside, then removed
            old = d.parent / f".{d.name}.old-{tag}"
            d.rename(old)
        elif d.is_dir():
            d.rmdir()
        tmp.rename(d)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return d


def newest_map(folder: str | Path) -> Path | None:
    """The most recent map folder inside ``folder`` (by ``map.json``'s created date); None if none."""
    best: tuple[_dt.datetime, str] | None = None
    out = None
    root = Path(folder)
    if not root.is_dir():
        return None
    for d in root.iterdir():
        meta = read_meta(d) if d.is_dir() and not d.name.startswith(".") else None
        if meta is None or not (d / MAP_PT).is_file():
            continue
        try:
            t = _dt.datetime.fromisoformat(str(meta.get("created")))
        except ValueError:
            continue
        if t.tzinfo is None:
            t = t.replace(tzinfo=_dt.timezone.utc)
        if best is None or (t, d.name) > best:
            best, out = (t, d.name), d
    return out


# ----------------------------------------------------------------------------- clients


def _ask(session, namespace: str, name: str, msg: dict, timeout: float, what: str) -> dict:
    key = keys.key(namespace, name)
    try:
        return transport.query(session, key, msg, timeout)
    except TimeoutError:
        raise RuntimeError(f"no {what} answered on {key} within {timeout:.0f} s (is it running under namespace "
                           f"'{keys.validate_namespace(namespace)}' and reachable?)") from None
    except protocol.ProtocolError as e:
        if e.code == "no_map":
            raise RuntimeError(f"the {what} has no map yet ({e.message})") from None
        if e.code == "bad_request":  # the map (or request) itself
            raise ValueError(f"the {what} refused it: {e.message}") from None
        raise RuntimeError(f"the {what} failed: {e.message}") from None


def save_map(session, namespace: str, folder: str | Path, timeout: float = DEFAULT_TIMEOUT_S) -> Path:
    """Get the running mapper's map and write it to ``folder`` (atomically). Raises
    ``RuntimeError`` (no mapper, no map yet) or ``ValueError`` (a folder it may not write)."""
    d = Path(folder).absolute()
    if d.is_dir() and any(d.iterdir()) and read_meta(d) is None:  # refuse before the transfer
        raise ValueError(f"{d} is not empty and not a map folder: refusing to overwrite it")
    rep = _ask(session, namespace, SAVE_KEY, {"v": protocol.VERSION}, timeout, "mapper")
    data, meta = rep.get("map"), rep.get("meta")
    if not isinstance(data, (bytes, bytearray)) or not isinstance(meta, dict):
        raise RuntimeError("the mapper's reply carries no map")
    checkpoint_from_bytes(bytes(data))  # what is written is a map this module loads
    return write_map_folder(d, bytes(data), meta)


def load_map(session, namespace: str, folder: str | Path, timeout: float = DEFAULT_TIMEOUT_S) -> dict:
    """Send the map of ``folder`` to the running mapper, which replaces its map with it.
    Returns the mapper's reply: ``version``, ``epoch``, ``keyframes``, ``kind``, ``submaps``."""
    data, meta = read_map_folder(folder)
    checkpoint_from_bytes(data)  # a clear error here before anything is sent
    return _ask(session, namespace, LOAD_KEY, {"v": protocol.VERSION, "map": data, "meta": meta}, timeout, "mapper")


PALETTE = np.array([[230, 159, 0], [0, 114, 178], [0, 158, 115], [204, 121, 167], [86, 180, 233], [213, 94, 0],
                    [240, 228, 66]], np.uint8)
HORIZONTAL_COLOUR = np.array([150, 150, 150], np.uint8)  # direction -1: normal along the vertical (floors)


def surfel_triangles(surfels: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4N, 3) corners, (2N, 3) faces (facing along each normal) and (2N, 4) RGBA face
    colours of N surfels: rectangles center +- extent/2 along axis1 and axis2, coloured by
    Atlanta direction (grey for -1, one colour per horizontal direction k)."""
    c = np.asarray(surfels["center"], np.float64).reshape(-1, 3)
    a1 = np.asarray(surfels["axis1"], np.float64).reshape(-1, 3)
    a2 = np.asarray(surfels["axis2"], np.float64).reshape(-1, 3)
    e = np.asarray(surfels["extent"], np.float64).reshape(-1, 2) / 2
    n = len(c)
    u, w = a1 * e[:, :1], a2 * e[:, 1:2]
    verts = np.stack([c - u - w, c + u - w, c + u + w, c - u + w], 1).reshape(-1, 3)
    base = 4 * np.arange(n)[:, None]
    flip = np.einsum("ij,ij->i", np.cross(a1, a2), np.asarray(surfels["normal"], np.float64).reshape(-1, 3)) < 0
    quad = np.where(flip[:, None], [0, 3, 2, 0, 2, 1], [0, 1, 2, 0, 2, 3]) + base
    faces = quad.reshape(-1, 3).astype(np.int64)
    k = np.asarray(surfels["direction"]).reshape(-1)
    rgb = np.where((k < 0)[:, None], HORIZONTAL_COLOUR, PALETTE[np.maximum(k, 0) % len(PALETTE)])
    rgba = np.concatenate([rgb, np.full((n, 1), 255, np.uint8)], 1).astype(np.uint8)
    return verts, faces, np.repeat(rgba, 2, axis=0)


def export(session, namespace: str, mesh: str | Path | None = None, surfels: str | Path | None = None,
           resolution: float | None = None, timeout: float = DEFAULT_TIMEOUT_S) -> dict:
    """Write the query service's mesh (``query/mesh``) and the mapper's surfels
    (``map/surfels``) as PLY files. Returns what was written: ``mesh`` (path, map_version,
    vertices, faces) and ``surfels`` (path, version, surfels)."""
    import trimesh

    out: dict = {}
    if mesh is not None:
        msg = _ask(session, namespace, keys.QUERY_MESH, query_messages.MeshRequest(resolution).to_msg(), timeout,
                   "query service")
        rep = query_messages.MeshReply.from_msg(msg)
        path = Path(mesh)
        path.parent.mkdir(parents=True, exist_ok=True)
        trimesh.Trimesh(rep.vertices, rep.faces, process=False).export(path)
        out["mesh"] = {"path": path, "map_version": rep.map_version, "vertices": len(rep.vertices),
                       "faces": len(rep.faces)}
    if surfels is not None:
        msg = transport.get_latest(session, keys.key(namespace, keys.MAP_SURFELS), min(timeout, 10.0))
        if msg is None:
            raise RuntimeError(f"no surfel map on {keys.key(namespace, keys.MAP_SURFELS)} (is a mapper with the "
                               "Atlanta structure running, with a map yet?)")
        sm = protocol.SurfelMap.from_msg(msg)
        verts, faces, colours = surfel_triangles(sm.surfels)
        path = Path(surfels)
        path.parent.mkdir(parents=True, exist_ok=True)
        trimesh.Trimesh(verts, faces, face_colors=colours, process=False).export(path)
        out["surfels"] = {"path": path, "version": sm.version, "surfels": len(sm)}
    return out
