"""Mapper shards (protocol 1.14) without processes: the query engine orders each submap by
(term, version) and merges the shards' submaps on one grid across epochs; the front end's
outbox keeps a keyframe until every live owner it needs holds it."""

import time

import numpy as np
import pytest
import torch

from aisdf import protocol
from aisdf.cluster import ownership as own
from aisdf.network import NetworkConfig, SDFNetwork, model_spec, state_to_numpy
from aisdf.query.engine import QueryEngine
from aisdf.submaps.grid import SubmapGrid, cell_id
from aisdf_frontend.main import _shard_fields
from aisdf_frontend.outbox import KeyframeOutbox

GRID = SubmapGrid(np.eye(3), np.zeros(3), 4.0, 6.0, 0.5)


def snap(cell, version, term=None, mapper=None, epoch=1000, bias=0.0, grid=GRID):
    torch.manual_seed(0)
    net = SDFNetwork(NetworkConfig(width=16, offset=grid.centre_W(cell).tolist()))
    spec = model_spec(net)
    c = grid.corners_W(cell, grid.overlap_m)
    spec["bounds"] = [c.min(0).tolist(), c.max(0).tolist()]
    state = state_to_numpy(net)
    k = sorted(k for k in state if k.endswith("bias"))[-1]
    state[k] = state[k] + np.float32(bias)  # tells the snapshots apart
    hdr = {"id": cell_id(cell), "grid": grid.to_msg()}
    if term is not None:
        hdr.update(term=term, mapper=mapper)
    return protocol.WeightSnapshot(version, 10, time.time(), spec, state, epoch, None, hdr)


def held(e, cell):
    return e.state.submaps.submaps[cell]


def test_a_submap_orders_by_term_then_version_and_shards_merge_across_epochs():
    e = QueryEngine(device="cpu", bake=False)
    a, b = (0, 0, 0), (1, 0, 0)
    assert e.set_submap(snap(a, 500, term=10, mapper="m1", epoch=1000))
    assert e.set_submap(snap(b, 400, term=11, mapper="m2", epoch=1001))  # another shard, another epoch: joins
    assert set(e.state.submaps.submaps) == {a, b} and e.state.epoch == 1001
    assert e.set_submap(snap(a, 300, term=20, mapper="m2", epoch=1000))  # the new owner: newer term, lower version
    assert held(e, a).mapper == "m2" and held(e, a).order == (20, 300)
    assert not e.set_submap(snap(a, 900, term=10, mapper="m1", epoch=1000))  # the old owner, late: ignored
    assert held(e, a).mapper == "m2"
    assert e.set_submap(snap(a, 301, term=20, mapper="m2", epoch=1000))
    assert e.state.epoch == 1001 and e.state.version >= 500  # a served map never goes back
    # an index from one shard does not drop the other shard's submaps (it lists only its own)
    idx = protocol.SubmapIndex(600, time.time(), GRID.to_msg(), {cell_id(b): {"version": 400, "step": 10}}, 1001)
    assert e.set_index(idx) == []
    assert set(e.state.submaps.submaps) == {a, b}
    with pytest.raises(ValueError):
        e.set_submap(snap((2, 0, 0), 1, term=-1, mapper="m1"))


def test_without_terms_a_new_epoch_replaces_the_set_as_before():
    e = QueryEngine(device="cpu", bake=False)
    assert e.set_submap(snap((0, 0, 0), 5, epoch=1000))
    assert e.set_submap(snap((1, 0, 0), 1, epoch=2000))
    assert set(e.state.submaps.submaps) == {(1, 0, 0)}
    assert not e.set_submap(snap((0, 0, 0), 9, epoch=1000))
    assert e.set_submap(snap((1, 0, 0), 2, epoch=2000)) and not e.set_submap(snap((1, 0, 0), 2, epoch=2000))


def test_a_sharded_set_on_another_grid_needs_a_newer_epoch():
    e = QueryEngine(device="cpu", bake=False)
    other = SubmapGrid(np.eye(3), np.ones(3), 4.0, 6.0, 0.5)
    assert e.set_submap(snap((0, 0, 0), 5, term=3, mapper="m1", epoch=1000))
    assert not e.set_submap(snap((0, 0, 0), 6, term=4, mapper="m2", epoch=999, grid=other))
    assert e.set_submap(snap((0, 0, 0), 6, term=4, mapper="m2", epoch=1001, grid=other))
    assert e.state.submaps.grid.same_as(other)


def members_and_owners():
    members = ["m1", "m2", "m3"]
    touched = ["0_0_0", "1_0_0"]
    need = own.needed_acks(touched, members)
    return members, touched, need


def test_outbox_keeps_a_keyframe_until_every_needed_owner_holds_it():
    members, touched, need = members_and_owners()
    box = KeyframeOutbox(resend_period_s=3.0, clock=lambda: 0.0)
    box.set_members(members)
    box.add(7, b"kf")
    assert box.due() == [(7, b"kf")]
    by = {}
    for m, r in need:
        by.setdefault(m, []).append(r)
    outsider = [m for m in members if m not in by]
    if outsider:  # a mapper owning none of its regions acknowledges holding nothing: not enough
        assert box.ack([7], (), outsider[0], [touched], [[]]) == 0
    acks = sorted(by.items())
    for m, regions in acks[:-1]:
        assert box.ack([7], (), m, [touched], [regions]) == 0
        assert box.pending == 1
    m, regions = acks[-1]
    assert box.ack([7], (), m, [touched], [regions[:-1]]) == 0  # one region short
    assert box.ack([7], (), m, [touched], [regions]) == 1 and box.pending == 0
    assert box.counts["acked"] == 1


def test_outbox_a_dead_owner_no_longer_needed_and_a_legacy_ack_counts_alone():
    members, touched, need = members_and_owners()
    box = KeyframeOutbox()
    box.set_members(members)
    box.add(1, b"a")
    box.add(2, b"b")
    first = own.owners("0_0_0", members)[0]
    for m in members:
        if m != first:
            box.ack([1], (), m, [touched], [touched])
    assert box.pending == 2
    assert box.set_members([m for m in members if m != first]) == 1  # the rest hold it: done
    assert box.pending == 1
    assert box.ack([2]) == 1 and box.pending == 0  # no mapper id: a 1.11 mapper's ack


def test_shard_fields_of_an_acknowledgement():
    assert _shard_fields({"frame_ids": [1]}, 1) == ()
    assert _shard_fields({"mapper": "m1", "touched": [["0_0_0"]], "held": ["*"]}, 1) == ("m1", [["0_0_0"]], ["*"])
    for bad in ({"mapper": "m1", "touched": [], "held": []}, {"mapper": 3, "touched": [None], "held": ["*"]},
                {"mapper": "m1", "touched": [None], "held": ["all"]}, {"mapper": "m1", "touched": [[1]], "held": ["*"]}):
        with pytest.raises(ValueError):
            _shard_fields(bad, 1)
