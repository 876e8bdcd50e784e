"""``aisdf-mapper``: trains the SDF continually on incoming keyframes and publishes the map.
Zenoh wiring of an :class:`aisdf.mapper.Mapper` (``mapper: submaps`` or ``single``, made by
``aisdf.mapper.factory``), which it uses only through that interface.

* ``keyframes`` (subscribed): every keyframe is validated on arrival; a bad one is
  rejected with a log line and counted, and the map is untouched. Accepted keyframes
  wait in a bounded queue; when the mapper trains slower than keyframes come, the
  oldest waiting one is dropped, logged and counted, so memory stays bounded.
* The map, published every ``snapshot_period_s`` while training and answered on ``get``
  with the latest (late joiners): with submaps (default, protocol 1.3) the submaps trained
  since their last publication on ``map/submaps/<id>``, the index of all submaps on
  ``map/index`` and ``map/surfels``; with one network, ``map/weights`` and ``map/surfels``.
* ``keyframes/ack`` (protocol 1.2): once a keyframe is in the map (and, with a checkpoint
  directory, in the journal on disk), or rejected for good, the mapper says so; front ends
  resend what is not acknowledged. Keyframes are deduplicated by (sensor, frame_id), also
  across restarts (the checkpoint and the journal remember them), so a resend is
  acknowledged again and never added twice. A keyframe dropped from the queue is not
  acknowledged: its sender resends it.
* Every incarnation has an ``epoch`` (milliseconds since 1970 at start, above any earlier
  incarnation's), put on every WeightSnapshot and SurfelMap: maps order by (epoch,
  version). A resumed mapper also continues its versions above the highest it published
  (kept in the checkpoint directory), so receivers that only know ``version`` take it too.
* Mapper shards (protocol 1.14, ``cluster.enabled``): several mappers in one namespace share
  the map's regions; acknowledgements name the mapper and the regions held (``shard.py``).
* ``info/mapper`` (extension, not part of protocol v1): a map of counters and the
  per-module timings, for the demo and operators.
* ``control/mapper/save`` and ``control/mapper/load`` (extension): map files, ``aisdf.mapfiles``.
* ``control/mapper/poses`` (protocol 1.11): new poses for keyframes in the map (a SLAM system's
  loop closure). Checked in the Zenoh callback (a malformed request changes nothing), applied
  by the training loop between two steps (``aisdf.mapper.repose``), published and (with a
  checkpoint directory) checkpointed; then the request is answered with what was done.

The control requests live in ``control.py``, the checkpoint, journal and incarnation in
``persist.py``, the shard's part in ``shard.py`` and the checkpoint directory's lock (one
writer per directory, or a slot each) in ``slots.py``.
"""

from __future__ import annotations

import argparse
import collections
import logging
import threading
import time
import uuid
from pathlib import Path

import torch
import zenoh

from aisdf import keys, mapfiles, protocol, transport
from aisdf.config import add_common_args, config_from_args, service_setup
from aisdf.mapper import Mapper
from aisdf.mapper.factory import make_mapper

from .config import MapperConfig
from .control import POSES_WAIT_S, ControlMixin  # noqa: F401 (POSES_WAIT_S: its old home)
from .journal import Incarnation, KeyframeJournal
from .persist import CHECKPOINT_NAME, INCARNATION_NAME, JOURNAL_NAME, CheckpointMixin  # noqa: F401
from .shard import Shard

log = logging.getLogger("aisdf.mapper")
INFO_KEY = "info/mapper"


