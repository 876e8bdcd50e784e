"""``aisdf bench bake``: what the query service's bake costs as a submap
map grows, incremental (re-evaluating only around the submaps and surfels that changed)
against a full bake of the same map, and the tiled mesh's memory.

A SubmapPipeline walks a synthetic building (the floor by default) at a few training steps
per keyframe; after every ``--period`` keyframes its messages of that period (only the
submaps trained since their last publication, the index and the surfels, as the mapper
publishes them) go into a QueryEngine, which bakes. From ``--bake-from`` keyframes on, per period it prints the submaps,
those that changed, the blocks baked, and the evaluations and seconds of the incremental
bake and of a full bake of the same map with the same surfels (the incremental bake's
reference: surfels that moved less than ``bake_surfel_tol`` keep the geometry they were
baked with), their answers compared (they should be equal), and how far the fused field
with the newest surfels is from the reference's (what the tolerance costs: a tiny move can
flip the fused answer's gate at ``fuse_radius`` or move the measured rule's ramp).
The incremental evaluations include those of the bake of newly mapped space alone that goes
first when the map grew. Figures, not assertions: the machine's load changes the seconds, not the evaluations."""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
import torch

from .. import keys, protocol, query_messages
from ..baked import bake
from ..mapping.frames import Frame
from ..structure.fusion import DEFAULT_FUSE_RADIUS
from ..submaps.pipeline import SubmapPipeline
from ..query.engine import QueryEngine
from ..synthetic import SyntheticSequence


def feed(engine: QueryEngine, messages) -> int:
    """Packed (key, bytes) map messages into ``engine``; how many submap snapshots it took."""
    n = 0
    for key, data in messages:
        taken = engine.take(key, protocol.unpack(data))
        n += key.startswith(keys.MAP_SUBMAPS + "/") and bool(taken)
    return n


