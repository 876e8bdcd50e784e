"""Protocol 1.2 in-process: the frontend's bounded outbox, the mapper's deduplication,
journal and acknowledgements, epochs and versions across restarts, and old v1 messages."""

import msgpack
import numpy as np
import pytest

from aisdf import keys, protocol
from aisdf_frontend.outbox import KeyframeOutbox
from aisdf_mapper.config import MapperConfig
from aisdf_mapper.main import JOURNAL_NAME, MapperNode

# ----------------------------------------------------------------------------- frontend outbox


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_outbox_holds_a_bounded_number_while_no_mapper_is_there():
    box = KeyframeOutbox(hold_max=3, window=8, resend_period_s=2.0, clock=Clock())
    for i in range(5):
        box.add(i, b"kf%d" % i)
    assert box.due() == []  # no mapper: nothing is sent
    assert list(box.items) == [2, 3, 4] and box.counts["dropped"] == 2 and box.pending == 3
    box.set_mapper_present(True)
    assert [fid for fid, _ in box.due()] == [2, 3, 4]
    assert box.due() == []  # in flight, not due yet
    assert box.ack([2, 3, 4]) == 3 and box.pending == 0
    assert box.counts == {"sent": 3, "resent": 0, "acked": 3, "rejected": 0, "dropped": 2}


def test_outbox_window_resend_and_a_new_mapper():
    clock = Clock()
    box = KeyframeOutbox(hold_max=100, window=2, resend_period_s=2.0, clock=clock)
    box.set_mapper_present(True)
    for i in range(5):
        box.add(i, b"x")
    assert [f for f, _ in box.due()] == [0, 1]  # the window
    box.ack([0])
    assert [f for f, _ in box.due()] == [2]
    clock.t = 2.5
    assert [f for f, _ in box.due()] == [1, 2]  # unacknowledged for 2 s: again
    box.ack([1], rejected=[2])
    assert [f for f, _ in box.due()] == [3, 4]
    box.set_mapper_present(False)  # the mapper died: hold
    box.add(5, b"x")
    clock.t = 10.0
    assert box.due() == []
    box.set_mapper_present(True)  # a new mapper: everything in flight again at once, then the window
    assert [f for f, _ in box.due()] == [3, 4]
    box.ack([3, 4, 77])  # 77: unknown (acknowledged before), ignored
    assert [f for f, _ in box.due()] == [5]
    box.ack([5])
    assert box.pending == 0
    assert box.counts == {"sent": 6, "resent": 4, "acked": 5, "rejected": 1, "dropped": 0}


# ----------------------------------------------------------------------------- mapper


class FakeSession:
    """Records puts (the mapper's acknowledgements and maps)."""

    def __init__(self):
        self.puts = []

    def put(self, key, data, encoding=None):
        self.puts.append((key, protocol.unpack(data)))

    def acks(self):
        out = [protocol.KeyframeAck.from_msg(m) for k, m in self.puts if k.endswith("/" + keys.KEYFRAMES_ACK)]
        self.puts = [p for p in self.puts if not p[0].endswith("/" + keys.KEYFRAMES_ACK)]
        return out


def room_keyframe(i, sensor="depth"):
    """A camera in a 4 m box room, turning: enough structure for the Atlanta step."""
    H, W = 30, 40
    K = np.array([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])
    a = 0.3 * i
    T = np.eye(4)
    T[:3, :3] = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    v, u = np.mgrid[0:H, 0:W]
    dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1) @ T[:3, :3].T
    with np.errstate(divide="ignore"):
        t = np.min(np.where(np.abs(dirs) > 1e-9, 2.0 / np.abs(dirs), np.inf), axis=-1)  # box |x|,|y|,|z| <= 2
    return protocol.pack(protocol.Keyframe(i, float(i), t.astype(np.float32), K, T, sensor=sensor).to_msg())


def node_in(tmp_path, **kw):
    cfg = MapperConfig(preset="cpu", training={"network": {"width": 16}}, checkpoint_dir=tmp_path, **kw)
    return MapperNode(cfg, session=FakeSession())


