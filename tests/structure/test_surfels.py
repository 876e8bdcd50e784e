"""Atlanta-aware surfels against analytic rooms (rotated worlds, Kinect-like noise)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from aisdf.structure.atlanta import AtlantaEstimator
from aisdf.geometry import backproject, transform
from aisdf.structure.surfel_config import SurfelConfig
from aisdf.structure.surfel_fit import find_planes, find_rectangles
from aisdf.structure.surfel_map import explicit_sdf
from aisdf.structure.surfels import extract_surfels, keyframe_points
from helpers.atlanta_scene import atlanta_room, camera, trajectory


def run_sequence(seed: int, H: int, n: int, config: SurfelConfig | None = None, use_local: bool = False):
    """Per keyframe: (T_WC, depth, noise-free depth, LocalAtlanta, surfels, mask, timings ms).

    Surfels use the global frame's directions (every published one), or with ``use_local``
    only those the keyframe's histogram supports (the paper's local frame)."""
    W = H * 4 // 3
    scene = atlanta_room(seed)
    K = camera(H)
    rng = np.random.default_rng(seed)
    est = AtlantaEstimator()
    out = []
    for i, T in enumerate(trajectory(scene, n, seed)):
        depth = scene.render(T, K, H, W, rng)
        t0 = time.perf_counter()
        kp = keyframe_points(depth, K, T, config)
        t1 = time.perf_counter()
        local = est.update(kp.normals_W, T)
        t2 = time.perf_counter()
        s, mask = extract_surfels(depth, K, T, local if use_local else local.frame, config, frame_id=i, points=kp)
        t3 = time.perf_counter()
        out.append({"T": T, "depth": depth, "gt": scene.render(T, K, H, W, None), "local": local, "surfels": s,
                    "mask": mask, "ms": (1e3 * (t1 - t0), 1e3 * (t2 - t1), 1e3 * (t3 - t2))})
    return scene, K, est, out


def surfel_checks(scene, s) -> tuple[np.ndarray, np.ndarray]:
    """Per surfel: share of its area on a true face, |plane offset| of its centre to that face."""
    faces = scene.faces()
    R_SW = np.linalg.inv(scene.T_WS)[:3, :3]
    fracs, offs = [], []
    for k in range(len(s)):
        pts, _ = s[k: k + 1].sample_uniform(1500, np.random.default_rng(k))
        x = scene.to_scene(pts)
        n_S = R_SW @ s.normal[k]
        best = (0.0, np.inf)
        for f in faces:
            if n_S @ f["normal"] < np.cos(np.radians(5)):  # same plane orientation (free side)
                continue
            fr = scene.on_face(x, f, 0.03, 0.01).mean()
            if fr > best[0]:
                best = (fr, abs(scene.to_scene(s.center[k: k + 1])[0] @ f["normal"] - f["offset"]))
        fracs.append(best[0])
        offs.append(best[1])
    return np.array(fracs), np.array(offs)


@pytest.fixture(scope="module")
def seq120():
    return run_sequence(3, 120, 16)


@pytest.mark.parametrize("seed,H", [(3, 120), (6, 120), (5, 240)])
def test_surfels_lie_on_true_faces(seed: int, H: int, seq120) -> None:
    scene, K, est, out = seq120 if (seed, H) == (3, 120) else run_sequence(seed, H, 12)
    all_f, all_o, n, area = [], [], 0, 0.0
    for kf in out:
        f, o = surfel_checks(scene, kf["surfels"])
        all_f += list(f)
        all_o += list(o)
        n += len(kf["surfels"])
        area += kf["surfels"].area().sum()
    all_f, all_o = np.array(all_f), np.array(all_o)
    print(f"seed {seed} {H}p: {n} surfels, {area:.1f} m^2; area on a true face min {all_f.min():.3f} "
          f"median {np.median(all_f):.3f}; centre plane offset max {100 * all_o.max():.2f} cm "
          f"median {100 * np.median(all_o):.2f} cm; mask share {np.mean([kf['mask'].mean() for kf in out]):.2f}")
    assert n >= 4 * len(out)
    assert all_f.min() >= 0.9
    assert all_o.max() <= 0.02


def test_surfel_geometry_and_mask(seq120) -> None:
    scene, K, est, out = seq120
    M = len(est.frame.horizontal)
    for kf in out[4:]:
        s, T, mask = kf["surfels"], kf["T"], kf["mask"]
        assert mask.shape == kf["depth"].shape and mask.dtype == bool
        if not len(s):
            continue
        cam = T[:3, 3]
        assert np.all(np.einsum("nc,nc->n", s.normal, cam - s.center) > 0)  # normals face free space
        for a, b in ((s.normal, s.axis1), (s.normal, s.axis2), (s.axis1, s.axis2)):
            assert np.allclose(np.einsum("nc,nc->n", a, b), 0, atol=1e-9)
        assert np.all((s.direction >= -1) & (s.direction < M))
        wall = s.direction >= 0
        assert np.allclose(np.abs(s.axis1[wall] @ kf["local"].vertical), 1)
        assert np.allclose(np.abs(s.normal[~wall] @ kf["local"].vertical), 1)
        h = kf["local"].frame.horizontal[s.direction[wall]]
        assert np.allclose(np.abs(np.einsum("nc,nc->n", s.normal[wall], h)), 1)
        assert np.all(s.keyframe == s.keyframe[0])
        # Mask pixels lie on a kept surfel (noise-free points within a few cm).
        P = transform(T, backproject(kf["gt"], K)[mask])
        d, _, _ = explicit_sdf(P, s)
        assert np.percentile(np.abs(d), 99) < 0.05
    assert np.mean([kf["mask"].mean() for kf in out[4:]]) > 0.4


def test_paper_variant_local_frame_and_floor_axes() -> None:
    scene, K, est, out = run_sequence(4, 120, 10, SurfelConfig(floor_axes="reference"), use_local=True)
    fr = np.concatenate([surfel_checks(scene, kf["surfels"])[0] for kf in out])
    assert len(fr) > 20 and fr.min() >= 0.9


def test_find_planes_fixed_normal() -> None:
    rng = np.random.default_rng(0)
    off = np.concatenate([rng.normal(0.0, 0.005, 500), rng.normal(0.74, 0.005, 200), rng.uniform(-2, 2, 60)])
    cfg = SurfelConfig()
    planes = find_planes(off, np.full(len(off), 0.02), np.ones(len(off)), cfg, 30)
    assert len(planes) >= 2
    (d0, i0), (d1, i1) = planes[:2]
    assert abs(d0) < 0.002 and abs(d1 - 0.74) < 0.002
    assert i0[:500].mean() > 0.99 and i1[500:700].mean() > 0.99 and not (i0 & i1).any()


def test_find_rectangles_l_shape() -> None:
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 3, (6000, 2))
    uv = uv[~((uv[:, 0] > 1.5) & (uv[:, 1] > 1.5))]  # an L: the top-right quadrant is empty
    rects = find_rectangles(uv, 0.08, SurfelConfig(), rng)
    assert len(rects) >= 2
    covered = 0.0
    for lo, hi, inside in rects:
        assert np.all(lo >= -1e-9) and np.all(hi <= 3 + 1e-9)
        inter = np.clip(np.minimum(hi, 3) - np.maximum(lo, 1.5), 0, None)  # overlap with the empty quadrant
        assert inter.prod() <= 0.05 * np.prod(hi - lo)
        covered += np.prod(hi - lo)
    assert covered > 0.9 * 6.75


# Median per-keyframe time (points and normals, Atlanta update, surfels and mask), measured by
# ``pytest -s tests/structure/test_surfels.py -k timing`` at 34be166 on 2026-12-05 (2 CPU cores
# shared with another job): 41.3 ms at 160x120, 78.6 ms at 320x240. Bounds 6x that: a timing
# test with a margin that load does not break.
TIMING_BOUND_MS = {120: 250.0, 240: 500.0}


def test_timing_per_keyframe(seq120) -> None:
    """Per-keyframe Atlanta update + surfel extraction times, well within a keyframe period."""
    for H, out in ((120, seq120[3]), (240, run_sequence(5, 240, 8)[3])):
        ms = np.array([kf["ms"] for kf in out[2:]])  # after initialisation
        med = np.median(ms, axis=0)
        total = float(np.median(ms.sum(axis=1)))
        print(f"{H * 4 // 3}x{H}: points+normals {med[0]:.1f} ms, Atlanta update {med[1]:.1f} ms, "
              f"surfels+mask {med[2]:.1f} ms, total {total:.1f} ms (max {ms.sum(axis=1).max():.1f})")
        assert 0 < total < TIMING_BOUND_MS[H], (H, total)


def test_nothing_before_initialisation() -> None:
    scene = atlanta_room(1)
    K = camera(120)
    T = trajectory(scene, 4, 1)[0]
    depth = scene.render(T, K, 120, 160, np.random.default_rng(1))
    est = AtlantaEstimator()
    assert not est.frame.valid
    s, mask = extract_surfels(depth, K, T, est.frame)
    assert len(s) == 0 and not mask.any() and mask.shape == depth.shape
    local = est.update(keyframe_points(depth, K, T).normals_W, T)
    assert local.initialised and local.frame.valid  # one good keyframe is enough here
    s, mask = extract_surfels(depth, K, T, local.frame)
    assert len(s) > 0 and mask.any()
