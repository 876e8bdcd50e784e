"""The mapper service with a parked robot (no Zenoh needed): every keyframe is acknowledged and
counts as seen, a resend is acknowledged again, few are stored; a bad mask is rejected."""

import numpy as np

from aisdf import protocol
from aisdf.synthetic import SyntheticSequence
from aisdf.synthetic.render import render_depth
from aisdf_mapper.config import MapperConfig
from aisdf_mapper.main import MapperNode


class _Acks(MapperNode):
    """Records the node's acknowledgements instead of putting them."""

    def _ack(self, sensor, frame_ids=(), rejected=()):
        self.acks = getattr(self, "acks", [])
        self.acks.append((sensor, list(frame_ids), list(rejected)))


def test_parked_keyframes_are_all_acknowledged_and_few_stored(tmp_path):
    seq = SyntheticSequence(building="atlanta", n_frames=60, H=45, W=60, seed=1)
    f = seq.frame(10)
    cfg = MapperConfig(preset="cpu", namespace="t", checkpoint_dir=tmp_path,
                       training={"network": {"width": 16}, "n_rays": 10})
    node = _Acks(cfg, session=None)
    payloads = []
    for i in range(60):
        d = render_depth(seq.scene, f["T_WC"], seq.K, seq.H, seq.W, seq.noise, (seq.seed, 500 + i))
        payloads.append(protocol.pack(protocol.Keyframe(i, 5.0 * i, d, f["K"], f["T_WC"], sensor="cam").to_msg()))
    for start in range(0, 60, 10):  # as a frontend's send window delivers them
        for p in payloads[start:start + 10]:
            node.on_keyframe(p)
        node._add_pending()
    acked = sorted(i for s, ids, _ in node.acks if s == "cam" for i in ids)
    assert acked == list(range(60)) and not any(r for _, _, r in node.acks)
    assert all(node.is_seen("cam", i) for i in range(60))
    info = node.info()
    assert info["accepted"] == 60 and info["seen"] == 60 and info["rejected"] == 0
    assert 1 <= info["keyframes"] <= 5 and info["stats"]["redundant"] == 60 - info["keyframes"]
    node.acks.clear()
    node.on_keyframe(payloads[30])  # a resend of a redundant keyframe: acknowledged, not judged again
    node._add_pending()
    assert node.acks == [("cam", [30], [])] and node.counts["duplicates"] == 1
    assert node.info()["stats"]["redundant"] == 60 - info["keyframes"]
    node.save_checkpoint()
    node.dir_lock.release()  # its process gone
    again = _Acks(cfg, session=None)  # resumed: still seen, still not stored
    assert all(again.is_seen("cam", i) for i in range(60)) and again.pipeline.n_keyframes == info["keyframes"]

    # A keyframe whose mask does not fit its depth: rejected for good, the map untouched.
    msg = protocol.Keyframe(99, 1.0, f["depth"], f["K"], f["T_WC"], sensor="cam").to_msg()
    msg["mask"] = protocol.encode_array(np.zeros((3, 3), np.uint8))
    n = again.pipeline.n_keyframes
    again.acks = []
    again.on_keyframe(protocol.pack(msg))
    assert again.acks == [("cam", [], [99])] and again.counts["rejected"] == 1 and not again.pending
    assert again.pipeline.n_keyframes == n and not again.is_seen("cam", 99)
