"""Table I's additions: the served column is the query service's answer (``served_answer``),
the voxel maps at 5 and 2 cm report memory and time, seeds give a spread, and the
observed / unobserved split (Table Ib) covers every point once."""

from __future__ import annotations

import math

import numpy as np
import pytest

import open3d  # noqa: F401 - the voxel maps need it (dev extra)

from aisdf import protocol, query_messages
from aisdf.bench import methods as bench_methods
from aisdf.bench.evaluation import EvalSet, observed_mask
from aisdf.bench.methods import ComputeClock, make_runner
from aisdf.bench.profiles import resolve
from aisdf.bench.report import table1, table1b
from aisdf.bench.scenes import make_scene
from aisdf.bench.suite import config_from_args, run

SCENE = "manhattan"
TINY = {"n_frames": 40, "H": 45, "W": 60}


@pytest.fixture(scope="module")
def aisdf_runner():
    """AiSDF's model after a short stream (a few keyframes, a handful of steps each)."""
    sc = make_scene(SCENE, TINY)
    training = {"network": {"width": 32}, "n_rays": 30, "window_size": 3, "seed": 0, "steps_first_frame": 10,
                "steps_per_keyframe": 3}
    r = make_runner("aisdf", sc, ComputeClock(), "cpu", training)
    for i in range(len(sc)):
        r.see(sc.frames.frame(i), train=True)
    assert r.keyframes >= 2 and len(r.pipe.measured_points()) > 100 and r.surfels() is not None
    frames = [sc.frames.frame(i) for i in range(0, len(sc), 5)]
    return sc, r, EvalSet(sc, frames, 3_000, 0).points[:400]


def test_served_column_is_the_query_services_default_answer(aisdf_runner):
    """The column's values are what a query service holding this map answers (exact, fused)."""
    from aisdf.query.engine import QueryEngine

    _, r, pts = aisdf_runner
    eng = QueryEngine(device="cpu", bake=False)
    for key, data in r.pipe.map_messages(1, changed_only=False, epoch=1):
        eng.take(key, protocol.unpack(data))
    assert eng.state.measured is not None and len(eng.state.surfels)
    rep = eng.answer_sdf(query_messages.SdfRequest(pts.astype(np.float32), gradient=True))
    f, g = r.query("served", pts, True)
    np.testing.assert_allclose(f, rep.sdf, atol=2e-4)
    np.testing.assert_allclose(g, rep.gradient, atol=2e-3)
    # the measured points matter here: the served answer is not the paper's fused one
    assert np.abs(f - r.query("fused", pts, False)[0]).max() > 1e-3


def test_served_column_is_computed_by_served_answer(aisdf_runner, monkeypatch):
    """Break ``served_answer`` on purpose: the column follows it."""
    import aisdf.query.answer as answer

    _, r, pts = aisdf_runner
    before = r.query("served", pts, False)[0]
    real = answer.served_answer
    calls = []

    def broken(points, *a, **k):
        calls.append(len(points))
        f, g = real(points, *a, **k)
        return f + 1.0, g

    monkeypatch.setattr(answer, "served_answer", broken)
    after = r.query("served", pts, False)[0]
    assert calls == [len(pts)]
    np.testing.assert_allclose(after, before + 1.0, atol=1e-5)


def test_voxel_maps_at_5_and_2_cm_report_memory_and_time():
    """Both voxel rows on a small box: their voxel size, integration and ESDF time, memory."""
    sc = make_scene(SCENE, {"n_frames": 12, "H": 30, "W": 40})
    sc.bounds = np.array([[2.0, -2.5, -0.5], [5.0, 0.5, 2.5]])  # a small box: the 2 cm grid stays small
    out = {}
    for model in ("voxel-5cm", "voxel-2cm"):
        r = make_runner(model, sc, ComputeClock(), "cpu", {})
        for i in range(len(sc)):
            r.see(sc.frames.frame(i), train=True)
        r.query("voxel", np.array([[3.0, -1.0, 1.0]]), True)
        out[model] = r.summary()
    assert out["voxel-5cm"]["voxel_size"] == 0.05 and out["voxel-2cm"]["voxel_size"] == 0.02
    for s in out.values():
        assert s["timings_ms"]["integrate"] > 0 and s["timings_ms"]["esdf"] > 0
        assert s["memory_mb"]["tsdf"] > 0 and s["memory_mb"]["esdf"] > 0
    assert out["voxel-2cm"]["memory_mb"]["esdf"] > 5 * out["voxel-5cm"]["memory_mb"]["esdf"]


