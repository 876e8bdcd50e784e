"""Layout and furniture labels of the built-in buildings (``Scene.kinds``): every box is
labelled, the walls of the floor are the only layout boxes, and the distance to the furniture
alone is exact (checked against every furniture box's own distance, point by point)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from aisdf.synthetic import BUILDINGS, Boxes, Room, Scene, make_building
from aisdf.synthetic.scene import LAYOUT_KINDS, ROOM_KIND

FURNITURE_KINDS = {"table", "chair", "shelf", "cabinet", "box", "stairs"}
N_BOXES = {"manhattan": 29, "atlanta": 21, "stairs": 15, "office": 34, "floor": 156}  # unchanged by the labels


@pytest.mark.parametrize("name", list(BUILDINGS))
def test_every_box_is_labelled_and_every_building_has_furniture(name):
    s = make_building(name, 0)
    assert len(s.boxes) == N_BOXES[name] and len(s.kinds) == len(s.boxes)
    kinds = Counter(s.kinds)
    assert set(kinds) <= FURNITURE_KINDS | LAYOUT_KINDS
    assert kinds["table"] >= 5 and kinds["box"] >= 2  # a table (top and four legs) and boxes in every building
    assert s.furniture_mask.sum() == len(s.boxes) - kinds["wall"]
    assert s.with_frame(np.eye(4)).kinds == s.kinds  # placing it elsewhere keeps them
    if name == "stairs":
        assert kinds["stairs"] == 8  # seven steps and the landing: not part of a room layout


def test_the_floors_walls_are_layout_and_nothing_else_is():
    s = make_building("floor", 0, "identity")
    k = np.array(s.kinds)
    top = s.boxes.centers[:, 2] + s.boxes.halves[:, 2]
    assert (k[np.isclose(top, s.room.height)] == "wall").all()  # whatever reaches the ceiling is a wall
    walls = s.boxes.halves[k == "wall"] * 2
    assert len(walls) == 22 and np.allclose(np.sort(walls, axis=1)[:, 0], 0.12)  # 12 cm thick, lintels included
    for name in ("manhattan", "atlanta", "stairs", "office"):
        assert "wall" not in make_building(name, 0).kinds


def _brute(scene: Scene, p_canon: np.ndarray):
    """Every primitive's own signed distance: (nearest primitive's kind, distance to furniture)."""
    d = np.c_[scene.boxes.sdf(p_canon), scene.room.sdf_grad(p_canon)[0]]
    labels = np.array(list(scene.kinds) + [ROOM_KIND], dtype=object)
    furn = scene.furniture_mask
    return labels[np.argmin(d, axis=1)], d[:, :-1][:, furn].min(axis=1)


@pytest.mark.parametrize("name", ["manhattan", "stairs", "floor"])
def test_furniture_distance_and_nearest_kind_match_every_primitive(name):
    s = make_building(name, 1)  # tilted: world points in, canonical geometry inside
    lo, hi = s.room.polygon.min(axis=0), s.room.polygon.max(axis=0)
    rng = np.random.default_rng(3)
    p = np.c_[rng.uniform(lo - 0.3, hi + 0.3, (3000, 2)), rng.uniform(-0.2, s.room.height + 0.2, 3000)]
    kind, dist = _brute(s, p)
    W = s.to_world(p)
    np.testing.assert_allclose(s.furniture_distance(W), dist, atol=1e-9)
    assert (s.nearest_kind(W) == kind).all()
    want = np.array([k != ROOM_KIND and k not in LAYOUT_KINDS for k in kind])
    assert (s.nearest_is_furniture(W) == want).all() and 0.05 < want.mean() < 0.95


def test_a_point_on_a_chair_is_near_furniture_the_centre_of_an_empty_wall_is_not():
    s = make_building("manhattan", 0)
    k = np.array(s.kinds)
    seat = int(np.flatnonzero(k == "chair")[0])  # the first chair box is its seat
    c, h = s.boxes.centers[seat], s.boxes.halves[seat]
    on_seat = c + [0.0, 0.0, h[2] + 0.01]  # 1 cm above the seat
    in_leg = s.boxes.centers[seat + 1]  # the middle of a leg
    wall = np.array([0.05, 2.5, 1.35])  # 5 cm from the middle of the x = 0 wall (nothing stands there)
    W = s.to_world(np.stack([on_seat, in_leg, wall]))
    d = s.furniture_distance(W)
    assert d[0] == pytest.approx(0.01, abs=1e-9) and d[1] < 0 and d[2] > 1.0
    assert list(s.nearest_kind(W)) == ["chair", "chair", ROOM_KIND]
    assert list(s.nearest_is_furniture(W)) == [True, True, False]


def test_unlabelled_and_empty_scenes():
    room = Room(np.array([[0, 0], [4, 0], [4, 3], [0, 3]], dtype=float), 2.5)
    cube = Boxes([[2.0, 1.5, 0.5]], [np.eye(3)], [[0.5, 0.5, 0.5]])
    p = np.array([[1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="no labels"):
        Scene(room, cube).furniture_distance(p)
    with pytest.raises(ValueError, match="one label per box"):
        Scene(room, cube, kinds=("box", "chair"))
    walls_only = Scene(room, cube, kinds=("wall",))
    assert walls_only.furniture_distance(p)[0] == np.inf and not walls_only.nearest_is_furniture(p)[0]
    assert Scene(room, cube, kinds=("box",)).furniture_distance(p)[0] == pytest.approx(0.5)
