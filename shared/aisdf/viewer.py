"""``aisdf view``: a live rerun view of a running stack, from the wire protocol alone.

Subscribes to ``<ns>/keyframes``, ``<ns>/map/surfels`` and ``<ns>/map/weights`` (or, from a
submap mapper, ``<ns>/map/index``: protocol 1.3; only for the map version), asks
``<ns>/query/mesh`` every ``mesh_period_s`` and logs to rerun as things arrive.

What is logged where is :class:`aisdf.mapview.MapView`'s (cameras, paths, the surfel map
and the Atlanta frame, the mesh, stats; malformed messages are logged, counted and
skipped: they never stop the viewer). A keyframe seen again (a 1.2 frontend resends until
acknowledged) is logged once per (sensor, frame_id).

Default: spawns the rerun viewer window; ``--save FILE.rrd`` records to a file instead
(no window, no server). Only protocol messages are used (aisdf.protocol, aisdf.keys,
aisdf.transport); nothing of the mapper's internals. rerun-sdk is the optional extra
``aisdf[viewer]``.
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
import uuid
from pathlib import Path

from pydantic import Field

from . import keys, protocol, query_messages, transport
from .config import ServiceConfig, add_common_args, config_from_args, service_setup
from .mapview import MapView, blueprint, import_rerun

log = logging.getLogger("aisdf.viewer")


class ViewerConfig(ServiceConfig):
    """``aisdf view``: the transport settings every service has, plus what to show."""

    save: Path | None = Field(None, description="record to this .rrd file instead of spawning the viewer window")
    mesh_period_s: float = Field(5.0, ge=0, description="ask query/mesh this often (0: never)")
    mesh_resolution: float = Field(0.08, gt=0, description="marching-cubes voxel size asked for (m)")
    mesh_timeout_s: float = Field(60.0, gt=0, description="give up on a mesh request after this long")
    duration_s: float | None = Field(None, gt=0, description="stop after this long (default: until Ctrl-C/SIGTERM)")
    frustum_m: float = Field(0.3, gt=0, description="drawn depth of the camera frustum (m)")
    surfel_thickness_m: float = Field(0.01, gt=0, description="drawn thickness of a surfel (m)")
    keyframe_queue: int = Field(256, ge=1, description="keyframes waiting to be logged; beyond, new ones are dropped")


class LiveViewer:
    """Zenoh wiring: subscriptions feed a worker thread that logs; another thread asks for meshes."""

    DECODERS = {keys.KEYFRAMES: protocol.Keyframe, keys.MAP_SURFELS: protocol.SurfelMap,
                keys.MAP_WEIGHTS: protocol.WeightSnapshot, keys.MAP_INDEX: protocol.SubmapIndex}
    LATEST = (keys.MAP_SURFELS, keys.MAP_WEIGHTS, keys.MAP_INDEX)  # only the newest of each waits

    def __init__(self, session, view: MapView, namespace: str = keys.DEFAULT_NAMESPACE,
                 mesh_period_s: float = 5.0, mesh_resolution: float = 0.08, mesh_timeout_s: float = 60.0,
                 keyframe_queue: int = 256):
        self.session = session
        self.view = view
        self.ns = keys.validate_namespace(namespace)
        self.mesh_period_s = mesh_period_s
        self.mesh_resolution = mesh_resolution
        self.mesh_timeout_s = mesh_timeout_s
        self.keyframes: queue.Queue = queue.Queue(maxsize=keyframe_queue)
        self.latest: dict[str, object] = {}  # LATEST keys: only the newest waits
        self.dropped = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._decls: list = []
        self._threads = [threading.Thread(target=self._work, name="viewer-log", daemon=True)]
        if mesh_period_s > 0:
            self._threads.append(threading.Thread(target=self._meshes, name="viewer-mesh", daemon=True))

    def start(self) -> "LiveViewer":
        for name in (keys.KEYFRAMES, *self.LATEST):
            self._decls.append(self.session.declare_subscriber(
                keys.key(self.ns, name), lambda s, name=name: self._on_sample(name, s)))
        # Subscribed: say so (the demo and the tests wait for this token before starting a frontend).
        self._decls.append(self.session.liveliness().declare_token(
            keys.status_key(self.ns, "viewer", uuid.uuid4().hex[:8])))
        for t in self._threads:
            t.start()
        for name in self.LATEST:  # the latest map at once, not at the next publication
            for reply in self.session.get(keys.key(self.ns, name), timeout=2.0):
                if reply.ok is not None:
                    self._offer(name, transport.payload_bytes(reply.ok.payload))
        return self

    def _on_sample(self, name: str, sample) -> None:
        self._offer(name, transport.payload_bytes(sample.payload))

    def _offer(self, name: str, raw: bytes) -> None:
        """Decode on arrival (a malformed message is counted and skipped here); queue for logging."""
        try:
            msg = self.DECODERS[name].from_msg(protocol.unpack(raw))
        except protocol.ProtocolError as e:
            self.view.malformed(name, e.message)
            return
        except Exception as e:  # noqa: BLE001 - never let a message break the subscription
            self.view.malformed(name, f"{type(e).__name__}: {e}")
            return
        with self._cond:
            if name == keys.KEYFRAMES:
                try:
                    self.keyframes.put_nowait(msg)
                except queue.Full:
                    self.dropped += 1
                    log.warning("keyframe queue full (%d): dropped one (%d so far)", self.keyframes.maxsize,
                                self.dropped)
            else:  # only the newest map waits: (epoch, version) order, as the protocol says
                held = self.latest.get(name)
                if held is None or (msg.epoch, msg.version) > (held.epoch, held.version):
                    self.latest[name] = msg
            self._cond.notify()

    def _log(self, name: str, msg) -> None:
        try:
            {keys.KEYFRAMES: self.view.keyframe, keys.MAP_SURFELS: self.view.surfel_map,
             keys.MAP_WEIGHTS: self.view.weights, keys.MAP_INDEX: self.view.index}[name](msg)
        except Exception as e:  # noqa: BLE001 - a message that decodes but cannot be drawn is skipped too
            log.exception("could not log a message on %s", name)
            self.view.malformed(name, f"{type(e).__name__}: {e}")

    def _drain(self) -> bool:
        did = False
        while True:
            try:
                kf = self.keyframes.get_nowait()
            except queue.Empty:
                break
            self._log(keys.KEYFRAMES, kf)
            did = True
        for name in self.LATEST:
            with self._cond:
                msg = self.latest.pop(name, None)
            if msg is not None:
                self._log(name, msg)
                did = True
        return did

    def _work(self) -> None:
        while not self._stop.is_set():
            if not self._drain():
                with self._cond:
                    self._cond.wait(0.2)
        self._drain()  # what arrived before the stop is still recorded

    def _meshes(self) -> None:
        key = keys.key(self.ns, keys.QUERY_MESH)
        request = query_messages.MeshRequest(self.mesh_resolution).to_msg()
        while not self._stop.is_set():
            t = time.monotonic()
            asked = False
            v = self.view
            if v.counts["meshes"] == 0 or v.map_key is None or v.map_key[1] != v.counts["mesh_version"]:
                asked = True
                try:
                    reply = query_messages.MeshReply.from_msg(transport.query(self.session, key, request,
                                                                        self.mesh_timeout_s))
                    v.mesh(reply)
                    log.info("mesh of map v%d: %d vertices, %d faces", reply.map_version, len(reply.vertices),
                             len(reply.faces))
                except protocol.ProtocolError as e:
                    if e.code in ("no_map", "busy"):
                        log.info("no mesh yet: %s", e.message)
                    else:
                        v.malformed(keys.QUERY_MESH, f"{e.code}: {e.message}")
                except TimeoutError as e:
                    log.info("no mesh: %s", e)
                except Exception as e:  # noqa: BLE001 - e.g. the session closing under a request at shutdown
                    if not self._stop.is_set():
                        log.warning("mesh request failed: %s", e)
            # A mesh at most every period, and never more often than every 2x the last one's time:
            # meshes take at most half of the query service's mesh worker on a busy machine.
            took = time.monotonic() - t if asked else 0.0
            self._stop.wait(max(self.mesh_period_s - took, took))

    def close(self, timeout: float = 5.0) -> None:
        """Stop taking messages, record what is queued, stop the threads."""
        for d in self._decls:
            d.undeclare()
        self._decls.clear()
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout)


def summary_line(view: MapView, dropped: int, save: Path | None) -> str:
    c = view.counts
    where = f"; wrote {save}" if save else ""
    return (f"viewer: {c['keyframes']} keyframes ({c['repeats']} repeats skipped, {dropped} dropped), "
            f"{c['surfel_maps']} surfel maps (last: {c['surfels']} surfels), {c['weights']} weight snapshots, "
            f"{c['indexes']} submap indexes, {c['meshes']} meshes, {c['malformed']} malformed messages skipped{where}")


def run(cfg: ViewerConfig, stop: threading.Event | None = None) -> dict:
    """Run until ``stop`` is set (or ``cfg.duration_s``); returns the counters."""
    rr = import_rerun()
    stop = stop or threading.Event()
    rec = rr.RecordingStream("aisdf", recording_id=f"aisdf-{cfg.namespace}-{uuid.uuid4().hex[:8]}")
    if cfg.save:
        Path(cfg.save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(cfg.save), default_blueprint=blueprint(rr))
    else:
        try:
            rec.spawn(default_blueprint=blueprint(rr))
        except Exception as e:  # noqa: BLE001
            raise SystemExit(f"could not start the rerun viewer ({e}); record with --save FILE.rrd instead") from None
    view = MapView(rec, cfg.frustum_m, cfg.surfel_thickness_m)
    session = transport.open_session(cfg.zenoh)
    viewer = None
    try:
        viewer = LiveViewer(session, view, cfg.namespace, cfg.mesh_period_s, cfg.mesh_resolution,
                            cfg.mesh_timeout_s, cfg.keyframe_queue).start()
        log.info("viewing namespace %s%s", cfg.namespace, f", recording to {cfg.save}" if cfg.save else "")
        end = time.monotonic() + cfg.duration_s if cfg.duration_s else None
        while not stop.wait(0.5):
            if end is not None and time.monotonic() >= end:
                break
    finally:
        if viewer is not None:
            viewer.close()
        rec.flush(timeout_sec=30.0)
        rec.disconnect()
        session.close()
    print(summary_line(view, viewer.dropped if viewer else 0, cfg.save), flush=True)
    return dict(view.counts, dropped=viewer.dropped if viewer else 0)


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    add_common_args(p)
    p.add_argument("--save", metavar="FILE.rrd", help="record to this file instead of spawning the viewer window")
    p.add_argument("--mesh-period", type=float, metavar="S",
                   help="ask query/mesh every S seconds (default 5; 0: never)")
    p.add_argument("--mesh-resolution", type=float, metavar="M", help="mesh voxel size in metres (default 0.08)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C/SIGTERM)")
    return p


def main(args: argparse.Namespace) -> None:
    cfg = config_from_args(ViewerConfig, args, {"save": args.save, "mesh_period_s": args.mesh_period,
                                                "mesh_resolution": args.mesh_resolution,
                                                "duration_s": args.duration})
    import_rerun()  # a clear message before anything starts when the extra is missing
    stop = service_setup(cfg, "viewer")
    logging.getLogger().setLevel(cfg.log_level)  # the umbrella command configured logging already
    run(cfg, stop)