class MapperNode(CheckpointMixin, ControlMixin):
    def __init__(self, cfg: MapperConfig, session, pipeline: Mapper | None = None):
        self.slot = None  # 1.14: this mapper's slot of a shared checkpoint volume (slots.py)
        if cfg.cluster.enabled and cfg.cluster.slots and cfg.checkpoint_dir:
            from .slots import claim

            self.slot = claim(cfg.checkpoint_dir)
            cfg = cfg.model_copy(update={"checkpoint_dir": self.slot.dir, "cluster": cfg.cluster.model_copy(
                update={"mapper_id": cfg.cluster.mapper_id or self.slot.mapper_id})})
            log.info("state in %s (slot %d)", self.slot.dir, self.slot.n)
        self.dir_lock = None  # one writer per checkpoint directory: a second mapper given it stops here
        if self.slot is None and cfg.checkpoint_dir:
            from .slots import lock_dir

            try:
                self.dir_lock = lock_dir(cfg.checkpoint_dir)
            except RuntimeError as e:
                raise SystemExit(f"aisdf-mapper: {e}") from None
        self.cfg = cfg
        self.session = session
        self.ns = cfg.namespace
        self.pipeline = pipeline or make_mapper(
            cfg.mapper, cfg.preset, cfg.training, atlanta=cfg.atlanta, surfel_mask=cfg.surfel_mask, surfel_loss=cfg.surfel_loss,
            surfel_bounds=cfg.surfel_bounds, measured=cfg.measured, submaps=cfg.submap, keyframes=cfg.keyframes)
        self.pending: collections.deque = collections.deque()
        self.lock = threading.Lock()
        self.train_lock = threading.Lock()  # held through each training step; a map is saved or swapped between
        self.counts = {"received": 0, "rejected": 0, "dropped": 0, "accepted": 0, "duplicates": 0}
        self.version = 0
        self.epoch = 0
        self.seen: set[tuple[str, int]] = set()  # (sensor, frame_id) in the map
        self._seen_ids: set[int] = set()  # frame ids of a checkpoint older than 1.2 (no sensor kept)
        d = Path(cfg.checkpoint_dir) if cfg.checkpoint_dir else None
        self.journal = KeyframeJournal(d / JOURNAL_NAME) if d else None
        self.incarnation = Incarnation(d / INCARNATION_NAME) if d else None
        self._latest: dict[str, bytes] = {}  # key under the namespace -> newest payload published there
        self._published_all = False
        self._stop = threading.Event()
        self._decls: list = []
        self._thread = threading.Thread(target=self._train_loop, name="train", daemon=True)
        self._pose_jobs: collections.deque = collections.deque()  # PoseCorrections for the training loop
        self._restore()
        self.shard = None  # protocol 1.14: this mapper as one shard of the namespace's map
        if cfg.cluster.enabled:
            if getattr(self.pipeline, "kind", None) != "submaps":
                raise SystemExit("aisdf-mapper: cluster.enabled needs the submap mapper (mapper: submaps)")
            self.shard = Shard(self, cfg.cluster)

    # ------------------------------------------------------------------ keyframes in

    def on_keyframe(self, payload: bytes) -> None:
        self.counts["received"] += 1
        msg = None
        try:
            msg = protocol.unpack(payload)
            kf = protocol.Keyframe.from_msg(msg)
        except protocol.ProtocolError as e:
            self.counts["rejected"] += 1
            log.warning("rejected keyframe: %s", e.message)
            ident = _identity(msg)
            if ident is not None:  # refused for good: tell its sender not to resend it
                self._ack(ident[0], rejected=[ident[1]])
            return
        with self.lock:
            if self.is_seen(kf.sensor, kf.frame_id):
                self.counts["duplicates"] += 1
                duplicate = True
            else:
                duplicate = False
                self.pending.append((kf, payload))
                if len(self.pending) > self.cfg.queue_max:
                    old, _ = self.pending.popleft()
                    self.counts["dropped"] += 1
                    log.warning("dropped keyframe %d: %d waiting, training is slower than keyframes arrive; not "
                                "acknowledged, its sender resends it (dropped so far: %d)", old.frame_id,
                                self.cfg.queue_max, self.counts["dropped"])
        if duplicate:  # already in the map: our acknowledgement was lost or late
            log.debug("keyframe %s/%d is already in the map", kf.sensor, kf.frame_id)
            self._ack(kf.sensor, [kf.frame_id])

    def _ack(self, sensor: str, frame_ids=(), rejected=(), regions=None) -> None:
        """``regions`` (a shard, 1.14): per frame id, (the regions it touches or None, the
        regions held for or ALL), sent as ``touched`` and ``held`` beside ``mapper``."""
        if self.session is None:
            return
        msg = protocol.KeyframeAck(self.epoch, sensor, list(frame_ids), list(rejected)).to_msg()
        if self.shard is not None:
            msg["mapper"] = self.shard.id
            if regions is None:
                regions = [self.shard.ack_info((sensor, int(i))) for i in frame_ids]
            msg["touched"] = [t for t, _ in regions]
            msg["held"] = [h for _, h in regions]
        transport.put(self.session, keys.key(self.ns, keys.KEYFRAMES_ACK), msg)

    # ------------------------------------------------------------------ training

    def _take_pending(self) -> list[tuple[protocol.Keyframe, bytes]]:
        with self.lock:
            items = list(self.pending)
            self.pending.clear()
        return items

    def _add_pending(self) -> None:
        """Add the waiting keyframes to the map, journal them, acknowledge them (a shard: those
        touching regions it holds; the others feed only its structure)."""
        acks: dict[str, tuple[list, list, list]] = {}
        for kf, payload in self._take_pending() + (self.shard.take_fetched() if self.shard else []):
            ok, bad, regs = acks.setdefault(kf.sensor, ([], [], []))
            if self.is_seen(kf.sensor, kf.frame_id):  # a resend that was waiting with its original
                self.counts["duplicates"] += 1
                ok.append(kf.frame_id)
                regs.append(self.shard.ack_info((kf.sensor, kf.frame_id)) if self.shard else None)
                continue
            touched = None
            if self.shard is not None:
                hold, touched, held = self.shard.decide(kf)
                if not hold:  # no region of ours: its Atlanta frame and surfels only
                    self.shard.observe(kf)
                    ok.append(kf.frame_id)
                    regs.append((touched, held))
                    continue
            try:
                self.pipeline.add_keyframe(kf)
            except ValueError as e:
                self.counts["rejected"] += 1
                log.warning("rejected keyframe %d: %s", kf.frame_id, e)
                bad.append(kf.frame_id)
                continue
            if self.journal is not None:
                self.journal.append(payload)  # on disk before it is acknowledged
            with self.lock:
                self.seen.add((kf.sensor, kf.frame_id))
            if self.shard is not None:
                self.shard.kept((kf.sensor, kf.frame_id), payload, touched)
            self.counts["accepted"] += 1
            ok.append(kf.frame_id)
            regs.append(self.shard.ack_info((kf.sensor, kf.frame_id)) if self.shard else None)
        for sensor, (ok, bad, regs) in acks.items():
            if self.shard is not None:
                self._ack(sensor, ok, bad, regions=regs)
            else:
                self._ack(sensor, ok, bad)

    def switch_epoch(self, epoch: int) -> None:
        """A shard adopting the map's epoch (1.14): everything is published again under it."""
        self.epoch = int(epoch)
        self._published_all = False
        if self.incarnation is not None:
            self.incarnation.save(self.epoch, self.version)

    def _publish(self) -> None:
        self.version = self.shard.next_version(self.version) if self.shard is not None else self.version + 1
        if self.incarnation is not None:  # before anyone can see this version
            self.incarnation.save(self.epoch, self.version)
        # the first publication of an incarnation sends everything (a resumed map, a new epoch)
        msgs = self.pipeline.map_messages(self.version, changed_only=self._published_all, epoch=self.epoch)
        self._published_all = True
        if self.shard is not None and not self.shard.publishes_surfels():  # one surfel map per map (1.14)
            msgs = [(n, d) for n, d in msgs if n != keys.MAP_SURFELS]
        for name, data in msgs:
            self._latest[name] = data
            self.session.put(keys.key(self.ns, name), data, encoding=transport.ENCODING)
        self.counts["published_bytes"] = self.counts.get("published_bytes", 0) + sum(len(d) for _, d in msgs)

    def _train_loop(self) -> None:
        last_pub = last_ckpt = time.monotonic()
        dirty = False
        while not self._stop.is_set():
            with self.train_lock:
                if self.shard is not None:
                    self.shard.apply()
                self._add_pending()
                if self.shard is not None:
                    self.shard.apply()  # a grid made by this keyframe: the map's frame
                if self._pose_jobs:
                    self._add_pending()  # keyframes that came in meanwhile: before their corrections
                    self._apply_poses()
                    last_pub, dirty = time.monotonic(), False
                pause = 0.0 if self.pipeline.ready else self.cfg.idle_sleep_s
                if not pause:
                    try:
                        self.pipeline.step()
                        dirty = True
                    except Exception:  # noqa: BLE001 - keep serving the last good map
                        log.exception("training step failed")
                        pause = 1.0
                    now = time.monotonic()
                    if dirty and now - last_pub >= self.cfg.snapshot_period_s:
                        self._publish()
                        last_pub, dirty = now, False
                    if self.cfg.checkpoint_dir and now - last_ckpt >= self.cfg.checkpoint_period_s:
                        self.save_checkpoint()
                        last_ckpt = now
                elif self.shard is not None and time.monotonic() - last_pub >= self.cfg.snapshot_period_s:
                    if self.shard.surfels_due():  # the surfel map's publisher, with no submap of its own
                        self._publish()
                    last_pub = time.monotonic()
            if pause:
                self._stop.wait(pause)

    # ------------------------------------------------------------------ queries

    def info(self, req: dict | None = None) -> dict:
        """Counters; with ``{"keys": true}`` also the (sensor, frame_id) of every keyframe in the map."""
        out = {"v": protocol.VERSION, "version": self.version, "epoch": self.epoch, "steps": self.pipeline.steps,
               "keyframes": self.pipeline.n_keyframes, "seen": len(self.seen) + len(self._seen_ids),
               "pending": len(self.pending), **self.counts,
               "stats": self.pipeline.stats(), **({"cluster": self.shard.info()} if self.shard else {})}
        if isinstance(req, dict) and req.get("keys") is True:
            with self.lock:
                out["keys"] = sorted([s, int(i)] for s, i in self.seen)
            if self.shard is not None:  # the regions each kept keyframe touches (nil: before the grid)
                out["touched"] = [self.shard.touched.get((s, i)) for s, i in out["keys"]]
        return out

    def _latest_of(self, name: str):
        def on_query(q):
            data = self._latest.get(name)
            if data is None:
                q.reply_err(protocol.pack(protocol.error_message("no_map", f"no {name} published yet")),
                            encoding=transport.ENCODING)
            else:
                q.reply(q.key_expr, data, encoding=transport.ENCODING)

        return on_query

    def _on_submaps_query(self, q) -> None:
        """``get <ns>/map/submaps/**`` (or one id): the newest snapshot of each, on its own key."""
        prefix = keys.MAP_SUBMAPS + "/"
        n = 0
        for name, data in list(self._latest.items()):
            if not name.startswith(prefix):
                continue
            k = zenoh.KeyExpr(keys.key(self.ns, name))
            if q.key_expr.intersects(k):
                q.reply(k, data, encoding=transport.ENCODING)
                n += 1
        if n == 0:
            q.reply_err(protocol.pack(protocol.error_message("no_map", "no submap published yet")),
                        encoding=transport.ENCODING)

    def start(self) -> None:
        s = self.session
        self._decls = [
            s.declare_subscriber(keys.key(self.ns, keys.KEYFRAMES),
                                 lambda sample: self.on_keyframe(transport.payload_bytes(sample.payload))),
            s.declare_queryable(keys.key(self.ns, keys.MAP_WEIGHTS), self._latest_of(keys.MAP_WEIGHTS)),
            s.declare_queryable(keys.key(self.ns, keys.MAP_SURFELS), self._latest_of(keys.MAP_SURFELS)),
            s.declare_queryable(keys.key(self.ns, keys.MAP_INDEX), self._latest_of(keys.MAP_INDEX)),
            s.declare_queryable(keys.key(self.ns, keys.MAP_SUBMAPS) + "/**", self._on_submaps_query),
            transport.serve(s, keys.key(self.ns, mapfiles.SAVE_KEY), self.on_save, allow_empty=True),
            transport.serve(s, keys.key(self.ns, mapfiles.LOAD_KEY), self.on_load),
            transport.serve(s, keys.key(self.ns, keys.CONTROL_POSES), self.on_poses),
        ]
        if self.shard is not None:  # members, the map's frame, keyframes for the others; then the token
            self._decls += self.shard.start(s)
        self._decls.append(s.liveliness().declare_token(
            keys.status_key(self.ns, "mapper", self.shard.id if self.shard else uuid.uuid4().hex[:8])))
        if self.shard is not None:
            self.shard.apply()  # a resumed map: only the regions this mapper ranks first for
        if self.pipeline.n_keyframes:
            self._publish()  # a resumed map is served at once
        # info/mapper last: a mapper that answers it serves its (resumed) map already
        self._decls.append(transport.serve(s, keys.key(self.ns, INFO_KEY), self.info, allow_empty=True))
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=30)
        while self._pose_jobs:  # never applied: their senders are told at once
            job = self._pose_jobs.popleft()
            job["error"] = protocol.ProtocolError("busy", "the mapper is stopping; the corrections were not applied")
            job["done"].set()
        for d in self._decls:
            d.undeclare()
        self.save_checkpoint()
        if self.journal is not None:
            self.journal.close()
        for held in (self.slot, self.dir_lock):
            if held is not None:
                held.release()


