"""The mapper's control requests (``services/mapper/main.py``'s ``MapperNode`` mixes them in):
``control/mapper/poses`` (protocol 1.11: pose corrections, applied by the training loop between
two steps) and ``control/mapper/save`` / ``load`` (map files, ``aisdf.mapfiles``)."""

from __future__ import annotations

import logging
import threading
import time

from aisdf import keys, mapfiles, protocol

log = logging.getLogger("aisdf.mapper")
POSES_WAIT_S = 60.0  # a pose correction not applied by then is answered busy


class ControlMixin:
    """Needs the node's ``pipeline``, ``lock``, ``train_lock``, ``counts``, ``_pose_jobs``,
    ``_latest``, ``epoch``, ``version``, ``seen``, ``_publish`` and ``save_checkpoint``."""

    # ------------------------------------------------------------------ pose corrections

    def on_poses(self, req: dict) -> dict:
        """``control/mapper/poses`` (protocol 1.11): checked here (ProtocolError: nothing
        changes), applied by the training loop (``_apply_poses``), answered once published."""
        corr = protocol.PoseCorrections.from_msg(req)
        job = {"corr": corr, "done": threading.Event(), "reply": None, "error": None}
        self._pose_jobs.append(job)
        if not job["done"].wait(POSES_WAIT_S):
            raise protocol.ProtocolError("busy", f"the corrections were not applied within {POSES_WAIT_S:.0f} s; "
                                                 "they may still be: send them again (a pose already held is "
                                                 "counted unchanged)")
        if job["error"] is not None:
            raise job["error"]
        return job["reply"]

    def _apply_poses(self) -> None:
        """Every waiting correction batch, between two training steps: the map re-posed, then
        published (and checkpointed: the journal's keyframes carry the old poses)."""
        moved = 0
        jobs = []
        while self._pose_jobs:
            job = self._pose_jobs.popleft()
            jobs.append(job)
            corr: protocol.PoseCorrections = job["corr"]
            t = time.perf_counter()
            try:
                res = self.pipeline.repose({(corr.sensor, i): T for i, T in corr.as_dict().items()})
            except ValueError as e:  # checked on arrival: not expected
                job["error"] = protocol.ProtocolError("bad_request", str(e))
                continue
            moved += res["reposed"]
            for sid in res.get("removed", []):  # gone from the map: no longer answered on get
                self._latest.pop(f"{keys.MAP_SUBMAPS}/{sid}", None)
            self.counts["reposed"] = self.counts.get("reposed", 0) + res["reposed"]
            self.counts["pose_batches"] = self.counts.get("pose_batches", 0) + 1
            log.info("pose corrections from %s: %d keyframes re-posed, %d unknown, %d unchanged, %d submaps "
                     "retrained (%d networks moved, %d started again), %d removed; ms: %s", corr.sensor, res["reposed"],
                     len(res["unknown"]), res["unchanged"], len(res["submaps"]), len(res.get("moved", [])),
                     len(res.get("reset", [])), len(res.get("removed", [])),
                     " ".join(f"{k} {v:.0f}" for k, v in res["timings_ms"].items()))
            job["reply"] = protocol.PosesApplied(
                corr.sensor, res["reposed"], [int(i) for _, i in res["unknown"]], res["unchanged"],
                len(res["submaps"]), 0, self.epoch, time.perf_counter() - t)
        if moved and self.pipeline.n_keyframes:
            self._publish()
            self.save_checkpoint()
        for job in jobs:
            if job["reply"] is not None:
                job["reply"].version = self.version
                job["reply"] = job["reply"].to_msg()
            job["done"].set()

    # ------------------------------------------------------------------ map files

    def on_save(self, _req: dict) -> dict:
        """``control/mapper/save``: the map as a map file (``aisdf.mapfiles``)."""
        with self.train_lock:
            if not self.pipeline.n_keyframes:
                raise protocol.ProtocolError("no_map", "the mapper has no keyframes yet")
            return mapfiles.save_reply(self.checkpoint(), self.pipeline)

    def on_load(self, req: dict) -> dict:
        """``control/mapper/load``: checked and restored first (a bad one changes nothing), swapped in
        between training steps in a new epoch (versions go on above ours), checkpointed, published."""
        new = mapfiles.read_load_request(req)
        with self.train_lock:
            with self.lock:
                self.pipeline, self.seen, self._seen_ids = new.pipeline, new.seen, set()
                self.epoch = max(int(time.time() * 1000), self.epoch + 1)
                self.version = max(self.version, new.version)
                self._latest.clear()
                self._published_all = False
            self.save_checkpoint()  # the journal's keyframes were the old map's
            self._publish()  # saves the new epoch as this incarnation's
            log.info("loaded a map of %d keyframes in epoch %d", new.pipeline.n_keyframes, self.epoch)
            return mapfiles.load_reply(self.pipeline, self.version, self.epoch)
