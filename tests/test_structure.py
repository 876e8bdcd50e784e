"""The structure step on the synthetic buildings (tilted world frames, Kinect-like noise):
the Atlanta frame against the buildings' truth, and the global surfel map."""

import numpy as np
import pytest

from aisdf.mapping.frames import Frame
from aisdf.structure import Structure
from aisdf.synthetic import SyntheticSequence
from aisdf_frontend.keyframes import KeyframeSelector


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
