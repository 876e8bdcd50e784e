"""``aisdf bench change``: its parts that are fast (the rays that see a space empty, the wall
profiles' surfaces, the report of every criterion), and its ``--quick`` run of the cart and
the parked robot through the real services (the person and the drift take minutes more; the
bench's full run is in docs/benchmarks.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aisdf.bench import change
from aisdf.synthetic.changes import ChangingSequence


def test_rays_through_the_cart_see_its_space_empty_only_when_it_is_gone():
    seq = ChangingSequence("office", "cart", n_frames=300, pause_s=1.0, noise=False)
    counts = []
    for i in range(150, 300, 30):
        f1, f2 = seq.frame(i), seq.frame(i + seq.removed_at)
        counts.append((change.rays_through(seq, f1, seq.true_poses[i], seq.cart),
                       change.rays_through(seq, f2, seq.true_poses[i], seq.cart)))
    assert all(a <= 5 for a, _ in counts), counts  # the cart stops them at its faces
    assert max(b for _, b in counts) > 100, counts  # gone, they pass through its space


def test_surfaces_and_crossings_of_a_profile():
    s = np.linspace(1.0, -0.1, 111)
    wall = s.copy()
    assert change.surfaces(wall) == 1 and change.crossings(wall) == 1
    assert change.surfaces(np.abs(wall)) == 1 and change.crossings(np.abs(wall)) == 0  # positive behind: one surface
    ghost = np.minimum(wall, np.abs(s - 0.2))  # a second wall 20 cm in front
    assert change.surfaces(ghost) == 2
    waver = np.where(np.abs(s) < 0.05, 0.02 + 0.005 * np.sign(np.sin(100 * s)), np.abs(s))
    assert change.surfaces(waver) == 1  # about 2 cm at the wall: one surface


def _result() -> dict:
    watch = [{"after_s": k, "occupied": max(0.0, 0.9 - 0.2 * k), "map_version": k} for k in range(9)]
    return {
        "date": "2026-12-05", "commit": "abc1234", "wall_s": 100.0,
        "args": {"building": "office", "seed": 0, "frames": 300, "preset": "cpu", "after_s": 10.0},
        "cart": {"standing": {"occupied": 0.85, "still_occupied": 0.9, "room_error_cm": 3.0},
                 "watch": watch, "cleared_after_s": 5, "after": {"room_error_cm": 3.2}, "room_ratio": 3.2 / 3.0,
                 "first_empty_frame": 500, "first_empty_t_s": 30.0, "seen_empty_t_s": 42.0,
                 "cleared_since_first_s": 3},
        "person": {"after_s": 10.0, "worst_below_m": -0.5, "occupied": 0.3},
        "drift": {"corrections_available": True, "ratio": 1.1,
                  "drift_end": {"error_cm": 9.0, "surfaces": [2, 1], "crossings": [1, 1]},
                  "drift_after": {"error_cm": 3.3, "surfaces": [1, 1], "crossings": [1, 1]},
                  "true_after": {"error_cm": 3.0, "surfaces": [1, 1], "crossings": [1, 1]}},
        "parked": {"frames": 3600, "redundant": 3598, "end": {"keyframes": 2, "rss_mb": 361.0},
                   "start": {"rss_mb": 359.0}},
    }


def test_report_gives_every_criterion_its_target_and_verdict():
    md = change.report(_result())
    assert "| cart: its volume answered occupied while it stands | 85.0 % | >= 80 % | yes |" in md
    assert "| cart: time until <= 5 % occupied | 5 s | <= 10 s | yes |" in md
    assert "| (the same, from the first keyframe that saw it gone, 12 s before the last) | 3 s |  |  |" in md
    assert "3.00 -> 3.20 cm (x1.07) | <= x1.10 | yes |" in md
    assert "| -50.0 cm | >= -20 cm | no |" in md
    assert "3.30 vs 3.00 cm (x1.10) | <= x1.2 | yes |" in md
    assert "2 (3,598 redundant)" in md and "359.0 -> 361.0 MB (+2.0)" in md
    res = _result()
    res["drift"].update(corrections_available=False, corrections_error="TimeoutError: no reply")
    assert "NOT corrected (TimeoutError)" in change.report(res)


@pytest.mark.e2e
def test_quick_run_of_the_cart_and_the_parked_robot(tmp_path, capsys):
    change.main(["--quick", "--only", "cart,parked", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    for text in ("cart: its volume answered occupied while it stands", "cart: time until <= 5 % occupied",
                 "cart: rest of the room's mean error", "parked: keyframes kept of 200 frames",
                 "parked: process memory start -> end", ">= 80 %", "<= 10 s", "<= x1.10"):
        assert text in out, text
    res = json.loads((tmp_path / "change.json").read_text())
    c = res["cart"]
    assert c["keyframes"] > 10 and c["keyframes_seeing_empty"] > 0 and len(c["watch"]) == 9
    assert c["first_empty_frame"] >= 420 and all(0 <= w["occupied"] <= 1 for w in c["clearing"])
    assert 0 <= c["standing"]["occupied"] <= 1 and c["standing"]["room_error_cm"] > 0
    assert res["parked"]["frames"] == 200 and "person" not in res and "drift" not in res
