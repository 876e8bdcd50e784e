"""The planner's client: numpy points in, numpy distances, gradients and costs out.

    from aisdf.client import SdfClient
    with SdfClient(namespace="aisdf", connect=["tcp/10.0.0.5:7447"]) as c:
        r = c.query(points_W, gradient=True, collision_epsilon=0.3)
        r.sdf, r.gradient, r.collision, r.map_version
        r = c.query(centres, radii=radii, observed=True)   # spheres; r.observed per point
        r = c.box([0, 0, 0], [2, 2, 1], 0.05, gradient=True)  # a dense window; r.grid("sdf")

Protocol errors come back as :class:`aisdf.protocol.ProtocolError` with ``.code``
(``bad_request``, ``too_large``, ``no_map``, ``internal``, ``busy``).

Query replicas (protocol 1.12): where query services announce replica tokens
(``query/replica/<id>``), each request goes to one live replica, spread over them (the one
this client has the fewest requests in flight to, then the least recently asked), and fails
over to another on ``busy``, ``no_map``, a timeout or a replica gone, at most
``max_attempts`` replicas and never beyond ``timeout`` in all (``aisdf.replicas``). With no
replica token visible (query services before 1.12) it asks the shared ``query/sdf`` as
before; ``replicas=False`` always does.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from . import keys, protocol, query_messages, transport
from .config import ZenohOptions
from .replicas import ReplicaGone, Replicas, ask
from .structure.surfel_types import Surfels

ProtocolError = protocol.ProtocolError
FAILOVER = ("busy", "no_map")  # error replies another replica may not give


class SdfClient:
    """Talks to a query service (and the mapper's latest-value keys) over Zenoh."""

    def __init__(
        self,
        namespace: str = keys.DEFAULT_NAMESPACE,
        zenoh: ZenohOptions | None = None,
        connect: list[str] | None = None,
        timeout: float = 10.0,
        max_batch: int | None = None,
        replicas: bool = True,
        max_attempts: int = 3,
        attempt_timeout: float | None = None,
    ):
        """``replicas`` (1.12): spread requests over the query replicas announced in the
        namespace and fail over between them; ``max_attempts``: replicas tried per request at
        most; ``attempt_timeout``: how long one replica may take while another is left to try
        (default half of ``timeout``; the request as a whole never takes longer than ``timeout``)."""
        opts = zenoh or ZenohOptions()
        if connect:
            opts = opts.model_copy(update={"connect": list(connect)})
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be at least 1, got {max_attempts}")
        self.namespace = keys.validate_namespace(namespace)
        self.timeout = timeout
        self.max_batch = max_batch
        self.max_attempts = max_attempts
        self.attempt_timeout = attempt_timeout
        self.failovers = 0  # requests answered by another replica than the first one asked
        self._session = transport.open_session(opts)
        self._replicas = Replicas(self._session, self.namespace) if replicas else None

    def close(self) -> None:
        if self._replicas is not None:
            self._replicas.close()
            self._replicas = None
        if self._session is not None:
            self._session.close()
            self._session = None

    def replica_ids(self) -> list[str]:
        """The query replicas seen alive (protocol 1.12; empty: the shared key answers)."""
        return [] if self._replicas is None else self._replicas.ids()

    def _request(self, name: str, msg: dict, timeout: float) -> dict:
        """``msg`` to ``query/<name>``: to one replica at a time when replicas are announced
        (failing over as the module says), else to the shared key."""
        shared = self._key({"sdf": keys.QUERY_SDF, "mesh": keys.QUERY_MESH}[name])
        reps = self._replicas
        if reps is None or not reps.ids():
            return transport.query(self._session, shared, msg, timeout)
        payload = protocol.pack(msg)
        end = time.monotonic() + timeout
        tried: list[str] = []
        last: Exception | None = None
        while len(tried) < self.max_attempts:
            left = end - time.monotonic()
            rid = reps.pick(tried) if left > 0 else None
            if rid is None:
                break
            tried.append(rid)
            others = len(tried) < self.max_attempts and any(r not in tried for r in reps.ids())
            t = min(left, self.attempt_timeout or timeout / 2) if others else left
            no_map = False
            try:
                out = ask(self._session, reps, rid, name, payload, t)
                if len(tried) > 1:
                    self.failovers += 1
                return out
            except ProtocolError as e:
                if e.code not in FAILOVER:
                    raise
                no_map, last = e.code == "no_map", e
            except TimeoutError as e:  # ReplicaGone too
                last = e
            finally:
                reps.done(rid, no_map)
        left = end - time.monotonic()
        if (last is None or isinstance(last, TimeoutError)) and left > 0.05:
            # every replica asked vanished or timed out: whoever answers the shared key now
            return transport.query(self._session, shared, msg, left)
        if isinstance(last, ReplicaGone):
            raise TimeoutError(f"no reply on {shared} within {timeout:.1f} s: {last}") from None
        raise last if last is not None else TimeoutError(f"no reply on {shared} within {timeout:.1f} s")

    def __enter__(self) -> "SdfClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _key(self, name: str) -> str:
        return keys.key(self.namespace, name)

    def query(
        self,
        points_W: np.ndarray,
        gradient: bool = False,
        collision_epsilon: float | None = None,
        source: str = "fused",
        radii: np.ndarray | None = None,
        observed: bool = False,
        exact: bool = False,
        unknown: bool = False,
        fresh: bool = True,
        predicted: bool = False,
    ) -> query_messages.SdfReply:
        """Signed distances (and optionally gradients and CHOMP costs) of (N, 3) points.

        ``radii`` (N,): the points are sphere centres and distances (and costs) are those of
        the spheres' surfaces. ``observed``: also return per point whether any keyframe has
        seen that space (treat False as occupied for safe planning). ``exact``: the
        network's answer instead of the baked field's. ``unknown`` (protocol 1.6): also return
        per point the distance to the nearest space no keyframe has seen (``reply.unknown``;
        with ``radii``, that of the sphere's surface): ``min(sdf, unknown)`` is the distance
        of a planner that treats unknown space as occupied. ``fresh=False`` (protocol 1.10):
        the baked field answers even when it trails the newest map (cheaper for the service;
        ``map_version`` and ``map_age_s`` say which map). ``predicted`` (protocol 1.13): also
        return per point whether the distance is to a surface the map predicts (the floor,
        ceiling or a wall carried on where no keyframe looked: ``reply.predicted``).

        With ``max_batch`` set, larger inputs are split into several requests and the
        replies concatenated (map_version is the smallest one seen)."""
        pts = np.asarray(points_W)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {pts.shape}")
        if pts.dtype != np.float64:
            pts = pts.astype(np.float32)
        if radii is not None:
            radii = np.asarray(radii)
            if radii.shape != (len(pts),):
                raise ValueError(f"radii must be ({len(pts)},), got {radii.shape}")
        step = self.max_batch or max(len(pts), 1)
        parts = []
        for i in range(0, max(len(pts), 1), step):
            req = query_messages.SdfRequest(pts[i:i + step], gradient, collision_epsilon, source,
                                            None if radii is None else radii[i:i + step], observed, exact, unknown,
                                            fresh=fresh, predicted=predicted)
            parts.append(query_messages.SdfReply.from_msg(self._request("sdf", req.to_msg(), self.timeout)))
        if len(parts) == 1:
            return parts[0]
        cat = lambda name: None if getattr(parts[0], name) is None else np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        first = min(parts, key=lambda p: (p.map_epoch, p.map_version))
        return query_messages.SdfReply(first.map_version, cat("sdf"), cat("gradient"), cat("collision"), cat("observed"),
                                 all(p.baked for p in parts), first.map_epoch, cat("unknown"),
                                 max(p.map_age_s or 0.0 for p in parts) if first.map_age_s is not None else None,
                                 None, cat("predicted"), first.surfel_version)

    def box(self, min_corner, size, resolution: float, gradient: bool = False, observed: bool = False,
            unknown: bool = False, exact: bool = False, source: str = "fused",
            collision_epsilon: float | None = None, fresh: bool = True,
            predicted: bool = False) -> query_messages.SdfReply:
        """A local distance window (protocol 1.9): the dense grid of samples ``resolution``
        apart over the world-axis-aligned box ``[min_corner, min_corner + size]``, in one
        request of a few bytes. ``reply.box`` gives the lattice (origin, resolution, shape);
        ``reply.grid("sdf")`` is (nx, ny, nz), ``reply.grid("gradient")`` (nx, ny, nz, 3)."""
        b = query_messages.Box.around(min_corner, size, resolution)
        req = query_messages.SdfRequest(np.zeros((0, 3), np.float32), gradient, collision_epsilon, source, None,
                                        observed, exact, unknown, b, fresh, predicted)
        return query_messages.SdfReply.from_msg(self._request("sdf", req.to_msg(), self.timeout))

    def sdf(self, points_W: np.ndarray, source: str = "fused") -> np.ndarray:
        return self.query(points_W, source=source).sdf

    def collision_cost(self, points_W: np.ndarray, epsilon: float) -> np.ndarray:
        return self.query(points_W, collision_epsilon=epsilon).collision

    def mesh(self, resolution: float | None = None, timeout: float = 60.0) -> query_messages.MeshReply:
        msg = self._request("mesh", query_messages.MeshRequest(resolution).to_msg(), timeout)
        return query_messages.MeshReply.from_msg(msg)

    def surfel_map(self, timeout: float = 2.0) -> protocol.SurfelMap | None:
        """Latest explicit planar map (None if no mapper answers)."""
        msg = transport.get_latest(self._session, self._key(keys.MAP_SURFELS), timeout)
        return None if msg is None else protocol.SurfelMap.from_msg(msg)

    def surfels(self, timeout: float = 2.0) -> Surfels | None:
        m = self.surfel_map(timeout)
        return None if m is None else Surfels.from_protocol_dict(m.surfels)

    def weights(self, timeout: float = 2.0) -> protocol.WeightSnapshot | None:
        msg = transport.get_latest(self._session, self._key(keys.MAP_WEIGHTS), timeout)
        return None if msg is None else protocol.WeightSnapshot.from_msg(msg)


class MapArrivals:
    """When each map version arrived here: a subscriber on ``map/index`` (submaps) and
    ``map/weights`` (one network) of the namespace ``ns``. ``lag(version)``: how far a reply
    of that map version trails the newest map (seconds since a newer one arrived; 0 when none
    did) — what the benchmarks and the demo measure answers by."""

    def __init__(self, session, ns: str):
        self.first: dict[int, float] = {}
        self.lock = threading.Lock()
        self._subs = [session.declare_subscriber(keys.key(ns, k), self._on) for k in (keys.MAP_INDEX, keys.MAP_WEIGHTS)]

    def _on(self, sample) -> None:
        t = time.monotonic()
        try:
            v = int(protocol.unpack(transport.payload_bytes(sample.payload))["version"])
        except Exception:  # noqa: BLE001 - a malformed message is not a version
            return
        with self.lock:
            self.first.setdefault(v, t)

    def lag(self, version: int, now: float) -> float:
        with self.lock:
            newer = [t for v, t in self.first.items() if v > version]
        return max(0.0, now - min(newer)) if newer else 0.0

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
