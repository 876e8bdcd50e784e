"""The multi-room floor: exact SDF (walls, door openings, furniture), named room regions,
and the walk through every room (collision free, at 30 fps and at one keyframe a second)."""

from __future__ import annotations

import numpy as np
import pytest

from aisdf.geometry import backproject, transform
from aisdf.synthetic import PLANS, SyntheticSequence, make_building
from aisdf.synthetic.buildings import WING_DEG, floor_plan
from aisdf.synthetic.primitives import polygon_area, polygon_contains

ROOMS = [f"room{k}" for k in range(1, 8)]


@pytest.fixture(scope="module")
def canon():
    return make_building("floor", 0, "identity")  # world = canonical frame


@pytest.fixture(scope="module")
def tilted():
    return make_building("floor", 0)  # an arbitrary world frame


def test_footprint_regions_and_directions(canon):
    plan = floor_plan()
    assert plan.names == ["corridor", *ROOMS]
    lo, hi = canon.room.polygon.min(axis=0), canon.room.polygon.max(axis=0)
    assert 23.0 < hi[0] - lo[0] < 25.0 and 13.5 < hi[1] - lo[1] < 15.0  # about 24 x 14.4 m
    # The regions tile the footprint: areas add up, every inside point is in exactly one.
    areas = {k: polygon_area(v) for k, v in plan.regions.items()}
    assert all(a > 0 for a in areas.values())  # counter-clockwise
    assert sum(areas.values()) == pytest.approx(polygon_area(canon.room.polygon), rel=1e-9)
    g = np.stack(np.meshgrid(np.linspace(0.05, 24.25, 200), np.linspace(0.05, 14.3, 120)), -1).reshape(-1, 2)
    inside = polygon_contains(g, canon.room.polygon)
    hits = np.stack([polygon_contains(g, p) for p in plan.regions.values()])
    assert np.all(hits[:, inside].sum(axis=0) == 1) and not hits[:, ~inside].any()
    assert all(12.0 < areas[r] < 45.0 for r in ROOMS)
    # Wall directions: the main wing's 0/90 and the wing's 42/132 degrees.
    vert, hor = canon.atlanta_truth(include_solids=False)
    ang = np.sort(np.degrees(np.arctan2(hor[:, 1], hor[:, 0])) % 180)
    np.testing.assert_allclose(ang, np.sort([0.0, 90.0, WING_DEG, WING_DEG + 90.0]), atol=1e-6)
    assert np.all(canon.planes_truth().direction > -2)  # furniture aligned with some wall


def test_sdf_exact_at_known_points(canon, tilted):
    P = np.array([
        [7.0, 5.5, 1.35],   # corridor centre, solid walls either side: 1 m to both
        [7.0, 5.5, 0.4],    # nearer the floor
        [6.0, 4.44, 1.0],   # inside room 2's door opening (in the wall's thickness): 0.5 m to the jambs
        [6.0, 4.5, 1.9],    # under the lintel: 0.2 m to it
        [7.0, 4.5, 1.0],    # on the corridor face of a wall
        [7.0, 4.44, 1.0],   # inside the wall (12 cm thick, on the room side of y = 4.5)
        [7.0, 4.0, 2.2],    # room 2, 38 cm in front of the wall, near the ceiling
    ])
    want = np.array([1.0, 0.4, 0.5, 0.2, 0.0, -0.06, 0.38])
    np.testing.assert_allclose(canon.sdf(P), want, atol=1e-9)
    np.testing.assert_allclose(tilted.sdf(tilted.to_world(P)), want, atol=1e-9)  # same in any world frame
    # Door openings are free all the way through; walls next to them are not.
    plan = floor_plan()
    for v in plan.visits:
        axis = (v.look - v.corridor) / np.linalg.norm(v.look - v.corridor)
        line = v.door + np.linspace(-0.3, 0.3, 13)[:, None] * axis
        through = np.c_[line, np.full(len(line), 1.2)]
        assert np.all(canon.sdf(through) > 0.45), v.room
        beside = np.r_[v.door + 0.8 * np.array([-axis[1], axis[0]]) + 0.06 * axis, 1.2][None]
        assert canon.sdf(beside)[0] < 0, v.room  # 0.8 m sideways from the door's centre: in the wall
    # Furniture: 2 cm above the top face of every solid lower than 1.5 m is 2 cm from it
    # (or inside what stands on it: a table top on its legs, a box on a box).
    b = canon.boxes
    low = (b.centers[:, 2] + b.halves[:, 2]) < 1.5
    top = b.centers[low] + np.c_[0 * b.halves[low][:, :2], b.halves[low][:, 2] + 0.02]
    d = canon.sdf(top)
    exact = np.abs(d - 0.02) < 1e-9
    assert np.all(exact | (d < 0)) and exact.sum() >= 30
    reg = plan.region_of(b.centers[low][:, :2])
    for r in ROOMS:
        assert np.sum(reg == plan.names.index(r)) >= 3, f"{r} has almost no furniture"


