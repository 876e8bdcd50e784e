"""``aisdf-frontend``: streams a posed depth source, selects keyframes by motion and
overlap, and publishes them on ``<namespace>/keyframes``."""

from __future__ import annotations

import argparse
import logging
import threading
import time
import uuid

import numpy as np

from aisdf import keys, protocol, transport
from aisdf.config import add_common_args, config_from_args, service_setup

from .config import FrontendConfig
from .keyframes import KeyframeSelector
from .sources import open_source

log = logging.getLogger("aisdf.frontend")


def to_keyframe(frame: dict, cfg: FrontendConfig) -> protocol.Keyframe:
    depth = np.asarray(frame["depth"], dtype=np.float32)
    scale = None
    if cfg.depth_encoding == "u2":
        depth = np.clip(np.round(np.nan_to_num(depth) * 1000.0), 0, 65535).astype(np.uint16)
        scale = 1000.0
    return protocol.Keyframe(int(frame["frame_id"]), float(frame["stamp"]), depth, np.asarray(frame["K"], np.float64),
                             np.asarray(frame["T_WC"], np.float64), scale, cfg.sensor)


INFO_KEY = "info/frontend"


def stream(cfg: FrontendConfig, publish, stop: threading.Event, counts: dict | None = None) -> dict:
    """Stream the source through keyframe selection into ``publish(msg)``; returns counts
    (``counts``, updated live, when given)."""
    src = open_source(cfg)
    selector = KeyframeSelector(cfg.keyframes)
    counts = counts if counts is not None else {}
    counts.update(frames=0, keyframes=0, total=len(src))
    n = len(src)
    indices = range(cfg.start, n, cfg.stride)
    t0 = time.monotonic()
    stamp0 = None
    while not stop.is_set():
        for i in indices:
            if stop.is_set() or (cfg.max_frames and counts["frames"] >= cfg.max_frames):
                return counts
            frame = src.frame(i)
            stamp = float(frame["stamp"])
            stamp0 = stamp if stamp0 is None else stamp0
            if cfg.realtime:  # the sensor's rate: wait until this frame's time
                wait = (stamp - stamp0) - (time.monotonic() - t0)
                if wait > 0 and stop.wait(wait):
                    return counts
            counts["frames"] += 1
            if selector.is_keyframe(stamp, frame["depth"], frame["K"], frame["T_WC"]):
                publish(to_keyframe(frame, cfg).to_msg())
                counts["keyframes"] += 1
                log.debug("keyframe %d (%s)", frame["frame_id"], selector.last_reason)
        if not cfg.loop:
            break
    return counts


def main(cfg: FrontendConfig, stop: threading.Event | None = None) -> dict:
    stop = stop or threading.Event()
    with transport.open_session(cfg.zenoh) as session:
        token = session.liveliness().declare_token(keys.status_key(cfg.namespace, "frontend", uuid.uuid4().hex[:8]))
        counts: dict = {"frames": 0, "keyframes": 0, "done": False}
        info = transport.serve(session, keys.key(cfg.namespace, INFO_KEY), lambda _req: {"v": 1, **counts}, allow_empty=True)
        key = keys.key(cfg.namespace, keys.KEYFRAMES)
        log.info("frontend streaming %s to %s", cfg.source if cfg.source != "synthetic" else
                 f"synthetic '{cfg.building}'", key)
        stream(cfg, lambda msg: transport.put(session, key, msg), stop, counts)
        counts["done"] = True
        log.info("done: %d frames, %d keyframes", counts["frames"], counts["keyframes"])
        time.sleep(0.2)  # let the last put leave
        if cfg.linger:
            stop.wait()
        info.undeclare()
        token.undeclare()
    return counts


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="aisdf-frontend",
        description="AiSDF frontend: streams posed depth (the built-in synthetic building by default, or a "
        "dataset folder), selects keyframes by motion and overlap, publishes them on <namespace>/keyframes.",
    )
    add_common_args(p)
    p.add_argument("--source", help="synthetic (default) or a dataset kind: generic, 7scenes, tum, icl, ...")
    p.add_argument("--path", help="dataset folder")
    p.add_argument("--building", help="synthetic building (office, manhattan, atlanta, stairs)")
    p.add_argument("--fast", action="store_true", help="as fast as possible instead of the sensor's rate")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    args = p.parse_args(argv)
    cfg = config_from_args(FrontendConfig, args, {"source": args.source, "path": args.path,
                                                  "building": args.building, "max_frames": args.max_frames,
                                                  "realtime": False if args.fast else None})
    stop = service_setup(cfg, "frontend")
    try:
        main(cfg, stop)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"aisdf-frontend: {e}") from None


if __name__ == "__main__":
    cli()