def compare(e: QueryEngine, version: int, n_keyframes: int, changed: int) -> np.ndarray:
    """Bake ``e``'s newest map incrementally, then fully with the same surfels; print the row;
    (incremental evaluations, seconds, full evaluations, seconds)."""
    for sm in e.state.submaps.submaps.values():  # warm the new networks up (torch's first call)
        e._implicit(sm.net, np.zeros((64, 3), np.float32), True)
    t = time.perf_counter()
    n_ext = e.baker.extensions
    inc = e.bake_now().field
    t_inc = time.perf_counter() - t
    # with the bake of the newly mapped space alone that went first, if one did
    ext = e.baker.last_extension.get("evaluations", 0) if e.baker.extensions > n_ext else 0
    # The full bake of the same map with the surfels the incremental one was computed with
    # (its reference: surfels that moved less than bake_surfel_tol keep their baked geometry).
    ref_state = e.state.with_surfels(e.baked.surfel_ref, e.state.surfel_version)
    t = time.perf_counter()
    full = bake(e.baker.fused_fn(ref_state), e.state.observed, e.baker.config)
    t_full = time.perf_counter() - t
    pts = e.state.observed.origin + np.random.default_rng(version).uniform(
        0, 1, (20_000, 3)) * (e.state.observed.bounds[1] - e.state.observed.origin)
    fa, _, ca = inc.query(pts, False)
    fb, _, cb = full.query(pts, False)
    d = np.abs(fa - fb)[ca & cb]
    diff, over = (float(d.max()), float(np.mean(d > 0.002))) if len(d) else (0.0, 0.0)
    assert (ca == cb).all()
    # What the tolerance costs: the fused field with the newest surfels against the reference's.
    inside = pts[ca]
    tol_d = np.abs(e.baker.fused_fn(e.state)(inside)[0] - e.baker.fused_fn(ref_state)(inside)[0])
    tol_max, tol_over = (float(tol_d.max()), float(np.mean(tol_d > 0.002))) if len(tol_d) else (0.0, 0.0)
    print(f"| {version} | {n_keyframes} | {len(e.state.submaps.submaps)} | {changed} | {inc.stats['blocks']:,} "
          f"| {inc.stats['evaluations'] + ext:,} / {t_inc:.2f} | {full.stats['evaluations']:,} / {t_full:.2f} "
          f"| {diff:.1e} / {over:.4f} | {tol_max:.1e} / {tol_over:.4f} |", flush=True)
    return np.array([inc.stats["evaluations"] + ext, t_inc, full.stats["evaluations"], t_full], float)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="aisdf bench bake", description=__doc__.split("\n\n")[0])
    ap.add_argument("--building", default="floor")
    ap.add_argument("--frames", type=int, default=3000, help="frames of the walk (one keyframe every --every)")
    ap.add_argument("--every", type=int, default=30)
    ap.add_argument("--steps", type=int, default=3, help="training steps per keyframe")
    ap.add_argument("--period", type=int, default=2, help="keyframes per publication period")
    ap.add_argument("--bake-from", type=int, default=60, help="first keyframe after which the map is baked (before: "
                    "only published into the engine)")
    ap.add_argument("--after", type=int, default=8, help="re-bakes after the walk, each after one training step "
                    "(one submap changed)")
    ap.add_argument("--width", type=int, default=32, help="network width (the bake's cost is per evaluation)")
    ap.add_argument("--mesh-resolution", type=float, default=0.1)
    ap.add_argument("--fuse-radius", type=float, default=DEFAULT_FUSE_RADIUS,
                    help="the engine's fuse_radius (m): how far around a changed surfel a re-bake re-evaluates")
    ap.add_argument("--measured", action=argparse.BooleanOptionalAction, default=True,
                    help="fused answers with the submaps' measured points (protocol 1.4; --no-measured: 1.3's)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seq = SyntheticSequence(building=args.building, n_frames=args.frames, H=60, W=80, seed=0)
    p = SubmapPipeline.from_settings("cpu", {"network": {"width": args.width}, "n_rays": 40})
    e = QueryEngine(device="cpu", bake_threads=1, fuse_radius=args.fuse_radius, measured=args.measured)
    version = 0
    print(f"{args.building}: {args.frames} frames, a keyframe every {args.every}, {args.steps} steps each, "
          f"published every {args.period} keyframes; width {args.width}; measured points "
          f"{'on' if args.measured else 'off'}")
    print("| version | keyframes | submaps | changed | blocks | incremental: evaluations / s | full: evaluations / s "
          "| difference: max (m) / share > 2 mm | newest surfels against the reference: max (m) / share > 2 mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    totals = np.zeros(4)
    for n, i in enumerate(range(0, args.frames, args.every), start=1):
        f = seq.frame(i)
        p.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        for _ in range(args.steps):
            if p.submaps:
                p.step()
        if n % args.period:
            continue
        version += 1
        changed = feed(e, p.map_messages(version, changed_only=True, epoch=1))
        if e.state is None or e.state.observed is None or n < args.bake_from:
            continue
        first = e.baked is None
        row = compare(e, version, p.n_keyframes, changed)
        if not first:
            totals += row
    print(f"after the first bake, in all: incremental {int(totals[0]):,} evaluations in {totals[1]:.1f} s, full "
          f"{int(totals[2]):,} in {totals[3]:.1f} s ({totals[0] / max(totals[2], 1):.2f} of the evaluations)")
    if args.after:
        # The walk done, the mapper refines: each step trains one submap (the one with the fewest
        # steps per keyframe); publishing after every step, one submap changed per re-bake.
        print(f"\nafter the walk: {args.after} re-bakes, each after one training step (one submap changed)")
        after = np.zeros(4)
        ratios = []
        for _ in range(args.after):
            p.step()
            version += 1
            changed = feed(e, p.map_messages(version, changed_only=True, epoch=1))
            row = compare(e, version, p.n_keyframes, changed)
            after += row
            ratios.append(row[0] / max(row[2], 1))
        print(f"after the walk, one submap changed: incremental {int(after[0]):,} evaluations in {after[1]:.1f} s, full "
              f"{int(after[2]):,} in {after[3]:.1f} s ({after[0] / max(after[2], 1):.2f} of the evaluations; per "
              f"re-bake {min(ratios):.2f}-{max(ratios):.2f})")
    # The whole map's mesh, tiled, and its peak numpy memory against one tile for the whole box.
    for tile in (64, 100_000):
        e.mesh_tile = tile
        tracemalloc.start()
        t = time.perf_counter()
        m = e.answer_mesh(query_messages.MeshRequest(args.mesh_resolution))
        dt = time.perf_counter() - t
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        n_cells = np.prod(np.ceil((e.state.bounds[1] - e.state.bounds[0]) / args.mesh_resolution + 5))
        print(f"mesh at {args.mesh_resolution} m ({int(n_cells):,} samples), tiles of {min(tile, 10 ** 9)}^3: "
              f"{len(m.vertices):,} vertices, {len(m.faces):,} faces, {dt:.1f} s, peak numpy memory {peak / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
