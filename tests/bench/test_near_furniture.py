"""Table I's near-furniture split: which points are near furniture (by the buildings' labels,
checked against every primitive's own distance), the errors there and away from it, n/a for
scenes without labels, and the rows the tables print."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from aisdf.bench.evaluation import NEAR_FURNITURE_M, EvalSet, labelled_building, near_furniture_mask
from aisdf.bench.report import table1, table1c
from aisdf.bench.scenes import make_scene


@pytest.fixture(scope="module")
def evalset():
    sc = make_scene("stairs", {"n_frames": 30, "H": 30, "W": 40})
    frames = [sc.frames.frame(i) for i in range(0, len(sc), 5)]
    return sc, EvalSet(sc, frames, 3_000, 0, split=True)


def _by_label(building, points_W):
    """Near furniture from every primitive's own signed distance (not the scene's code)."""
    p = building.to_canon(points_W)
    d = np.c_[building.boxes.sdf(p), building.room.sdf_grad(p)[0]]
    furn = np.r_[building.furniture_mask, False]  # the room prism is layout
    return furn[np.argmin(d, axis=1)] | (d[:, :-1][:, furn[:-1]].min(axis=1) <= NEAR_FURNITURE_M)


def test_near_furniture_points_are_what_the_labels_say(evalset):
    sc, es = evalset
    b = sc.frames.scene
    want = _by_label(b, es.points)
    assert es.near_furniture is not None and (es.near_furniture == want).all()
    assert 0.06 < want.mean() < 0.54  # the staircase, the table and two boxes: 0.179 measured on these frames
    # a point 1 cm above the first step is near furniture; 5 cm from the middle of the y = 4 wall it is not
    step = int(np.flatnonzero(np.array(b.kinds) == "stairs")[0])
    c, h = b.boxes.centers[step], b.boxes.halves[step]
    pts = b.to_world(np.array([c + [0, 0, h[2] + 0.01], [3.5, 3.95, 2.0]]))
    assert list(near_furniture_mask(b, pts)) == [True, False]


def test_split_scores_near_and_away(evalset):
    sc, es = evalset
    near = es.near_furniture
    exact = es.score(lambda p, g: (sc.gt_sdf(p), sc.gt_grad(p)))
    assert exact["sdf_error_near_furniture_cm"] == 0 and exact["sdf_error_away_from_furniture_cm"] == 0
    assert exact["near_furniture_share"] == pytest.approx(near.mean())
    assert exact["near_furniture_unobserved_share"] == pytest.approx((near & ~es.observed).mean())
    # a field 10 cm off near furniture only: 10 cm there, 0 away, the mean weighted by the share
    off = es.score(lambda p, g: (sc.gt_sdf(p) + 0.1 * near, sc.gt_grad(p)))
    assert off["sdf_error_near_furniture_cm"] == pytest.approx(10.0)
    assert off["sdf_error_away_from_furniture_cm"] == pytest.approx(0.0)
    assert off["sdf_error_near_furniture_unobserved_cm"] == pytest.approx(10.0)
    assert off["sdf_error_cm"] == pytest.approx(10.0 * near.mean())


def test_scenes_without_labels_have_no_split():
    assert labelled_building(SimpleNamespace(frames=SimpleNamespace())) is None  # a mesh or a reference
    unlabelled = SimpleNamespace(frames=SimpleNamespace(scene=SimpleNamespace(kinds=None)))
    assert labelled_building(unlabelled) is None


def _metrics(sdf, near=None, away=None):
    m = {"sdf_error_cm": sdf, "collision_cost_error": 0.01, "gradient_cosine_distance": 0.1, "n_points": 100,
         "observed_share": 0.9, "unobserved_share": 0.1, "sdf_error_observed_cm": sdf, "sdf_error_unobserved_cm": sdf}
    if near is not None:
        m.update(near_furniture_share=0.4, sdf_error_near_furniture_cm=near, sdf_error_away_from_furniture_cm=away,
                 near_furniture_unobserved_share=0.05, sdf_error_near_furniture_unobserved_cm=2 * near)
    return m


def test_tables_print_the_near_furniture_rows():
    methods = ["voxel-5cm", "aisdf-served"]
    scene = lambda final, kind: {"ground_truth": "gt", "gt_kind": kind, "frames": 10,  # noqa: E731
                                 "runs": [{"seed": 0, "final": final, "models": {}}]}
    res = {"mode": "iterations", "mode_note": "note", "profile": "quick", "n_points": 100, "seeds": 1,
           "methods": methods, "scenes": {
               "stairs": scene({"voxel-5cm": _metrics(3.0, 2.5, 3.5), "aisdf-served": _metrics(2.0, 1.25, 2.75)},
                               "exact"),
               "replica-office": scene({m: _metrics(4.0) for m in methods}, "mesh")}}
    md, data = table1(res)
    assert "| stairs | 40.0 | 2.50 / 3.50 | 1.25 / 2.75 |" in md
    assert "| replica-office | n/a | n/a | n/a |" in md and "n/a (replica-office): no labels" in md
    assert f"within {100 * NEAR_FURNITURE_M:g} cm" in md
    assert data["scenes"]["stairs"]["methods"]["aisdf-served"]["sdf_error_near_furniture_cm"] == 1.25
    assert "near_furniture_share" not in data["scenes"]["replica-office"]["methods"]["aisdf-served"]
    mdc, datac = table1c(res)
    assert "| stairs | AiSDF served (default answer) | 40.0 | 1.25 | 5.0 | 2.50 | 2.75 | 2.00 |" in mdc
    assert set(datac["scenes"]["stairs"]) == set(methods) and datac["scenes"]["replica-office"] == {}
    assert "replica-office" in datac["unlabelled"]


def test_scaling_scorer_splits_near_furniture():
    """``aisdf bench scaling``'s scorer: the served answer's error near furniture and away from it,
    and near furniture where no keyframe measured the nearest surface."""
    from aisdf.bench.scaling_walk import _Scorer
    from aisdf.structure.measured import MeasuredPoints

    x = np.linspace(0.1, 1.0, 10)
    pts = np.stack([x, np.zeros(10), np.zeros(10)], axis=1)
    gt = x.copy()  # the measured point at the origin is every point's nearest surface
    near = np.arange(10) % 2 == 0
    gt[8:] -= 0.2  # ... but the last two have an unmeasured surface 20 cm nearer (one near furniture)

    class Pipe:
        measured = None

        def sdf(self, points):
            return (gt + 0.1 * near).astype(np.float32)

        def surfels(self):
            return None

    *_, split = _Scorer(pts, gt, near).evaluate_split(Pipe(), source="implicit")
    assert split == {"points_pct": 50.0, "error_cm": pytest.approx(10.0), "away_error_cm": pytest.approx(0.0)}
    *_, split = _Scorer(pts, gt, near).evaluate_split(Pipe(), MeasuredPoints(np.zeros((1, 3))), source="implicit")
    assert split["unmeasured_pct"] == 10.0 and split["unmeasured_error_cm"] == pytest.approx(10.0)
    assert _Scorer(pts, gt).evaluate_split(Pipe())[3] == {}  # no labels: no split
