"""The Atlanta layout prior (aisdf.structure.layout): planes carried on into unobserved space
only, walls between the floor and the ceiling, a cabinet's face stopped where its top meets
it, and the served answer capped at the predicted surface (aisdf.query.answer)."""

import numpy as np

from aisdf.observed import ObservedGrid
from aisdf.query.answer import LAYOUT_SLACK, predicted_mask, served_answer
from aisdf.structure.layout import LayoutConfig, infer_vertical, planes, predict
from aisdf.structure.measured import MeasuredPoints
from aisdf.structure.surfel_types import Surfels

X, Y, Z = np.eye(3)
BOX = np.array([[-1.0, -1.0, -1.0], [5.0, 5.0, 4.0]])


def rect(center, normal, a1, a2, e1, e2, direction):
    return dict(center=center, normal=normal, axis1=a1, axis2=a2, extent=(e1, e2), direction=direction)


def room_surfels(cabinet_top: bool = True) -> Surfels:
    """A room seen for x in [0, 2]: its floor (z = 0) and ceiling (z = 2.6), the walls y = 0
    and y = 4, and a cabinet against the y = 4 wall (front y = 3.5, x in [0.2, 1.2], 1 m tall)
    with its top."""
    r = [rect((1, 2, 0), Z, X, Y, 2, 4, -1), rect((1, 2, 2.6), -Z, X, Y, 2, 4, -1),
         rect((1, 0, 1.3), Y, X, Z, 2, 2.6, 0), rect((1, 4, 1.3), -Y, X, Z, 2, 2.6, 0),
         rect((0.7, 3.5, 0.5), -Y, X, Z, 1.0, 1.0, 0)]
    if cabinet_top:
        r.append(rect((0.7, 3.75, 1.0), Z, X, Y, 1.0, 0.5, -1))
    return Surfels(**{k: np.array([np.asarray(x[k], float) for x in r]) for k in r[0]}, keyframe=np.zeros(len(r)))


def room_observed() -> ObservedGrid:
    """Observed space: x in [-0.2, 2] (rays, and 0.15 m behind the surfaces), less a pocket no
    camera saw: the cabinet behind its faces and the space above it, from 1.1 to 1.8 m."""
    voxel = 0.1
    origin = np.array([-0.2, -0.2, -0.2])
    shape = (30, 46, 32)
    c = origin + (np.argwhere(np.ones(shape, bool)) + 0.5) * voxel
    seen = (c[:, 0] < 2.0) & (c[:, 1] > -0.15) & (c[:, 1] < 4.15) & (c[:, 2] > -0.15) & (
        c[:, 2] < 2.75)
    x = (c[:, 0] > 0.2) & (c[:, 0] < 1.2)
    inside = (c[:, 1] > 3.6) & (c[:, 2] > 0.0) & (c[:, 2] < 0.9)  # the cabinet, behind its seen faces
    above = (c[:, 1] > 3.4) & (c[:, 2] > 1.1) & (c[:, 2] < 1.8)  # no camera looked over it
    pocket = x & (inside | above)
    return ObservedGrid(origin, voxel, (seen & ~pocket).reshape(shape))


def on_plane(p, normal, offset, tol=0.01):
    return np.abs(p @ normal - offset) < tol


def test_planes_group_surfels_by_direction_side_and_offset():
    s = room_surfels()
    ps = planes(s, 0.05)
    # floor, cabinet top (same side, 1 m apart), ceiling; y = 0, y = 4 wall and the cabinet front (3.5)
    assert len(ps) == 6
    areas = sorted(round(p.area, 3) for p in ps)
    assert areas == [0.5, 1.0, 5.2, 5.2, 8.0, 8.0]
    np.testing.assert_allclose(np.abs(infer_vertical(s)), Z, atol=1e-12)


