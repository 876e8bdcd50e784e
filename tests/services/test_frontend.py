"""Frontend: keyframe selection by motion and overlap; keyframe encoding."""

import numpy as np

from aisdf import geometry as g
from aisdf import protocol
from aisdf_frontend.config import FrontendConfig
from aisdf.keyframes import KeyframeConfig
from aisdf.keyframes import KeyframeSelector, overlap
from aisdf_frontend.main import stream, to_keyframe

K = g.intrinsics(60.0, 60.0, 39.5, 29.5)
WALL = np.full((60, 80), 2.0, np.float32)


def pose(x=0.0, yaw_deg=0.0):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[0, 3] = x
    return T


def test_overlap_of_shifted_views():
    assert overlap(WALL, K, pose(), WALL, K, pose()) == 1.0
    # Moving sideways by half the field of view at 2 m: about half the points stay in view.
    half = 2.0 * 40 / 60
    o = overlap(WALL, K, pose(half), WALL, K, pose())
    assert 0.4 < o < 0.6
    assert overlap(WALL, K, pose(10.0), WALL, K, pose()) == 0.0


def test_selector_reasons():
    sel = KeyframeSelector(KeyframeConfig(translation_m=0.3, rotation_deg=20, min_overlap=0.7, max_interval_s=5))
    assert sel.is_keyframe(0.0, WALL, K, pose()) and sel.last_reason == "first"
    assert not sel.is_keyframe(0.1, WALL, K, pose(0.1))
    assert sel.is_keyframe(0.2, WALL, K, pose(0.35)) and sel.last_reason == "translation"
    assert sel.is_keyframe(0.3, WALL, K, pose(0.35, 25)) and sel.last_reason == "rotation"
    assert sel.is_keyframe(5.4, WALL, K, pose(0.35, 25)) and sel.last_reason == "interval"
    sel2 = KeyframeSelector(KeyframeConfig(translation_m=5, rotation_deg=90, min_overlap=0.9))
    sel2.is_keyframe(0.0, WALL, K, pose())
    assert not sel2.is_keyframe(0.1, WALL, K, pose(0.2))  # overlap 1 - 0.2/2.67 = 0.93
    assert sel2.is_keyframe(0.2, WALL, K, pose(0.4)) and sel2.last_reason == "overlap"  # 0.85


def test_u2_keyframe_encoding_roundtrip():
    f = {"frame_id": 3, "stamp": 0.1, "depth": WALL, "K": K, "T_WC": pose()}
    kf = to_keyframe(f, FrontendConfig(depth_encoding="u2"))
    back = protocol.Keyframe.from_msg(protocol.unpack(protocol.pack(kf.to_msg())))
    assert back.depth.dtype == np.uint16 and back.depth_scale == 1000.0
    np.testing.assert_allclose(back.depth_m(), 2.0)


def test_stream_synthetic_as_fast_as_possible():
    import threading

    sent = []
    cfg = FrontendConfig(n_frames=60, realtime=False, width=80, height=60)
    counts = stream(cfg, sent.append, threading.Event())
    assert counts["frames"] == 60 and counts["keyframes"] == len(sent) >= 2
    kf = protocol.Keyframe.from_msg(protocol.unpack(protocol.pack(sent[0])))
    assert kf.depth.shape == (60, 80) and kf.frame_id == 0


def test_without_a_mapper_the_frontend_waits_drain_timeout_s_for_acknowledgements_then_ends():
    """The source done, what is held unacknowledged (no mapper ever came) is waited for
    ``drain_timeout_s``, no longer: the frontend ends with them counted as pending."""
    import threading
    import time

    from aisdf.config import ZenohOptions
    from aisdf.stack import endpoint, free_port
    from aisdf_frontend.main import main

    cfg = FrontendConfig(namespace="aisdf/draintest", n_frames=30, realtime=False, width=80, height=60,
                         drain_timeout_s=2.0,
                         zenoh=ZenohOptions(mode="peer", listen=[endpoint(free_port())], multicast_scouting=False))
    out, stop = {}, threading.Event()
    t0 = time.monotonic()
    th = threading.Thread(target=lambda: out.update(main(cfg, stop)), daemon=True)
    th.start()
    th.join(40.0)  # measured 2.6 s in all (the 2 s drain, 30 frames, a session): 40 s only if it never ends
    elapsed, ended = time.monotonic() - t0, not th.is_alive()
    stop.set()  # (a frontend that never ended stops here, so the test does)
    th.join(10.0)
    assert ended, "the frontend did not end after its drain timeout"
    assert out["done"] and out["keyframes"] >= 2
    assert elapsed >= cfg.drain_timeout_s  # it did wait for acknowledgements (none came)
