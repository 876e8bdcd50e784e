"""Free space clears (aisdf.mapper.clearing): what newer depth rays pass through is retired
from the measured points, the stored keyframes' pixels and the global surfels; a static
scene keeps its surfaces."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from aisdf.mapper import clearing
from aisdf.mapper.single import MappingPipeline
from aisdf.mapping.frames import Frame
from aisdf.submaps.pipeline import SubmapPipeline
from aisdf.synthetic import SyntheticSequence
from aisdf.synthetic.primitives import Boxes
from aisdf.synthetic.render import render_depth

H, W, EVERY = 120, 160, 30
K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])


def _wall(z: float = 3.0, hole: tuple | None = None) -> np.ndarray:
    d = np.full((H, W), z, np.float32)
    if hole is not None:
        d[hole] = 0.0
    return d


def test_a_point_in_front_of_the_measured_surface_is_passed_through_beyond_the_noise():
    ev = clearing.FreeSpace(_wall(3.0, hole=(slice(0, 10), slice(0, 10))), K, np.eye(4))
    # on the optical axis: free at 2 m, not within margin + 3 sigma of the wall (3 sigma at 3 m = 4.3 cm),
    # not on or behind the wall, nothing behind the camera or outside the image, nothing next to a hole
    pts = np.array([[0, 0, 2.0], [0, 0, 2.95], [0, 0, 2.9], [0, 0, 3.0], [0, 0, 3.5], [0, 0, -2.0],
                    [5.0, 0, 2.0], [(2 - 80) / 100 * 2.0, (2 - 60) / 100 * 2.0, 2.0]])
    assert ev.passed(pts).tolist() == [True, False, True, False, False, False, False, False]
    tau = 0.05 + 3 * clearing.depth_sigma(3.0)
    assert ev.passed(np.array([[0, 0, 3.0 - tau - 0.002], [0, 0, 3.0 - tau + 0.002]])).tolist() == [True, False]
    # the same in a moved camera: world points through T_WC
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    assert clearing.FreeSpace(_wall(3.0), K, T).passed(np.array([[1.0, 2.0, 5.0], [1.0, 2.0, 6.0]])).tolist() == [
        True, False]


def test_a_depth_edge_does_not_clear_the_nearer_surface_beside_it():
    d = _wall(4.0)
    d[:, :80] = 1.0  # a near surface on the left half
    ev = clearing.FreeSpace(d, K, np.eye(4))
    # a point on the near surface, right at the edge: its pixel may look past the edge, the window does not
    x = (79.6 - 80) / 100 * 1.0
    assert not ev.passed(np.array([[x, 0.0, 1.0]]))[0]
    assert ev.passed(np.array([[(100 - 80) / 100 * 2.0, 0.0, 2.0]]))[0]


def test_a_window_in_degrees_covers_a_pose_s_angular_error_at_a_depth_edge():
    d = _wall(4.0)
    d[:, :80] = 1.0  # a near surface on the left half
    # a point of the near surface seen from a pose 1.1 degrees off: it lands 2 pixels past the edge
    p = np.array([[(82 - 80) / 100 * 1.0, 0.0, 1.0]])
    assert clearing.window_radius(W, K) == 1 and clearing.window_radius(W, K, 2.0) == 4  # tan(2 deg) x 100 px
    assert clearing.window_radius(640, np.diag([585.0, 585.0, 1.0]), 0.5) == 6
    assert clearing.FreeSpace(d, K, np.eye(4)).passed(p)[0]  # the pixel window: cleared
    assert not clearing.FreeSpace(d, K, np.eye(4), window_deg=2.0).passed(p)[0]
    # a point well clear of the edge is still passed through
    assert clearing.FreeSpace(d, K, np.eye(4), window_deg=2.0).passed(np.array([[(100 - 80) / 100 * 2.0, 0, 2.0]]))[0]


def _person_then_table(band: bool = True):
    """A person (rows 40-57, 1.6 m) in front of a wall (3 m), then the same view without
    them: a table top's edge at row 60 (2 m below it), and, as depth cameras do, a band of
    dropped pixels (rows 57-59) along the edge."""
    before = _wall(3.0)
    before[40:58, 60:100] = 1.6
    before[60:, :] = 2.0
    after = _wall(3.0)
    after[60:, :] = 2.0
    if band:
        after[57:60, :] = 0.0
    return before, after


def test_a_window_with_the_hole_band_of_a_depth_edge_clears_the_measured_points_but_not_pixels():
    from aisdf.structure.measured import MeasuredSurface
    _, after = _person_then_table()
    ev = clearing.FreeSpace(after, K, np.eye(4))
    # rows 56 (own pixel measured, 6 of 9 of its window), 58 (own pixel a hole), 61 (the table)
    pts = np.array([[0.0, (56 - 60) / 100 * 1.6, 1.6], [0.0, (58 - 60) / 100 * 1.6, 1.6],
                    [0.0, (61 - 60) / 100 * 2.0, 2.0]])
    assert ev.passed(pts, holes=True).tolist() == [True, False, False]
    assert ev.passed(pts).tolist() == [False, False, False]  # pixels and surfels: strict
    before, after = _person_then_table()
    m = MeasuredSurface(min_hits=1)
    m.add(before, K, np.eye(4))
    person = lambda P: np.abs(P[:, 2] - 1.6) < 0.05  # noqa: E731
    assert person(_measured_points(m)).sum() >= 8
    keys, pts, solid = clearing.clear_measured(m, clearing.FreeSpace(after, K, np.eye(4)), passes=1)
    assert person(pts).all() and person(_measured_points(m)).sum() == 0  # every person voxel, nothing else
    # without the band every window is whole: the same voxels go, and all of them are news
    m2 = MeasuredSurface(min_hits=1)
    m2.add(before, K, np.eye(4))
    keys2, _, solid2 = clearing.clear_measured(m2, clearing.FreeSpace(_person_then_table(band=False)[1], K, np.eye(4)),
                                               passes=1)
    assert keys2.tolist() == keys.tolist() and solid2 == len(keys2)
    assert solid < solid2  # the voxels only a window with holes passes are not news


def test_a_measured_point_goes_after_two_keyframes_in_a_row_pass_through_it_and_one_that_sees_it_resets_the_count():
    from aisdf.structure.measured import MeasuredSurface
    before, after = _person_then_table(band=False)
    m = MeasuredSurface(min_hits=1)
    m.add(before, K, np.eye(4))
    n = len(m)
    person = lambda P: np.abs(P[:, 2] - 1.6) < 0.05  # noqa: E731
    n_person = int(person(_measured_points(m)).sum())
    gone_ev, seen_ev = clearing.FreeSpace(after, K, np.eye(4)), clearing.FreeSpace(before, K, np.eye(4))
    # one view through the person's place: counted, nothing removed
    keys, _, solid = clearing.clear_measured(m, gone_ev)
    assert len(keys) == 0 and solid == 0 and len(m) == n
    assert int((m.misses == 1).sum()) == n_person and int(m.misses.max()) == 1
    # a view that measures the person again resets the count; the wall behind it is not touched
    clearing.clear_measured(m, seen_ev)
    assert int(m.misses.max()) == 0
    clearing.clear_measured(m, gone_ev)
    assert len(m) == n  # one miss again, not two
    keys, pts, solid = clearing.clear_measured(m, gone_ev)  # the second in a row
    assert person(pts).all() and len(pts) == n_person and solid == n_person
    assert len(m) == n - n_person and int(m.misses.max()) == 0
    # the count lives in the checkpoint; an older one without it starts at 0
    m.add(before, K, np.eye(4))
    clearing.clear_measured(m, gone_ev)
    st = m.state_dict()
    assert MeasuredSurface.from_state_dict(st).misses.tolist() == m.misses.tolist() and m.misses.max() == 1
    del st["misses"]
    assert MeasuredSurface.from_state_dict(st).misses.max() == 0
    with pytest.raises(ValueError):
        MeasuredSurface.from_state_dict({**m.state_dict(), "misses": m.misses[:-1]})


def _cart_scenes(seed: int = 0):
    seq = SyntheticSequence(building="office", n_frames=600, H=H, W=W, seed=seed)
    sc = seq.scene
    T = seq.poses[300]
    p = sc.T_canon_W[:3, :3] @ (T[:3, 3] + 2.0 * T[:3, 2]) + sc.T_canon_W[:3, 3]
    centre, half = np.array([p[0], p[1], 0.5]), np.array([0.4, 0.3, 0.5])
    cart = replace(sc, boxes=Boxes(np.concatenate([sc.boxes.centers, centre[None]]),
                                   np.concatenate([sc.boxes.rotations, np.eye(3)[None]]),
                                   np.concatenate([sc.boxes.halves, half[None]])),
                   kinds=None if sc.kinds is None else (*sc.kinds, "cart"))

    def phantom(P: np.ndarray) -> np.ndarray:
        """Points on the cart's surface (within 5 cm of its box, above the floor) that no
        surface of the scene without the cart explains."""
        q = (P - sc.T_W_canon[:3, 3]) @ sc.T_W_canon[:3, :3]
        return np.all(np.abs(q - centre) <= half + 0.05, axis=1) & (q[:, 2] > 0.05) & (np.abs(sc.sdf(P)) > 0.05)

    return seq, sc, cart, phantom


def _walk(mapper, seq, scene, offset: int) -> None:
    for i in range(0, 600, EVERY):
        d = render_depth(scene, seq.poses[i], seq.K, H, W, seq.noise, (0, i + offset))
        mapper.add_keyframe(Frame(i + offset, i / 30, d, seq.K.copy(), seq.poses[i].copy()))


def _frames(mapper) -> list[Frame]:
    return mapper.keyframes if hasattr(mapper, "keyframes") else mapper.trainer.keyframes


def _measured_points(m) -> np.ndarray:
    return m.sums / m.counts[:, None]


@pytest.mark.parametrize("kind", ["submaps", "single"])
def test_a_cart_taken_away_is_cleared_from_the_measured_points_pixels_and_surfels(kind):
    seq, sc, cart, phantom = _cart_scenes()
    mapper = SubmapPipeline.from_settings("cpu") if kind == "submaps" else MappingPipeline.from_settings("cpu")
    _walk(mapper, seq, cart, 0)
    m = mapper.measured
    before = int(phantom(_measured_points(m)).sum())
    surf_before = int(phantom(mapper.structure.map.surfels().center).sum())
    # measured 2026-12-05: 258 points and 6 surfels of the cart
    assert before > 100 and surf_before >= 2, (before, surf_before)
    stored = {k: np.count_nonzero(f.metres()) for k, f in ((f.key, f) for f in _frames(mapper))}
    _walk(mapper, seq, sc, 1000)  # the same walk, the cart gone
    after = int(phantom(_measured_points(m)).sum())
    assert after <= 5, (before, after)  # measured: 2
    assert int(phantom(mapper.structure.map.surfels().center).sum()) == 0
    c = mapper.intake.cleared
    assert c["pixels"] > 1000 and c["keyframes"] > 0 and c["surfels"] >= surf_before, c
    # the first walk's keyframes lost the cart's pixels (depth 0), in the arrays training reads
    lost = [k for k, f in ((f.key, f) for f in _frames(mapper)) if k in stored
            and np.count_nonzero(f.metres()) < stored[k]]
    assert lost
    for f in _frames(mapper):
        if f.key in stored:
            d = f.metres()
            v, u = np.nonzero(d > 0)
            D = d[v, u].astype(np.float64)
            P = np.stack([(u - f.K[0, 2]) / f.K[0, 0] * D, (v - f.K[1, 2]) / f.K[1, 1] * D, D], -1)
            P = P @ f.T_WC[:3, :3].T + f.T_WC[:3, 3]
            assert int(phantom(P).sum()) <= 0.02 * max(1, len(P)), f.key
    assert mapper.stats()["cleared_measured"] == c["measured"]


def test_a_static_scene_walked_again_keeps_its_surfaces_and_stores_no_more_keyframes_than_without_clearing():
    seq, sc, cart, phantom = _cart_scenes()
    on, off = SubmapPipeline.from_settings("cpu"), SubmapPipeline.from_settings(
        "cpu", keyframes={"clear_free_space": False})
    for mapper in (on, off):
        _walk(mapper, seq, cart, 0)
        _walk(mapper, seq, cart, 1000)  # the cart stays
    # what clearing removes in a static scene is depth noise: points off every true surface
    kept = _measured_points(on.measured)
    assert int(phantom(kept).sum()) >= 0.8 * int(phantom(_measured_points(off.measured)).sum())
    removed = len(off.measured) - len(on.measured)
    assert 0 <= removed <= 0.02 * len(off.measured), (removed, len(off.measured))  # measured: 0.8 %
    assert on.intake.cleared["surfels"] == 0
    assert abs(len(on.frames) - len(off.frames)) <= 2, (len(on.frames), len(off.frames))
    assert on.intake.cleared["pixels"] <= 0.002 * sum(np.count_nonzero(f.metres()) for f in on.keyframes)


def test_a_keyframe_at_a_stored_pose_that_clears_something_is_stored_not_redundant():
    seq, sc, cart, phantom = _cart_scenes()
    mapper = SubmapPipeline.from_settings("cpu")
    i = 300
    T = seq.poses[i]
    mapper.add_keyframe(Frame(1, 0.0, render_depth(cart, T, seq.K, H, W, seq.noise, (0, 1)), seq.K.copy(), T.copy()))
    # the same pose, the cart still there: redundant
    assert not mapper.add_keyframe(Frame(2, 1.0, render_depth(cart, T, seq.K, H, W, seq.noise, (0, 2)), seq.K.copy(),
                                         T.copy()))
    # the same pose, the cart gone: the first view counts a miss (and is stored for the wall it
    # sees behind the cart); the second, at the pose of that stored one, clears the cart: news
    gone = [Frame(k, k - 1.0, render_depth(sc, T, seq.K, H, W, seq.noise, (0, k)), seq.K.copy(), T.copy())
            for k in (3, 4)]
    assert mapper.add_keyframe(gone[0]) and mapper.intake.cleared["measured"] == 0
    assert mapper.add_keyframe(gone[1])
    assert mapper.intake.cleared["measured"] > 0


def test_a_submap_whose_measured_points_were_cleared_is_published_again_without_training():
    seq, sc, cart, phantom = _cart_scenes()
    mapper = SubmapPipeline.from_settings("cpu")
    _walk(mapper, seq, cart, 0)
    mapper.map_messages(1)  # everything published once
    assert [k for k, _ in mapper.map_messages(2) if k.startswith("map/submaps/")] == []
    T = seq.poses[300]
    for k in (5000, 5001):  # two views in a row through the cart's place
        mapper.add_keyframe(Frame(k, k / 100, render_depth(sc, T, seq.K, H, W, seq.noise, (0, k)), seq.K.copy(),
                                  T.copy()))
    assert mapper.intake.cleared["measured"] > 0
    out = [k for k, _ in mapper.map_messages(3) if k.startswith("map/submaps/")]
    assert out, "the submaps holding the cleared points were not published"
