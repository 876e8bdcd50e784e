"""``aisdf bench load`` end to end: planners hammering the real query service over Zenoh while
the real mapper trains a walk beside it. Small: 2 planners, a few seconds."""

from aisdf.bench.load import planners_beside_mapper, report


def test_planners_beside_a_training_mapper_are_answered_first(tmp_path):
    # fresh_s 0: every map newer than the bake makes it trail; one worker and two planners back
    # to back: a request waits while the other is answered, and the trailing bake answers.
    # The walk (36 keyframes, 18 s) goes on through the planners' 12 s, so the map keeps
    # changing while they ask (with 6 s of a 12 s walk, a loaded machine once held none).
    res = planners_beside_mapper(planners=2, seconds=12.0, n_points=2000, keyframes=36, period_s=0.5, warmup_s=6.0,
                                 query_set=["fresh_s=0", "workers=1"], mapper_set=["training.network.width=32"],
                                 log_dir=tmp_path / "logs", say=lambda s: None)
    assert res["answered"] == res["sent"] > 10 and res["lost"] == 0 and res["errors"] == res["timeouts"] == 0
    assert res["mapper_steps"] > 0 and res["keyframes_published"] > 12  # the mapper trained meanwhile
    assert res["service"]["answered"] >= res["answered"]
    assert res["service"]["held"] > 0  # planners first: some answers came from the trailing bake
    m = res["query_rss_mb"]
    assert 100 < m["start"] <= m["max"] < 4000
    assert "planners x" in report(res)