def test_mapper_deduplicates_and_acknowledges(tmp_path):
    node = node_in(tmp_path, queue_max=3)
    s = node.session
    for i in range(4):
        node.on_keyframe(room_keyframe(i))
    assert node.counts["dropped"] == 1 and s.acks() == []  # 0 was dropped: never acknowledged
    node._add_pending()
    (ack,) = s.acks()
    assert (ack.sensor, ack.frame_ids, ack.rejected, ack.epoch) == ("depth", [1, 2, 3], [], node.epoch)
    node.on_keyframe(room_keyframe(2))  # in the map already: acknowledged at once, not queued
    assert [a.frame_ids for a in s.acks()] == [[2]] and not node.pending
    node.on_keyframe(room_keyframe(4))
    node.on_keyframe(room_keyframe(4))  # a resend waiting with its original
    node.on_keyframe(room_keyframe(0))  # the dropped one, resent
    bad = protocol.Keyframe.from_msg(protocol.unpack(room_keyframe(9))).to_msg()
    bad["T_WC"] = protocol.encode_array(np.diag([2.0, 2, 2, 1]), "<f8")
    node.on_keyframe(protocol.pack(bad))  # invalid: rejected for good, at once
    assert [(a.sensor, a.frame_ids, a.rejected) for a in s.acks()] == [("depth", [], [9])]
    node._add_pending()
    assert [(a.sensor, a.frame_ids) for a in s.acks()] == [("depth", [4, 4, 0])]
    assert node.pipeline.n_keyframes == 5 and node.seen == {("depth", i) for i in range(5)}
    assert node.counts == {"received": 9, "rejected": 1, "dropped": 1, "accepted": 5, "duplicates": 2}
    # Keyframes are identified by (sensor, frame_id) (protocol 1.3): another sensor's frame 3
    # is a different keyframe, acknowledged and seen; the same again is a duplicate. (It has
    # depth frame 3's pose and pixels: it adds nothing new, so since 1.10 it is not stored.)
    node.on_keyframe(room_keyframe(3, sensor="left"))
    node._add_pending()
    assert [(a.sensor, a.frame_ids, a.rejected) for a in s.acks()] == [("left", [3], [])]
    assert ("left", 3) in node.seen and node.pipeline.n_keyframes == 5
    assert node.pipeline.stats()["redundant"] == 1
    node.on_keyframe(room_keyframe(3, sensor="left"))
    assert [(a.sensor, a.frame_ids) for a in s.acks()] == [("left", [3])] and node.counts["duplicates"] == 3
    print("mapper counts:", node.counts)


def test_dedup_and_versions_survive_a_crash(tmp_path):
    node = node_in(tmp_path)
    for i in range(3):
        node.on_keyframe(room_keyframe(i))
    node._add_pending()
    node.pipeline.step()
    node._publish()
    node.save_checkpoint()  # 0..2 in the checkpoint
    assert not (tmp_path / JOURNAL_NAME).exists()
    node.on_keyframe(room_keyframe(3))
    node._add_pending()  # 3 only in the journal
    for _ in range(3):
        node._publish()
    epoch1, published = node.epoch, node.version
    maps = [m for k, m in node.session.puts if k.endswith("map/index")]  # one per publication
    assert [m["epoch"] for m in maps] == [epoch1] * 4 and [m["version"] for m in maps] == [1, 2, 3, 4]
    assert (tmp_path / JOURNAL_NAME).stat().st_size > 0
    node.dir_lock.release()  # killed (its lock on the directory goes with the process):
    del node  # no checkpoint written after the journal

    again = node_in(tmp_path)  # checkpoint (0..2) + journal (3)
    assert again.pipeline.n_keyframes == 4 and again.seen == {("depth", i) for i in range(4)}
    assert again.epoch > epoch1 and again.version == published
    for i in range(5):  # every resend is acknowledged, none added twice
        again.on_keyframe(room_keyframe(i))
    again._add_pending()
    assert again.pipeline.n_keyframes == 5 and again.counts["duplicates"] == 4 and again.counts["accepted"] == 1
    again._publish()
    (m,) = [m for k, m in again.session.puts if k.endswith("map/index")]
    assert m["version"] == published + 1 and m["epoch"] == again.epoch
    print(f"epochs {epoch1} -> {again.epoch}; versions ..{published} -> {m['version']}")
    # A torn journal record (a crash mid-append) is ignored.
    again.journal.close()
    with open(tmp_path / JOURNAL_NAME, "ab") as f:
        f.write(b"\xff\xff\x00\x00partial")
    again.dir_lock.release()
    third = node_in(tmp_path)
    assert third.pipeline.n_keyframes == 5 and third.epoch > again.epoch


