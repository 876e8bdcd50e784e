"""``aisdf map save DIR | load DIR | export``: map files of a running stack (``aisdf.mapfiles``).

Each subcommand takes the services' connection flags (namespace, Zenoh) and ``--timeout``,
prints one line saying what it did, and exits non-zero with one sentence when it cannot.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from . import mapfiles, transport
from .config import ServiceConfig, add_common_args, config_from_args


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="map_cmd", required=True)
    s = sub.add_parser("save", help="write the running mapper's map to a folder (map.pt, map.json)",
                       description="Gets the map from the running mapper (<namespace>/control/mapper/save) and "
                       "writes the folder DIR atomically: map.pt (the mapper's checkpoint) and map.json. An existing "
                       "map folder is replaced; any other non-empty folder is refused.")
    s.add_argument("dir", metavar="DIR", help="the map folder to write")
    ld = sub.add_parser("load", help="replace the running mapper's map with a saved one",
                        description="Sends the map of DIR (a map folder, or a folder of map folders: the newest) to "
                        "the running mapper (<namespace>/control/mapper/load), which checks it (no code in the file "
                        "is ever run), replaces its map with it in a new epoch and publishes it at once.")
    ld.add_argument("dir", metavar="DIR", help="a map folder, or a folder holding map folders (the newest is loaded)")
    e = sub.add_parser("export", help="write the mesh (query/mesh) and the surfels (map/surfels) as PLY files",
                       description="Writes the query service's mesh of the current map and the mapper's surfel map "
                       "(each surfel two triangles, coloured by Atlanta direction) as PLY files.")
    e.add_argument("--mesh", metavar="FILE.ply", help="write the mesh here")
    e.add_argument("--surfels", metavar="FILE.ply", help="write the surfels here")
    e.add_argument("--resolution", type=float, metavar="M", help="mesh voxel size in metres (default: the service's)")
    for q in (s, ld, e):
        add_common_args(q)
        q.add_argument("--timeout", type=float, default=mapfiles.DEFAULT_TIMEOUT_S, metavar="S",
                       help=f"seconds to wait for the service (default {mapfiles.DEFAULT_TIMEOUT_S:.0f})")
        q.set_defaults(fn=main)


def _run(args: argparse.Namespace, cfg: ServiceConfig) -> str:
    ns, t = cfg.namespace, args.timeout
    if args.map_cmd == "load":
        folder = Path(args.dir)
        if folder.is_dir() and mapfiles.read_meta(folder) is None:
            folder = mapfiles.newest_map(folder) or folder  # a folder of maps: the newest
        mapfiles.read_map_folder(folder)  # a bad folder is refused before any connection
    if args.map_cmd == "export" and not (args.mesh or args.surfels):
        raise ValueError("nothing to export: give --mesh FILE.ply, --surfels FILE.ply or both")
    with transport.open_session(cfg.zenoh) as session:
        if args.map_cmd == "save":
            path = mapfiles.save_map(session, ns, args.dir, t)
            m = mapfiles.read_meta(path) or {}
            return (f"saved the map of '{ns}' to {path}: {m.get('keyframes')} keyframes, map version "
                    f"{m.get('map_version')} ({m.get('kind')}, {m.get('submaps')} submaps)")
        if args.map_cmd == "load":
            r = mapfiles.load_map(session, ns, folder, t)
            return (f"loaded {folder.absolute()} into the mapper of '{ns}': {r.get('keyframes')} keyframes, "
                    f"map version {r.get('version')}, epoch {r.get('epoch')}")
        done = mapfiles.export(session, ns, args.mesh, args.surfels, args.resolution, t)
        parts = []
        if "mesh" in done:
            m = done["mesh"]
            parts.append(f"mesh {m['path']} ({m['faces']} faces, map version {m['map_version']})")
        if "surfels" in done:
            m = done["surfels"]
            parts.append(f"surfels {m['path']} ({m['surfels']} surfels, map version {m['version']})")
        return "exported " + " and ".join(parts)


def main(args: argparse.Namespace) -> None:
    cfg = config_from_args(ServiceConfig, args)
    try:
        print(_run(args, cfg), flush=True)
    except (ValueError, RuntimeError, OSError) as e:
        raise SystemExit(f"aisdf map {args.map_cmd}: {e}") from None