def test_prediction_lies_only_in_unobserved_space_on_the_layout_planes():
    s, obs = room_surfels(), room_observed()
    p = predict(s, obs, BOX, Z)
    assert len(p) > 1000
    assert not obs.contains(p).any()  # observed space always wins
    floor, ceiling = on_plane(p, Z, 0.0), on_plane(p, Z, 2.6)
    wall0, wall4 = on_plane(p, Y, 0.0), on_plane(p, Y, 4.0)
    assert (floor | ceiling | wall0 | wall4).all()  # nothing else: no cabinet face, no cabinet top
    # A plane ends where the walls (seen, or predicted) meet it: nothing beyond them.
    assert p[:, 1].min() >= -0.05 - 1e-9 and p[:, 1].max() <= 4.05 + 1e-9
    # The floor carries on beyond the seen x <= 2, up to reach (1.5 m) beyond its surfel.
    assert floor.sum() > 500
    assert p[floor, 0].max() <= 3.5 + 0.05
    seen_x = floor & (p[:, 0] > 0) & (p[:, 0] < 2.0)  # only under the cabinet, which no camera saw
    assert seen_x.any() and (p[seen_x, 0] > 0.15).all() and (p[seen_x, 0] < 1.25).all() and (p[seen_x, 1] > 3.5).all()
    # Walls run from the floor to the ceiling, no farther.
    w = p[wall0 | wall4]
    assert w[:, 2].min() >= -0.05 - 1e-9 and w[:, 2].max() <= 2.65 + 1e-9
    # The wall behind the cabinet and above it, where no camera looked, is predicted; not where
    # the cabinet's top was seen (z 0.9 to 1.1).
    behind = p[wall4 & (p[:, 0] > 0.3) & (p[:, 0] < 1.1)]
    assert len(behind) > 200 and behind[:, 2].max() < 1.85
    assert not ((behind[:, 2] > 0.9) & (behind[:, 2] < 1.1)).any()


def test_a_cabinet_face_stops_where_its_top_meets_it():
    s, obs = room_surfels(cabinet_top=True), room_observed()
    front = lambda p: on_plane(p, Y, 3.5) & (p[:, 2] > 0.01) & (p[:, 2] < 2.59)  # not the floor's, the ceiling's
    assert not front(predict(s, obs, BOX, Z)).any()
    # Without its top, nothing says the face ends: it is carried up the unobserved pocket.
    bare = predict(room_surfels(cabinet_top=False), obs, BOX, Z)
    assert front(bare).sum() > 50 and bare[front(bare), 2].min() > 0.9


def test_nothing_is_predicted_without_observed_space_or_surfels():
    assert len(predict(room_surfels(), None, BOX)) == 0
    assert len(predict(Surfels(), room_observed(), BOX)) == 0
    # min_area: planes of less are not layout
    assert len(predict(room_surfels(), room_observed(), BOX, Z, LayoutConfig(min_area=100.0))) == 0


def test_served_answer_is_capped_at_the_predicted_floor():
    layout = MeasuredPoints(predict(room_surfels(), room_observed(), BOX, Z))
    q = np.array([[2.8, 2.0, 0.5],    # above the predicted floor, far from every surfel
                  [2.8, 2.0, 0.4],    # the network already says less than the cap
                  [2.8, 2.0, 0.3]])   # inside a surface by the network: left alone
    sdf_i = np.array([1.5, 0.2, -0.1], np.float32)
    grad_i = np.tile(np.float32([1, 0, 0]), (3, 1))
    f, g = served_answer(q, sdf_i, grad_i, None, None, None, layout=layout)
    assert abs(f[0] - (0.5 + LAYOUT_SLACK)) < 0.002
    np.testing.assert_allclose(g[0], Z, atol=0.08)
    assert f[1] == np.float32(0.2) and f[2] == np.float32(-0.1)
    np.testing.assert_array_equal(g[1:], grad_i[1:])
    np.testing.assert_array_equal(predicted_mask(layout, q, f), [True, False, False])
    f0, _ = served_answer(q, sdf_i, grad_i, None, None, None)
    np.testing.assert_array_equal(f0, sdf_i)  # no layout: the network's


def test_a_wall_seen_only_in_a_corner_still_bounds_the_room():
    """A wall a camera framed only at its edge (0.3 x 0.6 m of surfels, 0.18 m^2) is carried on
    into the space beyond the seen x <= 2 as the big walls are; a plane needs 0.1 m^2 of surfels
    (a 0.5 m^2 bar left most of a room's walls out of the layout on a walk that saw them in
    pieces)."""
    r = room_surfels(cabinet_top=True)
    keep = ~((np.abs(r.center[:, 1] - 4.0) < 1e-9) & (np.abs(r.normal[:, 1] + 1) < 1e-9))
    small = rect((1.85, 4.0, 1.3), -Y, X, Z, 0.3, 0.6, 0)
    s = Surfels(**{k: np.concatenate([getattr(r, k)[keep], np.asarray([small[k]], float)])
                   for k in small}, keyframe=np.zeros(int(keep.sum()) + 1))
    assert round(min(p.area for p in planes(s, 0.05) if abs(p.normal @ Y) > 0.9), 3) == 0.18
    wall4 = lambda p: on_plane(p, Y, 4.0) & (p[:, 0] > 2.0) & (p[:, 2] > 0.01) & (p[:, 2] < 2.59)
    p = predict(s, room_observed(), BOX, Z)
    assert wall4(p).sum() > 600 and p[wall4(p), 0].max() <= 3.5 + 0.05
    assert not wall4(predict(s, room_observed(), BOX, Z, LayoutConfig(min_area=0.5))).any()
