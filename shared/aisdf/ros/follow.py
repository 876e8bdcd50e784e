"""Following a SLAM system's ``map -> odom`` corrections (protocol 1.11).

A keyframe's pose comes from TF: ``fixed_frame`` (map) -> ``odom_frame`` (odom) -> ... ->
camera, at the image's stamp. When the SLAM system closes a loop it moves ``map -> odom``;
the keyframes already sent keep their odometry pose (``odom -> camera``: odometry is locally
consistent), so their right pose is the new ``map -> odom`` times that. :class:`MapOdomFollower`
keeps, for the last ``max_keyframes`` keyframes sent, their stamp, the ``map -> odom`` they
were placed with and their pose in ``odom``; ``poll()`` looks ``map -> odom`` up again and
returns the corrected ``T_WC`` of every keyframe whose ``map -> odom`` moved by more than
``min_m`` or ``min_deg`` (the front end sends them with ``aisdf.poses.send_corrections``).

Which ``map -> odom`` (``mode``):

* ``"stamp"`` (default): the one at the keyframe's own stamp, from the TF buffer. It changes
  when the SLAM system publishes transforms for past stamps again (a re-optimised
  trajectory), or when a sample arrives between the ones the keyframe was placed with.
  A keyframe whose stamp has left the buffer's cache (``cache_s``, 30 s by default) is no
  longer followed.
* ``"latest"``: the newest one in the buffer, for every keyframe followed: what a SLAM system
  that only publishes its current ``map -> odom`` (slam_toolbox, Cartographer) means after a
  loop closure, if its correction holds for the whole odometry trajectory since. It moves every
  followed keyframe by the same correction, also those the loop did not concern.
"""

from __future__ import annotations

import collections
import logging
import time

import numpy as np

from .tf import TFBuffer, TFError

log = logging.getLogger("aisdf.ros.follow")


def _moved(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two rigid transforms."""
    d = np.linalg.inv(A) @ B
    ang = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(ang)


class MapOdomFollower:
    """See the module docstring. ``track`` each keyframe sent; ``poll`` for corrections."""

    def __init__(self, tf: TFBuffer, fixed_frame: str, odom_frame: str, *, mode: str = "stamp",
                 max_keyframes: int = 5000, min_m: float = 0.01, min_deg: float = 0.5, period_s: float = 1.0):
        if mode not in ("stamp", "latest"):
            raise ValueError(f"mode {mode!r}: choose stamp or latest")
        self.tf, self.fixed, self.odom, self.mode = tf, fixed_frame, odom_frame, mode
        self.min_m, self.min_deg, self.period_s = float(min_m), float(min_deg), float(period_s)
        # frame_id -> (stamp_ns, T_map_odom as placed or last corrected, T_odom_camera)
        self.kept: collections.OrderedDict[int, tuple[int, np.ndarray, np.ndarray]] = collections.OrderedDict()
        self.max_keyframes = int(max_keyframes)
        self.counts = {"followed": 0, "untracked": 0, "corrected": 0, "batches": 0}
        self._last_poll = -np.inf

    def _map_odom(self, stamp_ns: int) -> np.ndarray | None:
        try:
            if self.mode == "latest":
                rng = self.tf.time_range(self.fixed, self.odom)
                stamp_ns = rng[1] if rng is not None else stamp_ns  # a static edge: any stamp
            return self.tf.lookup(self.fixed, self.odom, stamp_ns)
        except TFError:
            return None

    def track(self, frame_id: int, stamp_ns: int, T_WC: np.ndarray) -> bool:
        """Follow a keyframe just sent (``T_WC`` its pose in ``fixed_frame``). False when
        ``map -> odom`` cannot be looked up at its stamp (no odom frame in the chain)."""
        M = None
        try:
            M = self.tf.lookup(self.fixed, self.odom, int(stamp_ns))
        except TFError as e:
            if self.counts["untracked"] == 0:
                log.warning("map -> odom corrections not followed for keyframe %d: %s", frame_id, e)
        if M is None:
            self.counts["untracked"] += 1
            return False
        self.kept[int(frame_id)] = (int(stamp_ns), M, np.linalg.inv(M) @ np.asarray(T_WC, np.float64))
        self.kept.move_to_end(int(frame_id))
        while len(self.kept) > self.max_keyframes:
            self.kept.popitem(last=False)
        self.counts["followed"] = len(self.kept)
        return True

    def poll(self, now: float | None = None, force: bool = False) -> dict[int, np.ndarray]:
        """``{frame_id: corrected T_WC}`` of the followed keyframes whose ``map -> odom`` moved
        beyond the thresholds since they were placed or last corrected (at most once per
        ``period_s``, unless ``force``). The returned poses become the ones held."""
        now = time.monotonic() if now is None else now
        if not force and now - self._last_poll < self.period_s:
            return {}
        self._last_poll = now
        out = {}
        for fid, (stamp, M_old, T_OC) in list(self.kept.items()):
            M = self._map_odom(stamp)
            if M is None:
                continue
            dm, dd = _moved(M_old, M)
            if dm > self.min_m or dd > self.min_deg:
                out[fid] = M @ T_OC
                self.kept[fid] = (stamp, M, T_OC)
        if out:
            self.counts["corrected"] += len(out)
            self.counts["batches"] += 1
        return out


class CorrectionSender:
    """Sends correction batches with ``aisdf.poses.send_corrections`` on its own thread (a
    mapper answers once the corrected map is published: seconds), batches that wait merged
    (the newest pose of a keyframe wins). A mapper before 1.11 does not answer: logged."""

    def __init__(self, session, namespace: str, sensor: str, timeout: float = 30.0):
        import threading

        self.session, self.ns, self.sensor, self.timeout = session, namespace, sensor, timeout
        self._waiting: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.counts = {"sent": 0, "reposed": 0, "unknown": 0, "failed": 0}
        self._thread = threading.Thread(target=self._run, name="corrections", daemon=True)
        self._thread.start()

    def submit(self, corrections: dict[int, np.ndarray]) -> None:
        with self._lock:
            self._waiting.update(corrections)
        self._wake.set()

    def _run(self) -> None:
        from ..poses import send_corrections

        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                batch, self._waiting = self._waiting, {}
            if not batch:
                continue
            try:
                rep = send_corrections(self.session, self.ns, self.sensor, batch, self.timeout)
            except (TimeoutError, Exception) as e:  # noqa: BLE001 - the front end goes on mapping
                self.counts["failed"] += 1
                log.warning("pose corrections of %d keyframes not applied: %s", len(batch), e)
                continue
            self.counts["sent"] += len(batch)
            self.counts["reposed"] += rep["reposed"]
            self.counts["unknown"] += len(rep["unknown"])
            log.info("map -> odom moved: %d keyframes re-posed in map version %d (%d not in the map)",
                     rep["reposed"], rep["version"], len(rep["unknown"]))

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
