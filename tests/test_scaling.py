"""``aisdf bench scaling --quick`` for real: a tiny walk of the office and the floor with
every method, one keyframe per 0.25 s and 2 s more, then the table's structure and sane values."""

from __future__ import annotations

import importlib.util
import json
import math

import pytest

from aisdf.bench import scaling


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("scaling")
    cfg = scaling.resolve("quick", out=str(out), progress=False)
    return cfg, scaling.run(cfg), out


def test_quick_scaling_table(result):
    cfg, res, out = result
    methods = ["single"]
    if importlib.util.find_spec("aisdf.submaps.pipeline") is not None:
        methods.append("submaps")  # present in this tree: it must run
    assert set(methods) <= set(res["runs"]), res["unavailable"]
    saved = json.loads((out / "scaling.json").read_text())
    assert saved["criteria"] == res["criteria"]
    md = (out / "scaling.md").read_text()
    assert "| step time mean / p95 (ms) |" in md and "room7" in md and "implicit answer" in md
    assert cfg.source == "fused"  # the criteria judge query/sdf's default answer
    n, P = cfg.keyframes, cfg.period_s
    for m in methods:
        for scene in ("office", "floor"):
            r = res["runs"][m][scene]
            assert r["keyframes"] + r["rejected"] == n and r["rejected"] == 0
            assert r["step_ms"]["n"] == r["steps"]
            if r["steps"]:  # none only if adding the keyframes alone took the whole walk (an overloaded machine)
                assert 0 < r["step_ms"]["mean"] <= r["step_ms"]["p95"]
            # One publication per period over the walk and the tail (the clock pauses for them).
            assert abs(len(r["periods"]) - (n * P + cfg.tail_s) / P) <= 1
            assert sum(p["walking"] for p in r["periods"]) == pytest.approx(n, abs=1)
            assert 0 < r["bytes_per_s"] <= r["bytes_per_s_all"]
            mem = r["memory_end"]
            assert {"keyframes", "model", "observed"} <= set(mem) and all(v > 0 for v in mem.values())
            assert r["memory_bytes"] == sum(mem.values()) and r["memory_per_keyframe"] == r["memory_bytes"] // n
            for k in ("walk_end", "end"):
                assert math.isfinite(r[f"error_{k}_cm"]) and 0 < r[f"error_{k}_cm"] < 200
                by = r[f"error_{k}_by_source_cm"]  # the default answer (judged) and the network alone, both kept
                assert set(by) == {"fused", "implicit"} and by[cfg.source] == r[f"error_{k}_cm"]
                assert all(math.isfinite(v) and 0 < v < 200 for v in by.values())
            assert r["steps_end"] >= r["steps_walk_end"] and r["t_end"] >= r["t_walk_end"] >= n * P
            assert 0 <= r["keyframe_late_s"]["mean"] <= r["keyframe_late_s"]["max"]
        floor = res["runs"][m]["floor"]
        assert len(floor["rooms"]) >= 5  # a dozen keyframes over the whole walk: most rooms seen
        for room, v in floor["rooms"].items():
            assert room.startswith("room") and v["points"] >= 20 and v["keyframes"] >= 1
            assert v["ratio_end"] == pytest.approx(v["end_cm"] / v["after_visit_cm"], rel=1e-2)
        assert res["runs"][m]["office"]["rooms"] == {}
        crit = res["criteria"][m]
        assert any("<= 5 cm" in c for c in crit) and any("1/3" in c for c in crit)
        assert all(v["ok"] is None or v["ok"] == (v["value"] <= v["limit"]) for v in crit.values())
    assert res["runs"]["single"]["floor"]["bytes_ratio"] == 1.0  # one network: all of it, every period
    info = res["scene_info"]["floor"]
    assert len(info["visits"]) == 7 and info["stream_s_per_keyframe"] > 10  # spread over the whole walk


def test_training_overrides_from_the_command_line_merge_over_the_profile():
    import argparse

    p = argparse.ArgumentParser()
    scaling.add_arguments(p)
    args = p.parse_args(["--quick", "--training", '{"network": {"width": 128}, "lr_settle": null}'])
    cfg = scaling.config_from_args(args)
    assert cfg.training["network"] == {"width": 128} and cfg.training["lr_settle"] is None
    assert cfg.training["n_rays"] == scaling.PROFILES["quick"]["training"]["n_rays"]  # the profile's, kept
    with pytest.raises(SystemExit):
        p.parse_args(["--training", "[1, 2]"])
