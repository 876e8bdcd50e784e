"""A small trained map of the synthetic Atlanta building (a 32-wide network, 6 keyframes,
5 steps each), shared by the baked-field tests and the query service's end-to-end tests."""

from aisdf.mapping.frames import Frame
from aisdf.pipeline import MappingPipeline
from aisdf.synthetic import SyntheticSequence


def train_small_map():
    """(sequence, the keyframes' frame dicts, the trained MappingPipeline)."""
    seq = SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)
    p = MappingPipeline.from_settings("cpu", {"network": {"width": 32}, "n_rays": 20})
    frames = []
    for i in range(0, 120, 20):
        f = seq.frame(i)
        frames.append(f)
        p.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        for _ in range(5):
            p.step()
    return seq, frames, p
