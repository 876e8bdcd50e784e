"""One mapper as a shard of a map several mappers share (protocol 1.14, ``cluster.enabled``).

* Membership: the live mapper ids are the liveliness tokens ``status/mapper/<id>`` (this
  mapper's id is stable: ``cluster.mapper_id``). Region ranks: ``aisdf.cluster.ownership``.
* One frame per map: the first mapper to make the submap grid puts it on ``cluster/frame``
  (``{"grid", "epoch", "mapper", "created_ms"}``) and answers ``get`` on it; a mapper that
  finds one adopts it (grid and epoch) before its first keyframe. Two made at once: the one
  with the lowest (created_ms, mapper) wins; the other adopts its grid (its submaps made
  again on it) and an epoch above both, which it puts back, so all converge on that epoch.
* Keyframes: each keeps those touching regions it ranks 1 or 2 for (``decide``) and
  acknowledges every keyframe with its id, the regions the keyframe touches and those it
  holds it for. Those it does not hold still feed its Atlanta frame and surfels.
* Terms: a region's term is taken when this mapper becomes its rank 1: milliseconds since
  1970, above the term of any snapshot of its cells it has seen; every submap snapshot
  carries ``{"term", "mapper"}`` in its header, and the query service orders a submap's
  snapshots by (term, version). Versions are ``max(last + 1, centiseconds since 1970)``,
  comparable across mappers.
* Handover (``apply``, in the training loop between steps): when the members change, the
  ranks are recomputed; gained regions get submaps trained on the keyframes held, starting
  from the last snapshot of each cell seen on ``map/submaps/*``; regions newly held (rank 1
  or 2) get the keyframes this mapper lacks from the others (``cluster/keyframes/**``, a get
  whose payload lists the regions; each holder replies one keyframe per key).
* The surfel map: every mapper's structure sees every keyframe; the rank 1 of the
  pseudo-region ``surfels`` publishes ``map/surfels``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import threading
import time
from pathlib import Path

import zenoh

from aisdf import keys, protocol, transport
from aisdf.cluster import ownership as own
from aisdf.cluster.regions import touched_regions
from aisdf.submaps import shards
from aisdf.submaps.grid import SubmapGrid, parse_cell_id

log = logging.getLogger("aisdf.mapper")
FRAME_KEY = "cluster/frame"
KEYFRAMES_KEY = "cluster/keyframes"
FETCHED_PER_STEP = 4  # keyframes got from the others, added between two training steps


def default_mapper_id(checkpoint_dir) -> str:
    host = socket.gethostname().split(".")[0] or "mapper"
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in host)
    if checkpoint_dir:
        h = hashlib.blake2b(str(Path(checkpoint_dir).resolve()).encode(), digest_size=3).hexdigest()
        return f"{host}-{h}"
    return f"{host}-{os.getpid()}"


def now_ms() -> int:
    return int(time.time() * 1000)


class Shard:
    def __init__(self, node, cfg):
        self.node, self.cfg = node, cfg
        self.id = cfg.mapper_id or default_mapper_id(node.cfg.checkpoint_dir)
        self.members: frozenset[str] = frozenset({self.id})  # live, as the tokens say (replaced, never changed)
        self.ranked_members: frozenset[str] = self.members  # as last applied: ranks use these
        self.regions: set[str] = set()  # every region of the map heard of (keyframes, indexes, snapshots)
        self.frame: dict | None = None  # the frame this mapper uses (made or adopted)
        self._frame_in: dict | None = None  # the best frame received, not yet considered
        self.terms: dict[str, int] = {}  # regions this mapper is rank 1 of -> term
        self.held: set[str] = set()  # regions ranked 1 or 2 (keyframes kept)
        self.payloads: dict[tuple[str, int], bytes] = {}  # held keyframes as received
        self.touched: dict[tuple[str, int], list[str] | None] = {}
        self.observed: set[tuple[str, int]] = set()  # keyframes not held, seen by the structure
        self.cache: dict[str, tuple[tuple[int, int], bytes]] = {}  # submap id -> ((term, version), payload)
        self.fetched: list[bytes] = []  # keyframes got from the other mappers, to add
        self.lock = threading.Lock()
        self.changed = threading.Event()
        self.counts = {"handovers": 0, "gained": 0, "lost": 0, "fetched": 0, "not_held": 0}
        self.events: list[dict] = []  # handovers, for info/mapper
        self._decls: list = []
        self._surfels_seen = -1  # keyframes taken at this shard's last surfel-only publication

    # ------------------------------------------------------------------ ranks
    def region(self, cell) -> str:
        return own.region_id(own.region_of(cell, self.cfg.region_cells))

    def role(self, region: str) -> int:
        r = own.rank(self.id, region, self.ranked_members)
        return r if r <= self.cfg.replicas else 0

    def owns_cell(self, cell) -> bool:
        return self.role(self.region(cell)) == 1

    def publishes_surfels(self) -> bool:
        return own.surfel_owner(self.ranked_members) == self.id

    def surfels_due(self) -> bool:
        """Is the surfel map to be published by this shard although it trains nothing (it owns
        no submap)? When it is the surfel map's publisher, has the grid, and took keyframes since."""
        seen = len(self.node.seen) + self.counts["not_held"]
        if not self.publishes_surfels() or self.node.pipeline.grid is None or seen == self._surfels_seen:
            return False
        self._surfels_seen = seen
        return True

    def header(self, cell) -> dict:
        r = self.region(cell)
        if r not in self.terms:  # a region first mapped now
            self.terms[r] = self._new_term(r)
        return {"term": int(self.terms[r]), "mapper": self.id}

    def _new_term(self, region: str) -> int:
        with self.lock:
            seen = [o[0] for sid, (o, _d) in self.cache.items() if self.region(parse_cell_id(sid)) == region]
        return max([now_ms()] + [t + 1 for t in seen])

    @staticmethod
    def next_version(v: int) -> int:
        return max(int(v) + 1, int(time.time() * 100))

    # ------------------------------------------------------------------ wiring
    def start(self, session) -> list:
        ns = self.node.ns
        me = keys.status_key(ns, "mapper", self.id)
        if any(r.ok is not None for r in session.liveliness().get(me, timeout=self.cfg.start_wait_s)):
            raise SystemExit(f"aisdf-mapper: another live mapper already has the id {self.id!r} in '{ns}' "
                             "(set cluster.mapper_id)")
        for r in session.liveliness().get(keys.status_key(ns, "mapper", "*"), timeout=self.cfg.start_wait_s):
            if r.ok is not None:
                self.members = self.members | {str(r.ok.key_expr).rsplit("/", 1)[-1]}
        self.ranked_members = self.members
        for r in session.get(keys.key(ns, keys.MAP_INDEX), timeout=self.cfg.start_wait_s,
                             consolidation=zenoh.ConsolidationMode.NONE):  # the regions mapped so far
            try:
                idx = protocol.SubmapIndex.from_msg(protocol.unpack(transport.payload_bytes(r.ok.payload)))
                self.regions |= {self.region(parse_cell_id(sid)) for sid in idx.submaps}
            except (AttributeError, protocol.ProtocolError, ValueError):
                continue
        for r in session.get(keys.key(ns, FRAME_KEY), timeout=self.cfg.start_wait_s):
            if r.ok is not None:
                self._on_frame(transport.payload_bytes(r.ok.payload))
        self.node.pipeline.owns = self.owns_cell
        self.node.pipeline.cluster_header = self.header
        shards.install_warm_start(self.node.pipeline, self.snapshot_of)
        self._decls = [
            session.liveliness().declare_subscriber(keys.status_key(ns, "mapper", "*"), self._on_token, history=True),
            session.declare_subscriber(keys.key(ns, FRAME_KEY),
                                       lambda s: self._on_frame(transport.payload_bytes(s.payload))),
            session.declare_queryable(keys.key(ns, FRAME_KEY), self._serve_frame),
            session.declare_subscriber(keys.key(ns, keys.MAP_SUBMAPS) + "/*", self._on_submap),
            session.declare_queryable(keys.key(ns, KEYFRAMES_KEY) + "/**", self._serve_keyframes),
        ]
        log.info("mapper shard %s: %d member(s) %s, regions of %d x %d cells, %d owner(s) each%s", self.id,
                 len(self.members), sorted(self.members), self.cfg.region_cells, self.cfg.region_cells,
                 self.cfg.replicas, "" if self.frame is None and self._frame_in is None else "; the map's frame found")
        self.changed.set()
        return self._decls

    def _on_token(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.members = self.members | {name}
            elif name != self.id:
                self.members = self.members - {name}
        self.changed.set()

    def _on_frame(self, payload: bytes) -> None:
        try:
            m = protocol.unpack(payload)
            f = {"grid": SubmapGrid.from_msg(m["grid"]).to_msg(), "epoch": int(m["epoch"]), "mapper": str(m["mapper"]),
                 "created_ms": int(m["created_ms"])}
        except (protocol.ProtocolError, KeyError, TypeError, ValueError) as e:
            log.warning("ignoring a malformed map frame: %s", e)
            return
        with self.lock:
            cur = self._frame_in
            if cur is None or _ident(f) < _ident(cur) or (_ident(f) == _ident(cur) and f["epoch"] > cur["epoch"]):
                self._frame_in = f
        self.changed.set()

    def snapshot_of(self, cell) -> protocol.WeightSnapshot | None:
        """The newest snapshot of ``cell`` published (seen or got; the previous owner's), if any."""
        with self.lock:
            held = self.cache.get(f"{cell[0]}_{cell[1]}_{cell[2]}")
        if held is None:
            return None
        try:
            snap = protocol.WeightSnapshot.from_msg(protocol.unpack(held[1]))
        except protocol.ProtocolError:
            return None
        return snap

    def _serve_frame(self, q) -> None:
        f = self.frame
        if f is None:
            q.reply_err(protocol.pack(protocol.error_message("no_map", "no frame yet")), encoding=transport.ENCODING)
        else:
            q.reply(q.key_expr, protocol.pack({"v": protocol.VERSION, **f}), encoding=transport.ENCODING)

    def _on_submap(self, sample) -> None:
        try:
            data = transport.payload_bytes(sample.payload)
            m = protocol.unpack(data)
            hdr = m["submap"]
            order = (int(hdr.get("term", 0)), int(m["version"]))
            sid = str(hdr["id"])
            parse_cell_id(sid)
        except (protocol.ProtocolError, KeyError, TypeError, ValueError, AttributeError):
            return
        self.regions.add(self.region(parse_cell_id(sid)))
        if self.role(self.region(parse_cell_id(sid))) == 0:
            return  # neither owner nor replica: not ours to take over
        with self.lock:
            held = self.cache.get(sid)
            if held is None or order > held[0]:
                self.cache[sid] = (order, data)

    def _serve_keyframes(self, q) -> None:
        try:
            req = protocol.unpack(transport.payload_bytes(q.payload))
            regions = set(req["regions"])
        except (protocol.ProtocolError, KeyError, TypeError):
            q.reply_err(protocol.pack(protocol.error_message("bad_request", "want {'regions': [region ids]}")),
                        encoding=transport.ENCODING)
            return
        with self.lock:
            out = [p for k, p in self.payloads.items() if self.touched.get(k) is None or regions & set(self.touched[k])]
        base = keys.key(self.node.ns, f"{KEYFRAMES_KEY}/{self.id}")
        for i, p in enumerate(out):
            q.reply(f"{base}/{i}", p, encoding=transport.ENCODING)

    def close(self) -> None:
        for d in self._decls:
            d.undeclare()
        self._decls = []

    # ------------------------------------------------------------------ keyframes
    def decide(self, kf: protocol.Keyframe) -> tuple[bool, list[str] | None, list[str] | str]:
        """(hold it, the regions it touches or None before the grid, the regions held for or ALL)."""
        grid = self.node.pipeline.grid
        if grid is None:
            return True, None, own.ALL
        touched = touched_regions(grid, kf.depth_m(), kf.K, kf.T_WC, self.cfg.region_cells)
        self.regions.update(touched)
        held = [r for r in touched if self.role(r)]
        return bool(held) or not touched, touched, held

    def ack_info(self, key) -> tuple[list[str] | None, list[str] | str]:
        t = self.touched.get(key)
        return (None, own.ALL) if t is None else (t, [r for r in t if self.role(r)])

    def kept(self, key, payload: bytes, touched) -> None:
        with self.lock:
            self.payloads[key] = payload
            self.touched[key] = touched

    def take_fetched(self, limit: int = FETCHED_PER_STEP) -> list[tuple[protocol.Keyframe, bytes]]:
        """Keyframes got from the other mappers (regions this one now holds), decoded: at most
        ``limit`` per training step, so training goes on while they are added."""
        with self.lock:
            got, n = [], 0
            while self.fetched and n < limit:
                payload = self.fetched.pop(0)
                got.append(payload)
                n += 1
        out = []
        for payload in got:
            try:
                out.append((protocol.Keyframe.from_msg(protocol.unpack(payload)), payload))
            except protocol.ProtocolError as e:
                log.warning("a fetched keyframe is unreadable: %s", e.message)
        return out

    def observe(self, kf: protocol.Keyframe) -> None:
        """A keyframe of no region of ours: its Atlanta frame and surfels only, once."""
        key = (kf.sensor, kf.frame_id)
        if key in self.observed:
            return
        self.observed.add(key)
        self.counts["not_held"] += 1
        try:
            shards.observe_only(self.node.pipeline, kf)
        except ValueError:
            pass

    # ------------------------------------------------------------------ membership and frame changes
    def apply(self) -> None:
        """Between training steps (the caller holds the training lock): the map's frame, then
        ranks, handovers and keyframe fetches after a membership change."""
        pipe = self.node.pipeline
        if self.changed.is_set() or (pipe.grid is not None and self.frame is None):
            self.changed.clear()
            self._apply_frame(pipe)
            self._apply_ranks(pipe)

    def _apply_frame(self, pipe) -> None:
        node = self.node
        with self.lock:
            f_in = self._frame_in
        mine = self.frame
        if f_in is not None and (mine is None or _ident(f_in) < _ident(mine)
                                 or (_ident(f_in) == _ident(mine) and f_in["epoch"] > mine["epoch"])):
            grid = SubmapGrid.from_msg(f_in["grid"])
            rebuilt = shards.adopt_grid(pipe, grid)
            epoch = f_in["epoch"]
            conflict = mine is not None and _ident(f_in) != _ident(mine)
            if conflict or rebuilt:  # two frames made at once: an epoch above both, put back
                epoch = max(epoch, node.epoch + 1)
            if epoch != node.epoch or rebuilt:
                node.switch_epoch(epoch)
            self.frame = {**f_in, "epoch": epoch}
            log.info("map frame of %s adopted (epoch %d%s)", f_in["mapper"], epoch,
                     ", submaps made again on its grid" if rebuilt else "")
            if epoch != f_in["epoch"]:
                self._put_frame()
        elif mine is None and pipe.grid is not None:
            self.frame = {"grid": pipe.grid.to_msg(), "epoch": node.epoch, "mapper": self.id, "created_ms": now_ms()}
            log.info("made the map's frame (epoch %d)", node.epoch)
            self._put_frame()
        elif f_in is not None and mine is not None and _ident(mine) < _ident(f_in):
            self._put_frame()  # a later frame is about: ours wins, say it again

    def _put_frame(self) -> None:
        if self.node.session is not None and self.frame is not None:
            transport.put(self.node.session, keys.key(self.node.ns, FRAME_KEY), {"v": protocol.VERSION, **self.frame})

    def _apply_ranks(self, pipe) -> None:
        with self.lock:
            members = self.members
        self.ranked_members = members
        regions = self.regions | set(self.held) | set(self.terms) | {self.region(c) for c in pipe.submaps}
        ranks = {r: own.rank(self.id, r, members) for r in regions}
        first = {r for r, k in ranks.items() if k == 1}
        held = {r for r, k in ranks.items() if 1 <= k <= self.cfg.replicas}
        new_first = first - set(self.terms)
        for r in new_first:
            self.terms[r] = self._new_term(r)
        for r in set(self.terms) - first:
            del self.terms[r]
        if new_first and len(members) > 1:
            self._get_latest_submaps(new_first)
        w0 = getattr(pipe, "warm_started", 0)
        gained, lost = shards.reassign(pipe, self.owns_cell)
        if gained or lost:
            self.counts["handovers"] += 1
            self.counts["gained"] += len(gained)
            self.counts["lost"] += len(lost)
            ev = {"t": time.time(), "members": sorted(members), "gained": [f"{i}_{j}_{k}" for i, j, k in gained],
                  "lost": [f"{i}_{j}_{k}" for i, j, k in lost], "warm": getattr(pipe, "warm_started", 0) - w0}
            self.events = (self.events + [ev])[-20:]
            log.info("members %s: submaps gained %s (%d from their last weights), lost %s", sorted(members),
                     ev["gained"], ev["warm"], ev["lost"])
        new_held = held - self.held
        self.held = held
        if new_held and len(members) > 1 and pipe.grid is not None:
            threading.Thread(target=self._fetch, args=(sorted(new_held),), name="fetch", daemon=True).start()

    def _get_latest_submaps(self, regions: set[str]) -> None:
        """The last published snapshot of every submap of ``regions`` the others still serve
        (the previous owner's, when it is alive), into the cache."""
        s = self.node.session
        if s is None:
            return
        try:
            replies = list(s.get(keys.key(self.node.ns, keys.MAP_SUBMAPS) + "/**", timeout=3.0,
                                 consolidation=zenoh.ConsolidationMode.NONE))
        except Exception as e:  # noqa: BLE001 - then from what was seen, or anew
            log.warning("getting the last submap snapshots failed: %s", e)
            return
        for r in replies:
            if r.ok is not None:
                self._on_submap(r.ok)

    def _fetch(self, regions: list[str]) -> None:
        """Keyframes of newly held regions from the other mappers (replies on distinct keys)."""
        s = self.node.session
        if s is None:
            return
        n, seen = 0, set()
        try:
            for r in s.get(keys.key(self.node.ns, KEYFRAMES_KEY) + "/**", payload=protocol.pack({"regions": regions}),
                           timeout=20.0, consolidation=zenoh.ConsolidationMode.NONE):
                if r.ok is None or str(r.ok.key_expr).split("/")[-2] == self.id:
                    continue
                data = transport.payload_bytes(r.ok.payload)
                try:  # each holder sends its copy: one of each, and none already here
                    m = protocol.unpack(data)
                    key = (str(m.get("sensor", "depth")), int(m["frame_id"]))
                except (protocol.ProtocolError, KeyError, TypeError, ValueError):
                    continue
                if key in seen or self.node.is_seen(*key):
                    continue
                seen.add(key)
                with self.lock:
                    self.fetched.append(data)
                n += 1
        except Exception as e:  # noqa: BLE001 - the resends and the next change try again
            log.warning("fetching keyframes of regions %s failed: %s", regions, e)
        self.counts["fetched"] += n
        log.info("got %d keyframe(s) of newly held regions %s from the other mappers", n, regions)

    def info(self) -> dict:
        with self.lock:
            members = sorted(self.members)
        held = sorted(r for r in self.regions if self.role(r))
        return {"id": self.id, "members": members, "owned": sorted(self.terms), "held": held,
                "surfels": self.publishes_surfels(), "frame": None if self.frame is None else
                {"mapper": self.frame["mapper"], "epoch": self.frame["epoch"]}, **self.counts,
                "events": self.events[-5:]}


def _ident(f: dict) -> tuple[int, str]:
    return (int(f["created_ms"]), str(f["mapper"]))