def _identity(msg) -> tuple[str, int] | None:
    """(sensor, frame_id) of an invalid keyframe message, when it has them."""
    if not isinstance(msg, dict):
        return None
    fid, sensor = msg.get("frame_id"), msg.get("sensor", "depth")
    if isinstance(fid, int) and not isinstance(fid, bool) and isinstance(sensor, str):
        return sensor, fid
    return None


def main(cfg: MapperConfig, stop: threading.Event | None = None) -> None:
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    stop = stop or threading.Event()
    with transport.open_session(cfg.zenoh) as session:
        node = MapperNode(cfg, session)
        node.start()
        log.info("mapper up under '%s' (%s)", cfg.namespace, node.pipeline.describe())
        last = time.monotonic()
        while not stop.wait(0.5):
            if time.monotonic() - last > 10:
                i = node.info()
                t = i["stats"]
                times = " ".join(f"{k} {t[k]:.1f}" for k in ("atlanta", "surfels", "sampling", "bound", "forward",
                                                               "backward", "total") if k in t)
                log.info("version %d, %d steps, %d keyframes, %d pending, %d rejected, %d dropped; ms: %s",
                         i["version"], i["steps"], i["keyframes"], i["pending"], i["rejected"], i["dropped"], times)
                last = time.monotonic()
        node.stop()


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="aisdf-mapper",
        description="AiSDF mapper: subscribes to <namespace>/keyframes, trains the neural SDF continually with "
        "Atlanta-aware sampling (one network per submap by default), publishes <namespace>/map/submaps/<id>, "
        "<namespace>/map/index and <namespace>/map/surfels (or <namespace>/map/weights with --mapper single).",
    )
    add_common_args(p)
    p.add_argument("--preset", choices=["auto", "paper", "cpu"], help="training preset (default auto)")
    p.add_argument("--no-atlanta", action="store_true", help="plain iSDF: no Atlanta frame, surfels or surfel map")
    p.add_argument("--checkpoint-dir", help="checkpoint the map here and resume from it")
    p.add_argument("--mapper", choices=["submaps", "single"],
                   help="submaps: one network per submap (protocol 1.3; the default); single: one network (map/weights)")
    p.add_argument("--cluster", action="store_true", help="share the map with the namespace's other mappers that "
                   "have it (protocol 1.14, cluster.enabled)")
    p.add_argument("--mapper-id", help="this mapper's stable id in the cluster (cluster.mapper_id)")
    args = p.parse_args(argv)
    cfg = config_from_args(MapperConfig, args, {"preset": args.preset, "checkpoint_dir": args.checkpoint_dir,
                                                "atlanta": False if args.no_atlanta else None,
                                                "mapper": args.mapper, "cluster.enabled": True if args.cluster else None,
                                                "cluster.mapper_id": args.mapper_id})
    stop = service_setup(cfg, "mapper")
    main(cfg, stop)


if __name__ == "__main__":
    cli()