def test_a_keyframe_is_on_disk_before_it_is_acknowledged(tmp_path, monkeypatch):
    """The journal's promise: the record of every acknowledged keyframe was fsync'd first (a
    power cut after the acknowledgement loses nothing the frontend stopped resending)."""
    import os

    from aisdf_mapper import journal

    events = []
    real_fsync = os.fsync

    def fsync(fd):
        events.append(("fsync", os.fstat(fd).st_size))
        real_fsync(fd)

    monkeypatch.setattr(journal.os, "fsync", fsync)
    node = node_in(tmp_path)
    put = node.session.put

    def put_and_record(key, data, encoding=None):
        if key.endswith("/" + keys.KEYFRAMES_ACK):
            events.append(("ack", (tmp_path / JOURNAL_NAME).stat().st_size))
        put(key, data, encoding)

    node.session.put = put_and_record
    for i in range(3):
        node.on_keyframe(room_keyframe(i))
    node._add_pending()
    assert [a.frame_ids for a in node.session.acks()] == [[0, 1, 2]]
    # three records, each fsync'd, then one acknowledgement of the whole file's contents
    assert [e[0] for e in events] == ["fsync"] * 3 + ["ack"]
    sizes = [e[1] for e in events]
    assert sizes[0] < sizes[1] < sizes[2] == sizes[3]


# ----------------------------------------------------------------------------- protocol 1.2 on the wire


def test_keyframe_ack_round_trip_and_validation():
    a = protocol.KeyframeAck(1764000000000, "left", [1, 2], [7])
    b = protocol.KeyframeAck.from_msg(protocol.unpack(protocol.pack(a.to_msg())))
    assert b == a
    assert protocol.KeyframeAck.from_msg({"v": 1, "frame_ids": [3]}) == protocol.KeyframeAck(0, "depth", [3], [])
    for bad in ({"v": 1, "frame_ids": "3"}, {"v": 1, "frame_ids": [1.5]}, {"v": 1, "rejected": [True]},
                {"v": 1, "epoch": "x"}):
        with pytest.raises(protocol.ProtocolError):
            protocol.KeyframeAck.from_msg(bad)


def test_old_v1_maps_without_epoch_still_decode():
    """A 1.0 sender's WeightSnapshot and SurfelMap (no epoch, no unknown keys) decode with
    epoch 0; an unknown key from a newer sender is ignored."""
    arr = lambda a, dt: {"dtype": dt, "shape": list(np.shape(a)), "data": np.asarray(a, dt).tobytes()}  # noqa: E731
    ws = {"v": 1, "version": 5, "step": 10, "stamp": 1.0, "model": {"width": 4},
          "state": {"w": arr(np.ones((2, 2)), "<f4")}}
    snap = protocol.WeightSnapshot.from_msg(protocol.unpack(msgpack.packb(ws)))
    assert (snap.version, snap.epoch) == (5, 0) and "epoch" not in snap.to_msg()
    later = protocol.WeightSnapshot.from_msg({**ws, "epoch": 7, "from_the_future": [1]})
    assert later.epoch == 7 and later.to_msg()["epoch"] == 7
    sm = {"v": 1, "version": 3, "stamp": 2.0,
          "atlanta": {"vertical": arr([0, 0, 1], "<f8"), "horizontal": arr(np.eye(3)[:2], "<f8")},
          "surfels": {k: arr(np.zeros((0, 3) if k in ("center", "normal", "axis1", "axis2") else (0, 2)
                                      if k == "extent" else (0,)), dt)
                      for k, dt in (("center", "<f4"), ("normal", "<f4"), ("axis1", "<f4"), ("axis2", "<f4"),
                                    ("extent", "<f4"), ("direction", "<i4"), ("keyframe", "<i8"))}}
    smap = protocol.SurfelMap.from_msg(protocol.unpack(msgpack.packb(sm)))
    assert (smap.version, smap.epoch) == (3, 0)