def test_sdf_is_the_distance_to_the_nearest_surface(tilted):
    """Random free points: no surface is nearer than the SDF in any direction, and the
    surface along minus the gradient is exactly that far."""
    rng = np.random.default_rng(0)
    c = np.c_[rng.uniform([0, 0], [24.3, 14.4], (4000, 2)), rng.uniform(0.05, 2.65, 4000)]
    p = tilted.to_world(c)
    d, g = tilted.sdf_and_gradient(p)
    p, d, g = p[d > 0.01][:300], d[d > 0.01][:300], g[d > 0.01][:300]
    assert len(p) == 300
    np.testing.assert_allclose(tilted.raycast(p, -g), d, atol=1e-7)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for k in range(len(dirs)):
        t = tilted.raycast(p, np.broadcast_to(dirs[k], p.shape))
        assert np.all(t >= d - 1e-9)


@pytest.fixture(scope="module")
def walk30():
    return SyntheticSequence("floor", n_frames=6000, fps=30.0, noise=False)


def test_walk_collision_free_smooth_and_every_room_visited(walk30):
    seq = walk30
    s, plan = seq.scene, seq.plan
    assert 190.0 < seq.walk_s < 200.0  # 200 keyframes at 1 Hz cover it
    c = seq.poses[:, :3, 3]
    assert s.sdf(c).min() > 0.2
    h = (c - s.to_world(np.zeros((1, 3)))) @ s.up_W
    assert h.min() > 1.2 and h.max() < 1.5
    R = seq.poses[:, :3, :3]
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    rate = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))) * seq.fps
    assert rate.max() <= 50.0
    assert np.all(R[:, :, 1] @ -s.up_W > 0.85) and np.all(R[:, :, 2] @ -s.up_W > 0)  # upright, looking down
    speed = np.linalg.norm(np.diff(c, axis=0), axis=1) * seq.fps
    assert speed.max() < 0.7
    # Every room visited once, in order, for a while; the camera is in the room meanwhile.
    order = [v.room for v in plan.visits]
    assert sorted(order) == ROOMS and list(seq.visits) == order
    spans = np.array([seq.visits[r] for r in order])
    assert np.all(spans[:, 1] - spans[:, 0] > 12.0) and np.all(spans[1:, 0] > spans[:-1, 1])
    t = np.arange(len(seq)) / seq.fps
    where = seq.region_of(c)
    for k, r in enumerate(order):
        inside = (t > spans[k, 0] + 0.1) & (t < spans[k, 1] - 0.1)
        assert np.all(where[inside] == plan.names.index(r))
    assert np.all(where[t > spans[-1, 1] + 0.1] == 0)  # back in the corridor at the end
    # Frames held after the end of the walk.
    tail = SyntheticSequence("floor", n_frames=210, fps=1.0, noise=False)
    np.testing.assert_allclose(tail.poses[205], tail.poses[200])


def test_one_keyframe_a_second_sees_each_room_while_visiting():
    seq = SyntheticSequence("floor", n_frames=200, fps=1.0, H=60, W=80)
    assert len(seq) == 200 and seq.frame(199)["stamp"] == 199.0
    for r, (t0, t1) in seq.visits.items():
        ids = [i for i in range(len(seq)) if t0 <= i <= t1]
        assert len(ids) >= 12, r
        pts = []
        for i in ids[::3]:
            f = seq.frame(i)
            P = backproject(f["depth"], f["K"]).reshape(-1, 3)
            pts.append(transform(f["T_WC"], P[np.isfinite(P[:, 0])]))
        where = seq.region_of(np.concatenate(pts))
        assert np.mean(where == seq.plan.names.index(r)) > 0.5, r  # mostly looking around that room


def test_floor_registered_for_the_demo_and_the_bench():
    assert "floor" in PLANS
    from aisdf.bench.scenes import SCENES, make_scene

    assert "floor" in SCENES
    sc = make_scene("floor", {"n_frames": 20, "H": 30, "W": 40})
    assert sc.gt_kind == "exact" and len(sc) == 20 and sc.frames.plan is not None
    f = sc.frames.frame(19)
    assert f["depth"].shape == (30, 40)
