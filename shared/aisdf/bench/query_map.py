"""The demo building's map for ``aisdf bench query`` (``bench/query.py``): trained in-process
as the demo's mapper makes it, cached with the messages the mapper publishes for it, and
those messages fed to an in-process engine or republished at a new version."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .. import keys, protocol
from ..mapper import MAPPER_KINDS

# Bumped when what a cached map holds changes: 2 = the one-network map's snapshot carries its
# measured points (protocol 1.5); an older cache is trained again.
CACHE_FORMAT = 2
DEFAULT_STEPS = {"submaps": 1200, "single": 900}  # about what the demo's mapper makes in 180 s


def demo_map(out: Path, train_steps: int | None = None, seed: int = 0, duration: float = 180.0, quiet: bool = False,
             mapper: str = "submaps") -> dict:
    """Train (or load from ``out/map-<mapper>.msgpack``) the demo building's map as the demo
    makes it: ``messages``, what the mapper publishes for it ((key, message) pairs)."""
    from ..keyframes import KeyframeConfig, KeyframeSelector
    from ..mapper.factory import make_mapper
    from ..synthetic import SyntheticSequence

    if mapper not in MAPPER_KINDS:
        raise ValueError(f"mapper must be one of {MAPPER_KINDS}, not {mapper!r}")
    train_steps = train_steps or DEFAULT_STEPS[mapper]
    path = out / f"map-{mapper}.msgpack"
    fps = 30.0
    n_frames = int(max(10.0, 0.75 * duration) * fps)  # as the demo
    seq = SyntheticSequence(building="office", n_frames=n_frames, fps=fps, seed=seed)
    if path.exists():
        m = protocol.unpack(path.read_bytes())
        if (m.get("train_steps") == train_steps and m.get("n_frames") == n_frames and m.get("mapper") == mapper
                and m.get("cache_format") == CACHE_FORMAT):
            return {"seq": seq, **m}
    t0 = time.perf_counter()
    sel = KeyframeSelector(KeyframeConfig())
    kfs = []
    for i in range(n_frames):
        f = seq.frame(i)
        if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
            kfs.append(i)
    pipe = make_mapper(mapper, "cpu")
    per = max(1, train_steps // max(1, len(kfs)))
    for j, i in enumerate(kfs):
        f = seq.frame(i)
        pipe.add_keyframe(protocol.Keyframe(f["frame_id"], f["stamp"], np.asarray(f["depth"], np.float32), f["K"],
                                            f["T_WC"]))
        # per steps a keyframe, the rest after the last; a submap mapper steps once its grid
        # exists (a few keyframes in: it waits for the Atlanta frame), catching up then.
        target = per * (j + 1) if j < len(kfs) - 1 else train_steps
        while pipe.steps < target and pipe.ready:
            pipe.step()
        if not quiet and (j % 20 == 0 or j == len(kfs) - 1):
            print(f"  training the demo map: keyframe {j + 1}/{len(kfs)}, step {pipe.steps}/{train_steps}, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    if mapper == "submaps":
        messages = [(k, protocol.unpack(v)) for k, v in pipe.map_messages(1, changed_only=False, epoch=1)]
    else:
        messages = [(keys.MAP_WEIGHTS, pipe.weight_snapshot(1).to_msg()), (keys.MAP_SURFELS, pipe.surfel_map(1).to_msg())]
    m = {"cache_format": CACHE_FORMAT, "mapper": mapper, "train_steps": train_steps, "steps": pipe.steps, "n_frames": n_frames, "keyframes": len(kfs),
         "messages": messages, "describe": pipe.describe()}
    out.mkdir(parents=True, exist_ok=True)
    path.write_bytes(protocol.pack(m))
    return {"seq": seq, **m}


def versioned(messages, version: int) -> list[tuple[str, dict]]:
    """The map's messages as the mapper would publish them for map ``version`` (every
    submap changed): each snapshot, the index (its entries too) and the surfels at ``version``."""
    out = []
    for key, msg in messages:
        msg = dict(msg, version=version)
        if key == keys.MAP_INDEX:
            msg["submaps"] = {sid: dict(v, version=version) for sid, v in msg["submaps"].items()}
        out.append((key, msg))
    return out


def engine_of(m: dict, bake_threads: int = 2):
    """An in-process query engine holding the map ``m`` (``demo_map``'s)."""
    from ..query.engine import QueryEngine

    e = QueryEngine(device="auto", bake_threads=bake_threads)
    for key, msg in m["messages"]:
        e.take(key, msg)
    return e


def warm(e) -> None:
    """torch's first call of each network (not the bake's to pay)."""
    st = e.state
    nets = [st.net] if st.submaps is None else [sm.net for sm in st.submaps.submaps.values()]
    for net in nets:
        e._implicit(net, np.zeros((4096, 3), np.float32), True)
