"""The ownership rule of mapper shards (protocol 1.14): stable across processes, minimal
movement when a member joins or leaves, and the front end's "every needed owner acked"."""

import subprocess
import sys

import numpy as np
import pytest

from aisdf.cluster import ownership as own
from aisdf.cluster.regions import touched_regions
from aisdf.submaps.grid import SubmapGrid

REGIONS = [own.region_id((a, b, 0)) for a in range(-5, 5) for b in range(-5, 5)]


def table(members):
    return {r: own.owners(r, members) for r in REGIONS}


def test_region_of_groups_cells_horizontally():
    assert own.region_of((0, 0, 0)) == (0, 0, 0)
    assert own.region_of((1, 1, 0)) == (0, 0, 0)
    assert own.region_of((2, -1, 1)) == (1, -1, 1)
    assert own.region_of((-1, -2, 0)) == (-1, -1, 0)
    assert own.region_of((5, 7, 2), 1) == (5, 7, 2)
    assert own.region_id((1, -1, 0)) == "1_-1_0"
    with pytest.raises(ValueError):
        own.region_of((0, 0, 0), 0)


def test_the_same_owners_in_another_process():
    members = ["mapper-a", "mapper-b", "mapper-c"]
    code = ("from aisdf.cluster import ownership as o;"
            f"print([o.owners(r, {members!r}) for r in {REGIONS!r}])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONHASHSEED": "12345", "PATH": ""}).stdout
    assert out.strip() == str([own.owners(r, members) for r in REGIONS])
    # a fixed value: the hash is blake2b, never Python's salted hash
    assert own.score("mapper-a", "0_0_0") == int.from_bytes(
        __import__("hashlib").blake2b(b"mapper-a\x000_0_0", digest_size=8).digest(), "big")


def test_owners_are_distinct_ranked_and_fewer_with_fewer_members():
    t = table(["a", "b", "c"])
    assert all(len(o) == 2 and o[0] != o[1] for o in t.values())
    assert own.owners("0_0_0", ["a"]) == ["a"]
    assert own.owners("0_0_0", []) == []
    assert own.rank("z", "0_0_0", ["a"]) == 0
    for r, o in t.items():
        assert own.rank(o[0], r, ["a", "b", "c"]) == 1 and own.rank(o[1], r, ["c", "b", "a"]) == 2
    # every member is rank 1 of some regions: the work is shared (100 regions, 3 members)
    firsts = [o[0] for o in t.values()]
    assert all(15 <= firsts.count(m) <= 55 for m in "abc"), {m: firsts.count(m) for m in "abc"}


def test_a_member_leaving_moves_only_its_regions_and_its_replica_takes_over():
    before, after = table(["a", "b", "c"]), table(["a", "b"])
    for r in REGIONS:
        if "c" not in before[r]:
            assert after[r] == before[r]  # untouched
        elif before[r][0] == "c":
            assert after[r][0] == before[r][1]  # the replica becomes rank 1: it holds the keyframes
        else:
            assert after[r][0] == before[r][0]  # rank 1 stays


def test_a_member_joining_takes_only_what_it_ranks_in():
    before, after = table(["a", "b", "c"]), table(["a", "b", "c", "d"])
    moved = 0
    for r in REGIONS:
        if "d" not in after[r]:
            assert after[r] == before[r]
        else:
            moved += 1
            assert [m for m in after[r] if m != "d"] == before[r][:1]  # the others keep their order
    assert 25 <= moved <= 75  # about 2/4 of the regions gain d as an owner
    assert sum(after[r][0] == "d" for r in REGIONS) >= 10


def test_surfel_owner_is_one_live_member():
    assert own.surfel_owner([]) is None
    assert own.surfel_owner(["b", "a"]) in ("a", "b")
    assert own.surfel_owner(["b", "a"]) == own.surfel_owner(["a", "b"])


def test_satisfied_needs_ranks_1_and_2_of_every_touched_region():
    members = ["a", "b", "c"]
    touched = ["0_0_0", "1_0_0"]
    need = own.needed_acks(touched, members)
    assert need == {(m, r) for r in touched for m in own.owners(r, members)}
    holders = {}
    for m, r in need:
        holders.setdefault(m, set()).add(r)
    assert own.satisfied(touched, holders, members)
    m0, r0 = sorted(need)[0]
    partial = {m: set(h) for m, h in holders.items()}
    partial[m0].discard(r0)
    assert not own.satisfied(touched, partial, members)
    # a needed owner died: the remaining live owners decide (ranks recomputed)
    dead = own.owners("0_0_0", members)[0]
    alive = [m for m in members if m != dead]
    redo = {m: set(touched) for m in alive}
    assert own.satisfied(touched, redo, alive)
    assert not own.satisfied(touched, {dead: own.ALL}, alive)  # only a dead member acked


def test_satisfied_single_and_legacy_mappers_as_in_1_11():
    assert own.satisfied(None, {own.LEGACY: own.ALL}, [])  # an acknowledgement without a mapper id
    assert own.satisfied(["0_0_0"], {"m": own.ALL}, ["m"])
    assert own.satisfied(None, {"m": own.ALL}, ["m"])
    assert not own.satisfied(None, {"m": own.ALL}, ["m", "n"])  # before the grid: every member holds it
    assert not own.satisfied(None, {}, ["m"])
    assert own.satisfied([], {"m": set()}, ["m"])  # touches no region: any live acknowledgement


def test_touched_regions_of_a_keyframe():
    grid = SubmapGrid(np.eye(3), np.zeros(3), 4.0, 6.0, 0.5)
    K = np.array([[40.0, 0, 40], [0, 40.0, 30], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [2.0, 2.0, 3.0]
    depth = np.full((60, 80), 1.0, np.float32)  # a wall 1 m ahead (+z): inside cell (0, 0, 0)
    assert touched_regions(grid, depth, K, T) == ["0_0_0"]
    T[:3, 3] = [7.9, 2.0, 3.0]  # near the face x = 8: cells 1 and 2 along x, regions 0 and 1
    assert touched_regions(grid, depth, K, T) == ["0_0_0", "1_0_0"]
    assert touched_regions(grid, depth, K, T, region_cells=1) == ["1_0_0", "2_0_0"]
