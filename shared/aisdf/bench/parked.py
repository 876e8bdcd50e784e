"""A parked robot, in-process: ``--frames`` keyframes (default 3,600: five hours of one
every 5 s) at one pose of the synthetic building, each with its own depth noise, into a
submap mapper; prints the keyframes it stored, its ``redundant`` count and its memory
(the mapper's own accounting and the process's resident memory) at the start and the end.
Then a normal walk (``--walk-frames`` frames, the frontend's keyframe selection) with and
without the redundancy test: the keyframes each stores.

    python -m aisdf.bench.parked [--frames 3600] [--size 120x160] [--steps-every 0]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def rss_mb() -> float:
    """The process's resident memory (MB), after handing freed heap back (Linux; 0 elsewhere)."""
    from ..memory import trim

    trim()
    try:
        with open("/proc/self/statm") as f:
            import os

            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def parked(args) -> dict:
    from .. import protocol
    from ..mapper.factory import make_mapper
    from ..synthetic import SyntheticSequence
    from ..synthetic.render import render_depth

    seq = SyntheticSequence(building=args.building, n_frames=120, H=args.H, W=args.W, seed=args.seed)
    f = seq.frame(args.pose)
    mapper = make_mapper("submaps", args.preset, keyframes={"skip_redundant": not args.off})
    out = {"frames": args.frames, "size": f"{args.H}x{args.W}", "skip_redundant": not args.off}
    t0 = time.perf_counter()
    for i in range(args.frames):
        d = render_depth(seq.scene, f["T_WC"], seq.K, seq.H, seq.W, seq.noise, (seq.seed, 1_000_000 + i))
        mapper.add_keyframe(protocol.Keyframe(i, 5.0 * i, d, f["K"], f["T_WC"]))
        if args.steps_every and mapper.ready and i % args.steps_every == 0:
            mapper.step()
        if i == 9:  # the start: the first keyframes in, the networks made
            out["start"] = {"keyframes": mapper.n_keyframes, "rss_mb": round(rss_mb(), 1),
                            "mapper_mb": round(sum(mapper.memory().values()) / 2**20, 2)}
    out["end"] = {"keyframes": mapper.n_keyframes, "rss_mb": round(rss_mb(), 1),
                  "mapper_mb": round(sum(mapper.memory().values()) / 2**20, 2)}
    out["redundant"] = mapper.stats()["redundant"]
    out["evicted"] = mapper.stats()["evicted"]
    out["steps"] = mapper.steps
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


def walk(args) -> dict:
    from ..keyframes import KeyframeSelector, keyframe_message
    from ..mapper.factory import make_mapper
    from ..synthetic import SyntheticSequence

    seq = SyntheticSequence(building="office", n_frames=args.walk_frames, H=args.H, W=args.W, seed=args.seed)
    sel = KeyframeSelector()
    kfs = [keyframe_message(f) for f in seq if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"])]
    out = {"frames": args.walk_frames, "keyframes_sent": len(kfs)}
    for on in (True, False):
        m = make_mapper("submaps", args.preset, keyframes={"skip_redundant": on})
        for kf in kfs:
            m.add_keyframe(kf)
        out["stored_with_check" if on else "stored_without_check"] = m.n_keyframes
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m aisdf.bench.parked", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=3600)
    p.add_argument("--size", default="120x160", help="HxW of the depth images (the frontend's default)")
    p.add_argument("--building", default="atlanta")
    p.add_argument("--pose", type=int, default=10, help="the frame whose pose the robot is parked at")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--steps-every", type=int, default=0, help="a training step every n keyframes (0: none)")
    p.add_argument("--off", action="store_true", help="without the redundancy test")
    p.add_argument("--walk-frames", type=int, default=900, help="the walk's frames (0: no walk)")
    args = p.parse_args(argv)
    args.H, args.W = (int(x) for x in args.size.lower().split("x"))
    import torch

    torch.set_num_threads(1)
    np.seterr(all="ignore")
    res = {"parked": parked(args)}
    if args.walk_frames:
        res["walk"] = walk(args)
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
