"""Following map -> odom corrections (protocol 1.11, aisdf.ros.follow): keyframes placed
through map -> odom -> base -> camera are re-posed when map -> odom at their stamps changes
(or, in ``latest`` mode, when the newest one does), beyond 1 cm or 0.5 degrees; and the front
end's live loop hands the corrected poses to its sender."""

import threading

import numpy as np

from aisdf.ros.follow import MapOdomFollower
from aisdf.ros.tf import TFBuffer

S = 1_000_000_000


def pose(x=0.0, y=0.0, yaw_deg=0.0):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [x, y, 0.0]
    return T


def buffer(map_odom):
    tf = TFBuffer(cache_s=None)
    cam = np.eye(4)
    cam[:3, 3] = [0.1, 0.0, 0.5]
    tf.set_transform("base", "camera", 0, cam, static=True)
    for t in range(0, 11):
        tf.set_transform("odom", "base", t * S, pose(0.5 * t, 0.1 * t, 3.0 * t))
        tf.set_transform("map", "odom", t * S, map_odom(t))
    return tf


def test_keyframes_follow_map_to_odom_at_their_stamps():
    tf = buffer(lambda t: pose(0.01 * t))
    f = MapOdomFollower(tf, "map", "odom")
    for t in (2, 4, 6):
        assert f.track(t, t * S, tf.lookup("map", "camera", t * S))
    assert f.poll(force=True) == {}  # nothing moved
    # the SLAM system re-optimised its trajectory: map -> odom of the past stamps changes
    for t in range(0, 11):
        tf.set_transform("map", "odom", t * S, pose(0.01 * t + (0.3 if t >= 4 else 0.004), 0.0, 2.0 if t >= 4 else 0))
    got = f.poll(force=True)
    assert set(got) == {4, 6}  # keyframe 2's map -> odom moved 4 mm only: under 1 cm and 0.5 degrees
    for t in (4, 6):
        np.testing.assert_allclose(got[t], tf.lookup("map", "camera", t * S), atol=1e-9)
    assert f.poll(force=True) == {}  # corrected once; the held poses are the new ones
    assert f.counts == {"followed": 3, "untracked": 0, "corrected": 2, "batches": 1}
    assert f.poll() == {} and f.poll(now=1e12) == {}  # at most once a period


def test_latest_mode_applies_the_newest_correction_and_bounds_what_it_keeps():
    tf = buffer(lambda t: np.eye(4))
    f = MapOdomFollower(tf, "map", "odom", mode="latest", max_keyframes=2)
    for t in (2, 4, 6):
        f.track(t, t * S, tf.lookup("map", "camera", t * S))
    assert list(f.kept) == [4, 6]  # the newest two
    tf.set_transform("map", "odom", 11 * S, pose(0.0, 0.2, 1.0))  # a loop closure, now
    got = f.poll(force=True)
    assert set(got) == {4, 6}
    np.testing.assert_allclose(got[4], pose(0.0, 0.2, 1.0) @ tf.lookup("odom", "camera", 4 * S), atol=1e-9)


def test_untracked_without_an_odom_frame():
    tf = buffer(lambda t: np.eye(4))
    f = MapOdomFollower(tf, "map", "odom_missing")
    assert not f.track(1, S, np.eye(4)) and f.counts["untracked"] == 1 and f.poll(force=True) == {}


def test_the_live_loop_sends_the_corrections():
    from aisdf_frontend.config import FrontendConfig
    from aisdf_frontend.main import stream_live
    from aisdf.keyframes import KeyframeSelector
    from aisdf.synthetic import SyntheticSequence

    seq = SyntheticSequence(building="office", n_frames=40, H=30, W=40, seed=0)
    tf = buffer(lambda t: np.eye(4))

    class Live:
        live, counts = True, {"images": 0, "frames": 0, "skipped": 0, "skipped_reasons": {}, "topics": {}}
        follower = MapOdomFollower(tf, "map", "odom", period_s=0.0)

        def frames(self, stop):
            for i in range(0, 40, 4):
                fr = dict(seq.frame(i))
                fr["frame_id"], fr["stamp"] = i, i / 4.0
                if i == 20:  # half way: the SLAM system re-optimises the past
                    for t in range(0, 11):
                        tf.set_transform("map", "odom", t * S, pose(0.25, 0.0, 0.0))
                yield fr

        def close(self):
            pass

    sent, corrected = [], []
    cfg = FrontendConfig()
    stream_live(cfg, Live(), KeyframeSelector(cfg.keyframes), sent.append, threading.Event(), {}, corrected.append)
    assert sent and corrected
    ids = sorted(i for batch in corrected for i in batch)
    sent_ids = [m["frame_id"] for m in sent]
    assert ids and set(ids) <= set(sent_ids) and all(i < 20 for i in ids)
    np.testing.assert_allclose(corrected[0][ids[0]][:3, 3] - seq.frame(ids[0])["T_WC"][:3, 3], [0.25, 0, 0],
                               atol=1e-9)
