"""Explicit SDF of rectangles (exact values) and the global surfel map (merging)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aisdf.structure.atlanta import AtlantaEstimator
from aisdf.geometry import backproject, transform
from aisdf.structure.surfel_map import ExplicitSdf, GlobalSurfelMap, SurfelMapConfig, explicit_sdf
from aisdf.structure.surfel_types import Surfels
from aisdf.structure.surfels import extract_surfels, keyframe_points
from helpers.atlanta_scene import atlanta_room, camera, trajectory


def rects(centers, normals, axes1, extents, direction=0, keyframe=0) -> Surfels:
    n = np.asarray(normals, float).reshape(-1, 3)
    a1 = np.asarray(axes1, float).reshape(-1, 3)
    return Surfels(center=centers, normal=n, axis1=a1, axis2=np.cross(n, a1), extent=extents,
                   direction=np.full(len(n), direction), keyframe=np.full(len(n), keyframe))


# ----------------------------------------------------------------------------- explicit SDF


@pytest.fixture
def one_rect() -> Surfels:
    """A 2 x 1 rectangle in z = 0, normal +z, in a rotated and shifted frame (R, t applied)."""
    return rects([[0, 0, 0]], [[0, 0, 1]], [[1, 0, 0]], [[2.0, 1.0]])


CASES = [  # point (rectangle frame), sdf, gradient
    ((0.2, 0.1, 0.5), 0.5, (0, 0, 1)),  # in front
    ((0.2, 0.1, -0.3), -0.3, (0, 0, 1)),  # behind: negative, gradient towards free space
    ((1.5, 0.2, 0.0), 0.5, (1, 0, 0)),  # beside an edge, in the plane
    ((1.3, 0.9, 0.2), np.sqrt(0.3**2 + 0.4**2 + 0.2**2), np.array([0.3, 0.4, 0.2]) / np.sqrt(0.29)),  # corner
    ((1.3, 0.9, -0.2), -np.sqrt(0.29), -np.array([0.3, 0.4, -0.2]) / np.sqrt(0.29)),  # corner, behind
    ((-1.0, 0.5, 0.0), 0.0, (0, 0, 1)),  # on the corner itself
]


@pytest.mark.parametrize("p,sdf,grad", CASES)
def test_explicit_sdf_exact(one_rect: Surfels, p, sdf, grad) -> None:
    R = Rotation.from_rotvec([0.3, -0.7, 1.1]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    s = one_rect
    moved = Surfels(center=s.center @ R.T + t, normal=s.normal @ R.T, axis1=s.axis1 @ R.T, axis2=s.axis2 @ R.T,
                    extent=s.extent, direction=s.direction, keyframe=s.keyframe)
    d, g, idx = explicit_sdf((np.array(p) @ R.T + t)[None], moved)
    assert d[0] == pytest.approx(sdf, abs=1e-12)
    assert np.allclose(g[0], np.asarray(grad, float) @ R.T, atol=1e-9)
    assert idx[0] == 0
    du, _, _ = explicit_sdf((np.array(p) @ R.T + t)[None], moved, signed=False)
    assert du[0] == pytest.approx(abs(sdf), abs=1e-12)  # the paper's unsigned distance


def test_explicit_sdf_nearest_of_several() -> None:
    s = rects([[0, 0, 0], [0, 0, 1.0], [3, 0, 0]], [[0, 0, 1], [0, 0, -1], [-1, 0, 0]],
              [[1, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 1], [1, 1], [1, 1]])
    d, g, idx = explicit_sdf(np.array([[0, 0, 0.3], [0, 0, 0.8], [2.6, 0, 0.2], [10, 0, 0], [0, 0, 5]]), s)
    # the last two points are behind (outside) the wall at x = 3 and the ceiling at z = 1
    assert np.allclose(d, [0.3, 0.2, 0.4, -7.0, -4.0])
    assert list(idx) == [0, 1, 2, 2, 1]
    assert np.allclose(g[0], [0, 0, 1]) and np.allclose(g[1], [0, 0, -1]) and np.allclose(g[2], [-1, 0, 0])
    assert np.allclose(g[3], [-1, 0, 0]) and np.allclose(g[4], [0, 0, -1])  # towards free space
    empty, _, i = explicit_sdf(np.zeros((2, 3)), Surfels())
    assert np.all(np.isinf(empty)) and np.all(i == -1)


def test_explicit_sdf_pruning_matches_brute_force_and_timing() -> None:
    rng = np.random.default_rng(0)
    S = 300
    R = Rotation.random(S, random_state=1).as_matrix()
    surf = Surfels(center=rng.uniform(-5, 5, (S, 3)), normal=R[:, :, 0], axis1=R[:, :, 1], axis2=R[:, :, 2],
                   extent=rng.uniform(0.2, 2, (S, 2)), direction=np.zeros(S), keyframe=np.zeros(S))
    P = rng.uniform(-6, 6, (100_000, 3))
    sdf = ExplicitSdf(surf)
    t = time.perf_counter()
    d, g, idx = sdf(P)
    ms = 1e3 * (time.perf_counter() - t)
    brute = ExplicitSdf(surf, max_cell_pairs=10**12, chunk_pairs=200_000)  # every pair
    db, gb, ib = brute(P[:5000])
    assert np.allclose(d[:5000], db, atol=1e-6)
    assert np.mean(idx[:5000] == ib) > 0.999
    # numeric gradient of the signed field
    eps = 1e-6
    num = np.stack([(explicit_sdf(P[:200] + eps * e, surf)[0] - explicit_sdf(P[:200] - eps * e, surf)[0]) / (2 * eps)
                    for e in np.eye(3)], axis=1)
    assert np.allclose(num, g[:200], atol=1e-4)
    print(f"explicit_sdf: 100k points x {S} random surfels: {ms:.0f} ms")


# ----------------------------------------------------------------------------- global map


def test_merge_overlapping_coplanar() -> None:
    a = rects([[0, 0, 1.00]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]], keyframe=3)
    b = rects([[1.5, 0, 1.01]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]], keyframe=4)  # overlaps by 0.5, 1 cm higher
    m = GlobalSurfelMap()
    m.add(a)
    m.add(b)
    s = m.surfels()
    assert len(s) == 1 and m.n_produced == 2 and m.n_kept == 1
    assert np.allclose(s.extent[0], [3.5, 1.0])
    assert np.allclose(s.center[0], [0.75, 0, 1.005])  # area-weighted plane, union centre
    assert s.keyframe[0] == -1 and s.direction[0] == 0
    assert np.allclose(s.normal[0], [0, 0, 1])


@pytest.mark.parametrize("b,why", [
    (rects([[1.5, 0, 1.05]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]]), "plane 5 cm away"),
    (rects([[1.5, 0, 1.0]], [[0, 0, -1]], [[1, 0, 0]], [[2, 1]]), "opposite orientation"),
    (rects([[1.5, 0, 1.0]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]], direction=1), "another direction"),
    (rects([[3.0, 0, 1.0]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]]), "1 m gap"),
    (rects([[1.5, 1.0, 1.0]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]]), "union box poorly covered (L)"),
])
def test_no_merge(b: Surfels, why: str) -> None:
    m = GlobalSurfelMap()
    m.add(rects([[0, 0, 1.0]], [[0, 0, 1]], [[1, 0, 0]], [[2, 1]]))
    m.add(b)
    assert len(m) == 2, why


def test_merge_touching_and_chain() -> None:
    m = GlobalSurfelMap()
    for x in (0.0, 1.03, 2.06, 3.09):  # 1 m tiles with 3 cm gaps
        m.add(rects([[x, 0, 0]], [[0, 0, 1]], [[1, 0, 0]], [[1, 1]]))
    s = m.surfels()
    assert len(s) == 1 and np.allclose(s.extent[0], [4.09, 1.0])


def test_merge_tolerates_slightly_refined_directions() -> None:
    m = GlobalSurfelMap()
    m.add(rects([[0, 0, 0]], [[0, 0, 1]], [[1, 0, 0]], [[2, 2]]))
    R = Rotation.from_rotvec([0.01, 0.0, 0.01]).as_matrix()  # the frame refined by ~0.8 degrees
    m.add(rects([[1, 0, 0]], [[0, 0, 1] @ R.T], [[1, 0, 0] @ R.T], [[2, 2]]))
    assert len(m) == 1
    s = m.surfels()
    assert abs(s.center[0, 2]) < 0.01


@pytest.fixture(scope="module")
def sequence():
    """100 keyframes of the Atlanta room: per-keyframe surfels, noise-free surface points."""
    scene = atlanta_room(3)
    H, W = 120, 160
    K = camera(H)
    rng = np.random.default_rng(3)
    est = AtlantaEstimator()
    per_kf, surface = [], []
    for i, T in enumerate(trajectory(scene, 100, 3)):
        depth = scene.render(T, K, H, W, rng)
        kp = keyframe_points(depth, K, T)
        local = est.update(kp.normals_W, T)
        per_kf.append(extract_surfels(depth, K, T, local.frame, frame_id=i, points=kp)[0])
        gt = transform(T, backproject(scene.render(T, K, H, W, None), K)[::6, ::6].reshape(-1, 3))
        surface.append(gt[np.isfinite(gt).all(axis=1)])
    return scene, est, per_kf, np.vstack(surface)


def test_global_map_sequence(sequence) -> None:
    scene, est, per_kf, surface = sequence
    m = GlobalSurfelMap()
    t = time.perf_counter()
    for s in per_kf:
        m.add(s)
    ms = 1e3 * (time.perf_counter() - t) / len(per_kf)
    G, U = m.surfels(), Surfels.concat(per_kf)
    assert m.n_produced == len(U) and m.n_kept == len(G)
    # Merged surfels still lie on the true faces and planes.
    for k in range(len(G)):
        pts, _ = G[k: k + 1].sample_uniform(1000, np.random.default_rng(k))
        assert scene.on_any_face(pts, 0.03, 0.01).mean() >= 0.9
    # Planes: area-weighted tilt and offset of the surfels against their true faces.
    tilt_u, off_u = plane_errors(scene, U)
    tilt_g, off_g = plane_errors(scene, G)
    m.realign(est.frame)
    tilt_r, off_r = plane_errors(scene, m.surfels())
    # Explicit SDF at true surface points that per-keyframe surfels cover. (The union of
    # per-keyframe surfels takes the best of many overlapping copies at every point.)
    dg = np.abs(explicit_sdf(surface, G)[0])
    du = np.abs(explicit_sdf(surface, U)[0])
    near = du < 0.01
    print(f"global map: {len(U)} produced -> {len(G)} kept ({len(G) / len(U):.2f}), {ms:.1f} ms per keyframe; "
          f"area {U.area().sum():.0f} -> {G.area().sum():.0f} m^2; plane tilt / offset (area-weighted): "
          f"per-keyframe {tilt_u:.3f} deg / {1e3 * off_u:.2f} mm, global {tilt_g:.3f} deg / {1e3 * off_g:.2f} mm, "
          f"realigned {tilt_r:.3f} deg; |explicit sdf| at covered true surface: "
          f"per-keyframe {1e3 * du[near].mean():.1f} mm, "
          f"global {1e3 * dg[near].mean():.1f} mm")
    assert len(G) <= len(U) / 3
    assert tilt_g <= tilt_u and off_g <= off_u + 2e-4 and tilt_r <= tilt_g
    assert dg[near].mean() < 0.003
    assert np.mean(dg < 0.02) >= np.mean(near)  # covers as much of the surface (within the 2 cm plane bound)


def plane_errors(scene, s: Surfels) -> tuple[float, float]:
    """Area-weighted angle (deg) and centre offset (m) of surfels to their nearest true face planes."""
    R_SW = np.linalg.inv(scene.T_WS)[:3, :3]
    faces = scene.faces()
    tilt, off = [], []
    for k in range(len(s)):
        n, c = R_SW @ s.normal[k], scene.to_scene(s.center[k: k + 1])[0]
        f = max(faces, key=lambda f: n @ f["normal"] - 10 * abs(c @ f["normal"] - f["offset"]))
        tilt.append(np.degrees(np.arccos(min(1.0, n @ f["normal"]))))
        off.append(abs(c @ f["normal"] - f["offset"]))
    a = s.area()
    return float(np.sum(a * tilt) / a.sum()), float(np.sum(a * off) / a.sum())


def test_realign_and_state_round_trip(sequence) -> None:
    scene, est, per_kf, _ = sequence
    m = GlobalSurfelMap(SurfelMapConfig())
    for s in per_kf[:10]:
        m.add(s)
    before = m.surfels()
    m.realign(est.frame)
    after = m.surfels()
    f = est.frame
    for k in range(len(after)):
        v = f.direction(int(after.direction[k]))
        assert abs(abs(after.normal[k] @ v) - 1) < 1e-9
        assert after.normal[k] @ before.normal[k] > np.cos(np.radians(2))
    assert np.allclose(after.center, before.center)
    m2 = GlobalSurfelMap()
    m2.load_state_dict(m.state_dict())
    assert np.allclose(m2.surfels().center, after.center) and m2.n_produced == m.n_produced
