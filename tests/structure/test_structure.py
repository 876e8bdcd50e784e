"""The structure step on the synthetic buildings (tilted world frames, Kinect-like noise):
the Atlanta frame against the buildings' truth, and the global surfel map."""

import numpy as np
import pytest

from aisdf.mapping.frames import Frame
from aisdf.structure import Structure
from aisdf.synthetic import SyntheticSequence
from aisdf.keyframes import KeyframeSelector


def angle_deg(a, b):
    return float(np.degrees(np.arccos(np.clip(abs(a @ b), 0, 1))))


@pytest.mark.parametrize("building, seed", [("atlanta", 0), ("office", 1)])
def test_atlanta_frame_and_global_map_on_synthetic_buildings(building, seed):
    seq = SyntheticSequence(building=building, n_frames=1200, seed=seed)
    assert angle_deg(seq.scene.up_W, np.array([0, 0, 1.0])) > 10  # the world is tilted
    sel, st = KeyframeSelector(), Structure(seed=seed)
    for i in range(0, len(seq), 2):
        f = seq.frame(i)
        if sel.is_keyframe(f["stamp"], f["depth"], f["K"], f["T_WC"]):
            st.process(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
    af = st.atlanta_frame()
    v, walls = seq.scene.atlanta_truth(include_solids=False)
    _, every = seq.scene.atlanta_truth(include_solids=True)
    assert angle_deg(af.vertical, v) < 1.0
    for w in walls:  # every wall direction found
        assert min(angle_deg(h, w) for h in af.horizontal) < 2.0
    for h in af.horizontal:  # nothing spurious: each estimate is a true direction
        assert min(angle_deg(h, w) for w in every) < 2.0
    s = st.global_surfels()
    assert st.map.n_produced >= 3 * len(s) > 0
    # Surfels lie on true planes: the centre's offset along its normal matches a true face.
    truth = seq.scene.planes_truth()
    ok = []
    for c, n in zip(s.center, s.normal):
        same = np.abs(truth.normal @ n) > np.cos(np.radians(2))
        off = np.abs((c - truth.center[same]) @ n)
        ok.append(off.size > 0 and off.min() < 0.02)
    assert np.mean(ok) > 0.9


def test_structure_uses_only_the_depth_the_mapper_trains_on():
    """Pixels beyond the mapper's ``max_depth`` (or non-finite) are invalid for training; they
    give no normals to the Atlanta frame and no surfels either (``geometry.valid_depth``, one
    rule for every consumer of a keyframe's depth). Same analytic room and frames, with and
    without the limit."""
    from helpers.atlanta_scene import atlanta_room, camera, trajectory

    from aisdf.geometry import transform, valid_depth
    from aisdf.mapper.single import MappingPipeline

    scene, K, H, W, max_depth = atlanta_room(0), camera(120), 120, 160, 2.5
    rng = np.random.default_rng(0)
    frames = []
    for i, T in enumerate(trajectory(scene, 12, 0)):
        d = scene.render(T, K, H, W, rng).astype(np.float32)
        d[:4, :4] = np.nan  # non-finite pixels are invalid whatever the limit
        frames.append((i, d, T))
    assert valid_depth(np.array([np.nan, np.inf, -1.0, 0.0, 1.0, 2.5, 2.6]), 2.5).tolist() == [
        False, False, False, False, True, True, False]
    far = np.mean([np.mean(d[np.isfinite(d)] > max_depth) for _, d, _ in frames])
    assert far > 0.2  # the room reaches beyond the limit in a good share of the pixels

    limited, unlimited = Structure(seed=0, max_depth=max_depth), Structure(seed=0)
    beyond = {"limited": 0, "unlimited": 0}
    for i, d, T in frames:
        for name, st in (("limited", limited), ("unlimited", unlimited)):
            f = Frame(i, float(i), d, K, T)
            st.process(f)
            if f.surfel_mask is not None:
                assert not (f.surfel_mask & ~np.isfinite(d)).any()
                beyond[name] += int((f.surfel_mask & (d > max_depth)).sum())
            if f.surfels is not None and len(f.surfels):
                z_C = transform(np.linalg.inv(T), f.surfels.center)[:, 2]
                if name == "limited":
                    assert z_C.max() <= max_depth + 0.05
    assert beyond["unlimited"] > 0 and beyond["limited"] == 0  # the limit is what keeps them out

    # The pipeline gives its structure the training's limit, and its map's bounds use the same rule.
    reach = max_depth * np.linalg.norm([80 / K[0, 0], 60 / K[1, 1], 1])  # the longest valid ray
    cams = np.array([T[:3, 3] for _, _, T in frames])
    overshoot = {}
    for limit in (max_depth, 12.0):
        pipe = MappingPipeline.from_settings("cpu", training={"max_depth": limit})
        assert pipe.structure.max_depth == limit
        for i, d, T in frames:
            pipe.add_keyframe(Frame(i, float(i), d, K, T))
        lo, hi = pipe.intake.bounds
        overshoot[limit] = float(np.max(np.r_[cams.min(0) - lo, hi - cams.max(0)]))
    assert overshoot[max_depth] <= reach + 1e-6 < overshoot[12.0]
