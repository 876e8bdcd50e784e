"""``aisdf-query``: keeps the latest map and answers ``query/sdf`` and ``query/mesh``.

It asks for the latest snapshot at start (and again until one arrives) and follows
new ones, so the order in which services start does not matter. Requests are
checked on Zenoh's thread (a malformed one is answered at once) and evaluated on
``workers`` threads; a bad request never stops the service. The sdf queue is bounded
(``queue_max``): a request that finds it full is answered at once with ``busy``, so
under overload latency stays bounded and planners hear about it instead of timing out.
A background thread bakes every new map. The answers come from :class:`aisdf.query.engine.QueryEngine`
(the engine, its baker and the served answer live in ``aisdf.query``); this module is its wiring.

Submaps (protocol 1.3): it also follows ``map/submaps/*`` (one WeightSnapshot per changed
submap) and ``map/index``. A late joiner gets ``map/submaps/**`` (every submap's latest)
and ``map/index``; when an index lists a submap at a version newer than the one held (a
lost sample), that submap is fetched with a ``get`` on its key (on the fetcher thread,
never on Zenoh's). A malformed message is logged and skipped.

Replicas (protocol 1.12): several query services may share one namespace. Each has a
replica id (``replica_id``, default ``<hostname>-<6 hex digits>``), answers its own
``query/replica/<id>/sdf`` and ``.../mesh`` beside the shared ``query/sdf`` and ``query/mesh``,
and announces itself with the liveliness tokens ``query/replica/<id>`` and
``status/query/<id>``. Every query key is declared complete, so a ``get`` with Zenoh's default
target (best matching) on a shared key is evaluated by one replica only. ``info/query``
carries the id and ``evaluated`` (requests its workers evaluated).
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time

import torch

from aisdf import keys, protocol, query_messages, transport
from aisdf.config import add_common_args, config_from_args, service_setup
from aisdf.query.engine import QueryEngine

from .config import QueryConfig, default_replica_id

log = logging.getLogger("aisdf.query")
INFO_KEY = "info/query"


class QueryNode:
    """Zenoh wiring of a QueryEngine."""

    def __init__(self, cfg: QueryConfig, session):
        self.cfg = cfg
        self.session = session
        self.engine = QueryEngine.from_config(cfg)
        self._sdf_jobs: queue.Queue = queue.Queue(maxsize=cfg.queue_max)
        self.pending = 0  # sdf requests accepted and not answered yet (waiting or being answered)
        self._pending_lock = threading.Lock()
        # planners first: while requests wait for a worker, a trailing bake answers
        self.engine.waiting = lambda: max(0, self.pending - cfg.workers)
        self.ns = cfg.namespace
        self.replica_id = cfg.replica_id or default_replica_id()
        self.answered = 0
        self.evaluated = 0  # requests the workers evaluated (answered, or an error while evaluating)
        self.errors = 0
        self.busy = 0
        self._mesh_jobs: queue.Queue = queue.Queue(maxsize=4)
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._work, args=(self._sdf_jobs,), name=f"sdf-worker-{i}", daemon=True)
            for i in range(cfg.workers)
        ] + [
            threading.Thread(target=self._work, args=(self._mesh_jobs,), name="mesh-worker", daemon=True),
            threading.Thread(target=self._fetch_latest, name="latest", daemon=True),
        ]
        self._decls = []
        self._want: set[str] = set()  # submap ids to get ("**": all of them)
        self._want_lock = threading.Lock()
        self._want_event = threading.Event()
        self.fetched = 0  # submap snapshots taken from gets (late join, lost samples)

    # ------------------------------------------------------------------ map following

    def _on_submap(self, msg: dict, key: str | None = None) -> bool:
        try:
            snap = protocol.WeightSnapshot.from_msg(msg)
            if snap.submap is None:
                raise ValueError("a message on map/submaps/<id> without 'submap'")
            sid = snap.submap["id"]
            last = key.rsplit("/", 1)[-1] if key is not None else None
            if last is not None and "*" not in last and last != sid:
                raise ValueError(f"submap {sid!r} published on {key!r}")
            if self.engine.set_submap(snap):
                log.debug("submap %s version %d (step %d) loaded", sid, snap.version, snap.step)
                return True
        except (protocol.ProtocolError, ValueError, KeyError, TypeError, RuntimeError) as e:
            log.warning("rejected a submap snapshot: %s", e)
        return False

    def _on_index(self, msg: dict) -> None:
        try:
            idx = protocol.SubmapIndex.from_msg(msg)
            want = self.engine.set_index(idx)
        except (protocol.ProtocolError, ValueError, KeyError, TypeError) as e:
            log.warning("rejected a submap index: %s", e)
            return
        if want is None or want:
            with self._want_lock:
                self._want.update(["**"] if want is None else want)
            self._want_event.set()

    def _get_submaps(self, sid: str) -> int:
        """Get ``map/submaps/<sid>`` (``**``: all); returns how many were taken."""
        n = 0
        key = keys.key(self.ns, f"{keys.MAP_SUBMAPS}/{sid}")
        try:
            replies = list(self.session.get(key, timeout=self.cfg.submap_get_timeout_s))
        except Exception as e:  # noqa: BLE001 - a transport failure: try again at the next index
            log.warning("get %s failed: %s", key, e)
            return 0
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                msg = protocol.unpack(transport.payload_bytes(reply.ok.payload))
            except protocol.ProtocolError as e:
                log.warning("malformed reply on %s: %s", key, e.message)
                continue
            n += self._on_submap(msg, str(reply.ok.key_expr))
        self.fetched += n
        return n

    def _on_weights(self, msg: dict) -> None:
        try:
            snap = protocol.WeightSnapshot.from_msg(msg)
            if self.engine.set_weights(snap):
                log.info("map version %d (step %d) loaded", snap.version, snap.step)
        except (protocol.ProtocolError, ValueError, KeyError, RuntimeError) as e:
            log.warning("rejected a weight snapshot: %s", e)

    def _on_surfels(self, msg: dict) -> None:
        try:
            smap = protocol.SurfelMap.from_msg(msg)
            if self.engine.set_surfels(smap):
                log.info("surfel map version %d with %d surfels loaded", smap.version, len(smap))
        except (protocol.ProtocolError, ValueError, KeyError) as e:
            log.warning("rejected a surfel map: %s", e)

    def _subscriber(self, name: str, fn, with_key: bool = False):
        def cb(sample):
            try:
                msg = protocol.unpack(transport.payload_bytes(sample.payload))
                fn(msg, str(sample.key_expr)) if with_key else fn(msg)
            except protocol.ProtocolError as e:
                log.warning("malformed message on %s: %s", name, e.message)
            except Exception:  # noqa: BLE001 - a message never stops the service
                log.exception("error handling a message on %s", name)

        return self.session.declare_subscriber(keys.key(self.ns, name), cb)

    def _fetch_latest(self) -> None:
        """Late joiner: get the latest weights, surfels, submaps and index until a map
        arrives; then get the submaps an index says are missing."""
        while not self._stop.is_set() and self.engine.state is None:
            for name, fn in ((keys.MAP_WEIGHTS, self._on_weights), (keys.MAP_SURFELS, self._on_surfels)):
                msg = transport.get_latest(self.session, keys.key(self.ns, name), timeout=1.0)
                if msg is not None:
                    fn(msg)
            self._get_submaps("**")
            msg = transport.get_latest(self.session, keys.key(self.ns, keys.MAP_INDEX), timeout=1.0)
            if msg is not None:
                self._on_index(msg)
            if self.engine.state is not None:
                break
            self._stop.wait(self.cfg.weights_retry_s)
        while not self._stop.is_set():
            if not self._want_event.wait(0.5):
                continue
            self._want_event.clear()
            with self._want_lock:
                want, self._want = self._want, set()
            for sid in (["**"] if "**" in want or len(want) > 8 else sorted(want)):
                if self._stop.is_set():
                    return
                n = self._get_submaps(sid)
                log.info("got %d submap snapshot(s) on map/submaps/%s (the index listed newer ones)", n, sid)

    # ------------------------------------------------------------------ requests

    def _reply_err(self, q, e: protocol.ProtocolError) -> None:
        self.errors += 1
        q.reply_err(protocol.pack(protocol.error_message(e.code, e.message)), encoding=transport.ENCODING)

    def _accept(self, q, decode, jobs: queue.Queue) -> None:
        """Zenoh thread: decode and validate now (errors answered at once), evaluate later."""
        try:
            req = decode(protocol.unpack(transport.payload_bytes(q.payload)))
            if self.engine.state is None:
                raise protocol.ProtocolError("no_map", "no map yet: the mapper has not published weights")
        except protocol.ProtocolError as e:
            log.info("rejected request: %s", e)
            self._reply_err(q, e)
            return
        except Exception as e:  # noqa: BLE001 - never stop on a request
            log.exception("internal error decoding a request")
            self._reply_err(q, protocol.ProtocolError("internal", f"{type(e).__name__}: {e}"))
            return
        sdf = jobs is self._sdf_jobs
        if sdf:
            with self._pending_lock:
                self.pending += 1
        try:
            jobs.put_nowait((q, req))
        except queue.Full:
            if sdf:
                with self._pending_lock:
                    self.pending -= 1
            self.busy += 1
            if self.busy == 1 or self.busy % 100 == 0:
                log.warning("request queue full (%d waiting): answering busy (%d so far)", jobs.maxsize, self.busy)
            self._reply_err(q, protocol.ProtocolError(
                "busy", f"{jobs.maxsize} requests already waiting; retry later or send fewer/smaller requests"))

    def _work(self, jobs: queue.Queue) -> None:
        while True:
            item = jobs.get()
            if item is None:
                return
            try:
                self._answer(*item)
            finally:
                if jobs is self._sdf_jobs:
                    with self._pending_lock:
                        self.pending -= 1
            # Drop the last reference now: Zenoh finalises a query (and the requester's
            # get returns) only when the Query object is released.
            del item

    def _answer(self, q, req) -> None:
        with self._pending_lock:
            self.evaluated += 1
        try:
            if isinstance(req, query_messages.SdfRequest):
                rep = self.engine.answer_sdf(req)
            else:
                rep = self.engine.answer_mesh(req)
            q.reply(q.key_expr, protocol.pack(rep.to_msg()), encoding=transport.ENCODING)
            self.answered += 1
        except protocol.ProtocolError as e:
            self._reply_err(q, e)
        except Exception as e:  # noqa: BLE001
            log.exception("internal error answering a request")
            self._reply_err(q, protocol.ProtocolError("internal", f"{type(e).__name__}: {e}"))

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        max_pts = self.cfg.max_points
        on_sdf = lambda q: self._accept(q, lambda m: query_messages.SdfRequest.from_msg(m, max_pts), self._sdf_jobs)  # noqa: E731
        on_mesh = lambda q: self._accept(q, query_messages.MeshRequest.from_msg, self._mesh_jobs)  # noqa: E731
        rid = self.replica_id
        self._decls = [
            self._subscriber(keys.MAP_WEIGHTS, self._on_weights),
            self._subscriber(keys.MAP_SURFELS, self._on_surfels),
            self._subscriber(f"{keys.MAP_SUBMAPS}/*", self._on_submap, with_key=True),
            self._subscriber(keys.MAP_INDEX, self._on_index),
            # complete (1.12): a best-matching get (Zenoh's default) reaches one replica only
            self.session.declare_queryable(keys.key(self.ns, keys.QUERY_SDF), on_sdf, complete=True),
            self.session.declare_queryable(keys.key(self.ns, keys.QUERY_MESH), on_mesh, complete=True),
            self.session.declare_queryable(keys.replica_key(self.ns, rid, "sdf"), on_sdf, complete=True),
            self.session.declare_queryable(keys.replica_key(self.ns, rid, "mesh"), on_mesh, complete=True),
            transport.serve(self.session, keys.key(self.ns, INFO_KEY), lambda _req: self.info(), allow_empty=True),
            self.session.liveliness().declare_token(keys.status_key(self.ns, "query", rid)),
            # last: planners that see the token find the replica's queryables declared
            self.session.liveliness().declare_token(keys.replica_key(self.ns, rid)),
        ]
        for t in self._threads:
            t.start()
        self.engine.start()

    def info(self) -> dict:
        st, bk = self.engine.state, self.engine.baked
        return {"v": protocol.VERSION, "replica": self.replica_id, "version": st.version if st else None, "epoch": st.epoch if st else None,
                "baked_version": bk.state.version if bk else None,
                # 1.19: the surfel map versions held and baked (a bake of weights alone keeps its
                # map version when the surfels arrive after it)
                "surfel_version": st.surfel_version if st else None,
                "baked_surfel_version": bk.state.surfel_version if bk else None, "bakes": self.engine.baker.bakes,
                "bake_extensions": self.engine.baker.extensions,
                "bake_failures": self.engine.baker.failures, "last_bake": self.engine.baker.last,
                "lag": self.engine.lag(), "answered": self.answered, "errors": self.errors, "busy": self.busy,
                "evaluated": self.evaluated,
                "queued": self._sdf_jobs.qsize(), "held": self.engine.held,

                "submaps": len(st.submaps.submaps) if st is not None and st.submaps is not None else None,
                # (1.4: counted once per submap holding them, as published; the union keeps copies once;
                # 1.5: a one-network map's points)
                "measured_points": 0 if st is None else (
                    sum(len(s.measured) for s in st.submaps.submaps.values() if s.measured is not None)
                    if st.submaps is not None else (0 if st.measured is None else len(st.measured))),
                "fetched": self.fetched}

    def stop(self) -> None:
        self._stop.set()
        for d in self._decls:
            d.undeclare()
        self.engine.stop()
        for _ in range(self.cfg.workers):
            self._drain_put(self._sdf_jobs)
        self._drain_put(self._mesh_jobs)

    @staticmethod
    def _drain_put(jobs: queue.Queue) -> None:
        """Queue the stop marker, dropping waiting jobs if the queue is full."""
        while True:
            try:
                jobs.put_nowait(None)
                return
            except queue.Full:
                try:
                    jobs.get_nowait()
                except queue.Empty:
                    pass


def main(cfg: QueryConfig, stop: threading.Event | None = None) -> None:
    """Run the query service until ``stop`` is set (or SIGINT/SIGTERM)."""
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    stop = stop or threading.Event()
    with transport.open_session(cfg.zenoh) as session:
        node = QueryNode(cfg, session)
        node.start()
        log.info("query service up under '%s' on %s, replica %s", cfg.namespace, node.engine.device, node.replica_id)
        last = time.monotonic()
        while not stop.wait(0.5):
            if time.monotonic() - last > 10:
                i = node.info()
                log.info("map version %s (baked %s, lag %s), %d evaluated, %d answered, %d errors, %d busy",
                         i["version"], i["baked_version"], i["lag"], node.evaluated, node.answered, node.errors,
                         node.busy)
                last = time.monotonic()
        node.stop()


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="aisdf-query",
        description="AiSDF query service: answers planners' batches on <namespace>/query/sdf (signed distance, "
        "gradient, CHOMP collision cost) and <namespace>/query/mesh, from the latest map the mapper published.",
    )
    add_common_args(p)
    p.add_argument("--max-points", type=int, help="largest batch answered (default 1000000)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"])
    p.add_argument("--replica-id", help="protocol 1.12: this replica's id, one key chunk (default "
                   "<hostname>-<6 random hex digits>, new at every start)")
    args = p.parse_args(argv)
    cfg = config_from_args(QueryConfig, args, {"max_points": args.max_points, "device": args.device,
                                               "replica_id": args.replica_id})
    stop = service_setup(cfg, "query")
    main(cfg, stop)


if __name__ == "__main__":
    cli()
