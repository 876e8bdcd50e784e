"""The mapper interface (``aisdf.mapper.Mapper``): one test of what the mapper service relies
on, run against both implementations through the interface alone, and a check that the
service uses nothing else."""

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from aisdf import keys, protocol
from aisdf.mapper import MAPPER_KINDS, Mapper
from aisdf.mapper.factory import make_mapper, restore_mapper
from aisdf.synthetic import SyntheticSequence

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[2]
SMALL = {"network": {"width": 32}, "n_rays": 20}


@pytest.fixture(scope="module")
def seq():
    return SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)


def wire(seq, i, u2=False) -> protocol.Keyframe:
    f = seq.frame(i)
    depth = np.asarray(f["depth"], np.float32)
    scale = None
    if u2:
        depth, scale = np.clip(np.round(np.nan_to_num(depth) * 1000), 0, 65535).astype(np.uint16), 1000.0
    return protocol.Keyframe(f["frame_id"], f["stamp"], depth, f["K"], f["T_WC"], scale, "cam")


def interface_names() -> set[str]:
    return {n for n in dir(Mapper) if not n.startswith("_")} | set(Mapper.__annotations__)


@pytest.mark.parametrize("kind", MAPPER_KINDS)
def test_both_mappers_do_what_the_service_relies_on(seq, kind):
    m = make_mapper(kind, "cpu", SMALL, submaps={"cell_m": 3.0})
    assert isinstance(m, Mapper) and m.kind == kind and m.atlanta_on
    assert not m.ready and m.n_keyframes == 0 and m.steps == 0
    assert m.map_messages(1) == [] or kind == "single"  # a submap map has nothing before its grid

    for i in range(0, 120, 20):
        m.add_keyframe(wire(seq, i, u2=i % 40 == 0))
    assert m.n_keyframes == 6 and m.ready
    assert m.keyframe_keys() == [("cam", i) for i in range(0, 120, 20)]

    # A bad keyframe changes nothing: too few valid pixels, or one already in the map.
    before = (m.n_keyframes, len(m.observed), m.measured_points().copy())
    empty = wire(seq, 110)
    empty.depth = np.zeros_like(empty.depth)
    with pytest.raises(ValueError, match="valid depth"):
        m.add_keyframe(empty)
    with pytest.raises(ValueError, match="already in the map"):
        m.add_keyframe(wire(seq, 20))
    assert (m.n_keyframes, len(m.observed)) == before[:2]
    np.testing.assert_array_equal(m.measured_points(), before[2])

    for _ in range(12):
        info = m.step()
        assert np.isfinite(info["loss"])
    assert m.steps == 12
    stats = m.stats()
    assert {"step_wall", "observed", "measured", "dropped_keyframes"} <= set(stats)

    pts = seq.poses[0][:3, 3] + np.random.default_rng(0).uniform(-1, 1, (200, 3))
    f = m.sdf(pts)
    assert f.shape == (200,) and np.all(np.isfinite(f))
    s = m.surfels()
    assert s is not None and len(s) > 0
    measured = m.measured_points()
    assert measured.ndim == 2 and measured.shape[1] == 3 and len(measured) > 100
    assert m.measured is not None and len(m.measured) > 0

    msgs = dict(m.map_messages(7, changed_only=False, epoch=3))
    assert keys.MAP_SURFELS in msgs
    weights = [k for k in msgs if k == keys.MAP_WEIGHTS or k.startswith(keys.MAP_SUBMAPS + "/")]
    assert weights and (kind == "submaps") == (keys.MAP_INDEX in msgs)
    for k in weights:
        snap = protocol.WeightSnapshot.from_msg(protocol.unpack(msgs[k]))
        assert (snap.version, snap.epoch) == (7, 3) and len(snap.measured["points"]) > 0
    smap = m.surfel_map(7)
    assert smap.version == 7 and len(smap.surfels["center"]) == len(s)
    mem = m.memory()
    assert set(mem) == {"keyframes", "model", "observed", "measured"} and min(mem.values()) > 0

    # A checkpoint resumes the same map, of the same kind, and trains on identically.
    back = restore_mapper(m.checkpoint())
    assert type(back) is type(m) and back.kind == kind
    assert (back.steps, back.n_keyframes, back.keyframe_keys()) == (m.steps, m.n_keyframes, m.keyframe_keys())
    np.testing.assert_array_equal(back.sdf(pts), f)
    np.testing.assert_array_equal(back.measured_points(), measured)
    m.step()
    back.step()
    np.testing.assert_array_equal(back.sdf(pts), m.sdf(pts))
    assert "mapper" not in m.describe() or kind in m.describe()


def test_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="unknown mapper"):
        make_mapper("octree")


def test_the_mapper_service_uses_only_the_interface():
    """Every attribute the service reads of its mapper (``self.pipeline.X``, ``node.pipeline.X``)
    is declared by ``Mapper``."""
    tree = ast.parse((ROOT / "services" / "mapper" / "main.py").read_text())
    used = {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Attribute) and node.value.attr == "pipeline"}
    assert used, "the service's mapper is no longer self.pipeline: update this test"
    assert used <= interface_names(), used - interface_names()
