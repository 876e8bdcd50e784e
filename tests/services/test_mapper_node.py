"""The mapper service's keyframe intake: validation, bounded queue, counters (no Zenoh needed)."""

import numpy as np

from aisdf import protocol
from aisdf_mapper.config import MapperConfig
from aisdf_mapper.main import MapperNode


def payload(i, T=None):
    d = np.full((30, 40), 2.0, np.float32)
    K = np.array([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])
    return protocol.pack(protocol.Keyframe(i, float(i), d, K, np.eye(4) if T is None else T).to_msg())


def test_queue_is_bounded_and_bad_keyframes_are_counted():
    node = MapperNode(MapperConfig(queue_max=2, preset="cpu"), session=None)
    for i in range(5):
        node.on_keyframe(payload(i))
    node.on_keyframe(b"\x00garbage")
    node.on_keyframe(payload(9, np.diag([1.0, 1, 2, 1])))
    assert [k.frame_id for k, _ in node.pending] == [3, 4]
    assert node.counts == {"received": 7, "rejected": 2, "dropped": 3, "accepted": 0, "duplicates": 0}
    assert node.pipeline.n_keyframes == 0  # nothing reached the map


def test_measured_setting_reaches_both_mappers():
    """``measured`` (default on): both mappers pool measured points (1.4 with submaps, 1.5 with
    one network); off, neither does; ``submap.measured: false`` turns off the submaps' as in 1.4."""
    def pooled(**kw):
        return MapperNode(MapperConfig(preset="cpu", **kw), session=None).pipeline.measured is not None

    assert pooled() and pooled(mapper="single")
    assert not pooled(measured=False) and not pooled(mapper="single", measured=False)
    assert not pooled(submap={"measured": False}) and pooled(mapper="single", submap={"measured": False})


class _Puts:
    """A stand-in for the Zenoh session: records what the node puts."""

    def __init__(self):
        self.puts = []

    def put(self, key, data, encoding=None):
        self.puts.append((key, bytes(data)))


def test_one_network_service_publishes_and_checkpoints_its_measured_points(tmp_path):
    """Protocol 1.5 through the mapper service's own path (no Zenoh): keyframes in as payloads,
    ``map/weights`` out with the measured points of every keyframe; a restarted mapper resumes
    the same points from its checkpoint and journal."""
    from aisdf.structure.measured import MeasuredSurface
    from aisdf.synthetic import SyntheticSequence

    seq = SyntheticSequence(building="atlanta", n_frames=60, H=30, W=40, seed=1)
    cfg = MapperConfig(preset="cpu", mapper="single", checkpoint_dir=tmp_path, namespace="t",
                       training={"network": {"width": 16}, "n_rays": 10})
    node = MapperNode(cfg, session=_Puts())
    own = MeasuredSurface(max_depth=node.pipeline.cfg.max_depth)
    for i in (0, 20, 40):
        f = seq.frame(i)
        node.on_keyframe(protocol.pack(protocol.Keyframe(f["frame_id"], f["stamp"], f["depth"], f["K"],
                                                         f["T_WC"]).to_msg()))
        own.add(f["depth"], f["K"], f["T_WC"])
    node._add_pending()
    node.pipeline.step()
    node._publish()
    weights = [d for k, d in node.session.puts if k == "t/map/weights"]
    snap = protocol.WeightSnapshot.from_msg(protocol.unpack(weights[-1]))
    assert snap.measured is not None and len(snap.measured["points"]) > 100
    np.testing.assert_array_equal(snap.measured["points"], own.points().astype(np.float32))
    node.save_checkpoint()
    f = seq.frame(50)  # after the checkpoint: journaled, replayed on restart
    node.on_keyframe(protocol.pack(protocol.Keyframe(f["frame_id"], f["stamp"], f["depth"], f["K"],
                                                     f["T_WC"]).to_msg()))
    node._add_pending()
    own.add(f["depth"], f["K"], f["T_WC"])
    node.dir_lock.release()  # its process gone
    again = MapperNode(cfg, session=_Puts())
    assert again.pipeline.n_keyframes == 4
    np.testing.assert_array_equal(again.pipeline.measured_points(), own.points().astype(np.float32))
