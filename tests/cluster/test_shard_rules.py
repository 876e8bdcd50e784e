"""A mapper shard's keyframe rule (protocol 1.14) without Zenoh: it keeps a keyframe touching a
region it ranks 1 or 2 for (rank 2: a replica, for a handover), and only then."""

from types import SimpleNamespace

import numpy as np

from aisdf import protocol
from aisdf.cluster import ownership as own
from aisdf.submaps.grid import SubmapGrid
from aisdf_mapper.config import ClusterConfig
from aisdf_mapper.shard import Shard, default_mapper_id

GRID = SubmapGrid(np.eye(3), np.zeros(3), 4.0, 6.0, 0.5)
MEMBERS = frozenset({"m1", "m2", "m3"})


def shard(mid, grid=GRID):
    node = SimpleNamespace(cfg=SimpleNamespace(checkpoint_dir=None), pipeline=SimpleNamespace(grid=grid), ns="t",
                           seen={("depth", 1)})
    s = Shard(node, ClusterConfig(enabled=True, mapper_id=mid, region_cells=1))
    s.members = s.ranked_members = MEMBERS
    return s


def keyframe(x):
    K = np.array([[40.0, 0, 40], [0, 40.0, 30], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [x, 2.0, 3.0]
    return protocol.Keyframe(1, 0.0, np.full((60, 80), 1.0, np.float32), K, T)


def test_ranks_1_and_2_keep_a_keyframe_rank_3_does_not():
    kf = keyframe(2.0)  # touches region 0_0_0 only
    first, second = own.owners("0_0_0", MEMBERS)
    (third,) = MEMBERS - {first, second}
    for mid, keeps in ((first, True), (second, True), (third, False)):
        hold, touched, held = shard(mid).decide(kf)
        assert touched == ["0_0_0"]
        assert hold is keeps and held == (["0_0_0"] if keeps else []), mid
    assert shard(first).owns_cell((0, 0, 0)) and not shard(second).owns_cell((0, 0, 0))


def test_before_the_grid_every_shard_keeps_every_keyframe():
    assert shard("m1", grid=None).decide(keyframe(2.0)) == (True, None, own.ALL)


def test_default_ids_are_stable_for_a_checkpoint_directory(tmp_path):
    assert default_mapper_id(tmp_path) == default_mapper_id(str(tmp_path) + "/")
    assert default_mapper_id(tmp_path) != default_mapper_id(tmp_path / "other")
    assert "/" not in default_mapper_id(None)


def test_the_surfel_publisher_publishes_also_without_submaps_of_its_own():
    owner = own.surfel_owner(MEMBERS)
    s, other = shard(owner), shard(sorted(MEMBERS - {owner})[0])
    s.node.seen = other.node.seen = {("depth", 1)}
    assert s.surfels_due() and not s.surfels_due()  # once per new keyframe taken
    s.node.seen = {("depth", 1), ("depth", 2)}
    assert s.surfels_due()
    assert not other.surfels_due()  # not its map to publish
    assert not shard(owner, grid=None).surfels_due()
