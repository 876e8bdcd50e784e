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

    assert pooled() and pooled(submaps=False)
    assert not pooled(measured=False) and not pooled(submaps=False, measured=False)
    assert not pooled(submap={"measured": False}) and pooled(submaps=False, submap={"measured": False})