def test_split_shares_add_up_and_ground_truth_scores_zero():
    # quick-profile images: at 80x60 pixels are about 5 cm apart on a wall 2 m away
    sc = make_scene("atlanta", {"n_frames": 40, "H": 60, "W": 80})
    frames = [sc.frames.frame(i) for i in range(0, 40, 5)]
    es = EvalSet(sc, frames, 3_000, 0, split=True)
    r = es.score(lambda p, g: (sc.gt_sdf(p), sc.gt_grad(p)))
    assert r["observed_share"] + r["unobserved_share"] == pytest.approx(1.0)
    assert 0.7 < r["observed_share"] < 0.98  # most nearest surfaces were measured, not all (0.83 measured)
    assert r["sdf_error_observed_cm"] == 0 and r["sdf_error_unobserved_cm"] == 0
    shifted = es.score(lambda p, g: (sc.gt_sdf(p) + 0.05, g and sc.gt_grad(p)))
    assert shifted["sdf_error_observed_cm"] == pytest.approx(5.0)
    assert shifted["sdf_error_unobserved_cm"] == pytest.approx(5.0)
    # a surface point seen by a frame is observed; with no frames nothing is
    assert not observed_mask(sc, [], es.points[:10], es.gt[:10]).any()


def test_seeds_option_and_spread(tmp_path):
    """``--seeds 0 2`` runs those seeds; one number is a count; tables give mean ± spread."""
    import argparse

    from aisdf.bench.suite import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    assert config_from_args(p.parse_args(["--quick", "--seeds", "0", "2"])).seed_list == [0, 2]
    assert config_from_args(p.parse_args(["--quick", "--seeds", "3"])).seed_list == [0, 1, 2]
    with pytest.raises(ValueError):
        resolve("quick", seeds=[1, 1])
    cfg = resolve("quick", scenes=[SCENE], methods=["voxel-5cm", "aisdf-served"], ablation=[], frames=30,
                  checkpoints=1, n_points=1_500, artefacts=False, progress=False, seeds=[0, 2],
                  training={"network": {"width": 32}, "n_rays": 30}, schedule_scale=0.05, out=str(tmp_path))
    res = run(cfg)
    runs = res["scenes"][SCENE]["runs"]
    assert [r["seed"] for r in runs] == [0, 2] and res["seeds"] == [0, 2]
    for r in runs:
        for m in ("voxel-5cm", "aisdf-served"):
            f = r["final"][m]
            assert math.isfinite(f["sdf_error_cm"])
            assert f["observed_share"] + f["unobserved_share"] == pytest.approx(1.0)
            assert 0 < f["near_furniture_share"] < 1 and math.isfinite(f["sdf_error_near_furniture_cm"])
        assert r["final"]["voxel-5cm"]["near_furniture_share"] == r["final"]["aisdf-served"]["near_furniture_share"]
    md, data = table1(res)
    assert " ± " in md and "AiSDF served (default answer)" in md
    assert "**Near furniture**" in md and (tmp_path / "table1c.md").exists()
    cell = data["scenes"][SCENE]["methods"]["aisdf-served"]
    assert cell["seeds"] == 2 and cell["sdf_error_cm_std"] > 0  # two trainings differ
    mdb, datab = table1b(res)
    assert "Table Ib" in mdb and set(datab["scenes"][SCENE]) == {"voxel-5cm", "aisdf-served"}
    assert (tmp_path / "table1b.md").exists()


def test_methods_table_lists_the_new_columns():
    assert bench_methods.METHODS["aisdf-served"] == ("aisdf", "served")
    assert bench_methods.MODELS["aisdf"].measured and not bench_methods.MODELS["isdf"].measured
    assert bench_methods.MODELS["voxel-2cm"].voxel_size == 0.02


def test_baked_column_is_the_services_baked_reply(aisdf_runner):
    """``aisdf-baked``: the default reply of a query service that has baked the map, close to
    the exact composition (the bake interpolates it)."""
    _, r, pts = aisdf_runner
    assert bench_methods.METHODS["aisdf-baked"] == ("aisdf", "baked")
    f, g = r.query("baked", pts, True)
    eng = r.engine()
    assert eng.baked is not None and r.engine() is eng  # baked once per map
    rep = eng.answer_sdf(query_messages.SdfRequest(pts.astype(np.float32)))
    assert rep.baked
    np.testing.assert_allclose(f, rep.sdf, atol=1e-6)
    exact = r.query("served", pts, False)[0]
    assert np.mean(np.abs(f - exact)) < 0.01 and g.shape == (len(pts), 3)
