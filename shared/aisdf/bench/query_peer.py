"""``aisdf bench query``'s peer: the voxel map a team would otherwise run (a TSDF fused from
the same keyframes with open3d, then a Euclidean signed distance field with scipy, as the
paper's Voxblox-like baseline, :class:`aisdf.bench.voxel.VoxelEsdf`) at 5 cm and 2 cm, beside
the served answer on the same points:

* accuracy on the demo's evaluation points (mean SDF error against the truth);
* the lookup of 10,000 points (trilinear, value and gradient) against the baked answer's;
* one map update: integrating a frame plus the distance field of the whole grid, against a
  training step plus the re-bake after one submap changed (its weights perturbed, a new
  version, then the engine's incremental bake), and a full bake;
* memory: the ESDF grid's bytes (value and gradient, float32) against the bake's arrays.
"""

from __future__ import annotations

import time

import numpy as np

from .. import protocol, query_messages


def _p50_ms(fn, repeats: int = 10) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def keyframe_indices(seq) -> list[int]:
    """The demo's keyframes (the frontend's selector over the sequence)."""
    from ..keyframes import KeyframeConfig, KeyframeSelector

    sel = KeyframeSelector(KeyframeConfig())
    out = []
    for i in range(len(seq)):
        f = seq.frame(i)
        if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
            out.append(i)
    return out


def training_step_ms(seq, kfs: list[int], n_keyframes: int = 12, steps: int = 20) -> float:
    """p50 of a submap mapper's training step (cpu preset) with the first keyframes."""
    from ..mapper.factory import make_mapper

    pipe = make_mapper("submaps", "cpu")
    for i in kfs[:n_keyframes]:
        f = seq.frame(i)
        pipe.add_keyframe(protocol.Keyframe(f["frame_id"], f["stamp"], np.asarray(f["depth"], np.float32), f["K"],
                                            f["T_WC"]))
    if not pipe.ready:
        return float("nan")
    for _ in range(3):
        pipe.step()
    return _p50_ms(pipe.step, steps)


def rebake_one_submap_s(eng, messages) -> float | None:
    """Wall time of the engine's re-bake after one submap changed (its weights perturbed and
    published at a new version, with the index)."""
    from .. import keys

    subs = [(k, m) for k, m in messages if k.startswith(keys.MAP_SUBMAPS + "/")]
    idx = next((protocol.SubmapIndex.from_msg(m) for k, m in messages if k == keys.MAP_INDEX), None)
    if not subs or idx is None or eng.baked is None:
        return None
    snap = protocol.WeightSnapshot.from_msg(sorted(subs, key=lambda km: km[0])[len(subs) // 2][1])
    rng = np.random.default_rng(0)
    state = {k: (v + np.asarray(1e-4 * rng.standard_normal(v.shape), v.dtype) if v.dtype.kind == "f" else v)
             for k, v in snap.state.items()}
    version = idx.version + 1
    snap.state, snap.version, snap.step = state, version, snap.step + 1
    eng.set_submap(snap)
    eng.set_index(protocol.SubmapIndex(version, time.time(), idx.grid, {
        **idx.submaps, snap.submap["id"]: {"version": version, "step": snap.step}}, idx.epoch))
    t = time.perf_counter()
    eng.bake_now()
    return time.perf_counter() - t


def run(seq, eng, messages, pts: np.ndarray, gt: np.ndarray, bake_full_s: float, say=print) -> dict:
    from .voxel import VoxelEsdf

    say("  the voxel map beside it: the demo's keyframes fused at 5 cm and 2 cm")
    kfs = keyframe_indices(seq)
    q = pts[np.random.default_rng(3).choice(len(pts), 10_000, replace=False)]
    res: dict = {"keyframes": len(kfs), "voxel": {}}
    for vs in (0.05, 0.02):
        m = VoxelEsdf(voxel_size=vs, max_depth=seq.max_depth if hasattr(seq, "max_depth") else 5.0)
        for i in kfs:
            f = seq.frame(i)
            m.integrate(f["depth"], f["K"], f["T_WC"])
        m.finalize()
        m.gradient(q[:1])  # the gradient grid, once
        t = m.timing_summary()
        esdf, _ = m.grid()
        res["voxel"][f"{int(round(vs * 100))}cm"] = {
            "sdf_error_cm": 100 * float(np.abs(m.sdf(pts) - gt).mean()),
            "lookup_10k_ms": _p50_ms(lambda: (m.sdf(q), m.gradient(q))),
            "integrate_ms": t["integrate_ms"], "esdf_s": t["finalize_ms"] / 1e3, "voxels": t["voxels"],
            "grid_mb": esdf.size * 4 * 4 / 1e6}
    req = query_messages.SdfRequest(q.astype(np.float32), gradient=True)
    res["served"] = {
        "sdf_error_cm": 100 * float(np.abs(eng.answer_sdf(query_messages.SdfRequest(pts)).sdf - gt).mean()),
        "lookup_10k_ms": _p50_ms(lambda: eng.answer_sdf(req)),
        "bake_mb": eng.baked.field.nbytes / 1e6 if eng.baked is not None else None,
        "training_step_ms": training_step_ms(seq, kfs),
        "rebake_one_submap_s": rebake_one_submap_s(eng, messages), "bake_full_s": bake_full_s}
    return res


def report(res: dict) -> str:
    s, v5, v2 = res["served"], res["voxel"]["5cm"], res["voxel"]["2cm"]
    rebake = s["rebake_one_submap_s"]
    return "\n".join([
        f"| beside the voxel map ({res['keyframes']} keyframes fused) | served (baked) | voxel 5 cm | voxel 2 cm |",
        "|---|---:|---:|---:|",
        f"| mean SDF error on the evaluation points (cm) | {s['sdf_error_cm']:.2f} | {v5['sdf_error_cm']:.2f} | "
        f"{v2['sdf_error_cm']:.2f} |",
        f"| 10,000 points, value and gradient, in-process p50 (ms) | {s['lookup_10k_ms']:.1f} | "
        f"{v5['lookup_10k_ms']:.1f} | {v2['lookup_10k_ms']:.1f} |",
        f"| a map update: training step (ms) / integrate a frame (ms) | {s['training_step_ms']:.0f} | "
        f"{v5['integrate_ms']:.0f} | {v2['integrate_ms']:.0f} |",
        f"| a map update: re-bake after one submap changed / distance field of the grid (s) | "
        f"{'-' if rebake is None else round(rebake, 2)} (full bake {s['bake_full_s']:.2f}) | {v5['esdf_s']:.2f} | "
        f"{v2['esdf_s']:.2f} |",
        f"| memory: baked arrays / ESDF and gradient grids (MB) | "
        f"{'-' if s['bake_mb'] is None else round(s['bake_mb'])} | {v5['grid_mb']:.0f} | {v2['grid_mb']:.0f} |"])
