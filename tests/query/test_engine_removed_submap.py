"""Protocol 1.11: a submap the mapper removed (a pose correction left it without keyframes)
is not listed in the next index; the query service drops it once an index at least as new as
its snapshot leaves it out, and answers from the others. An older index changes nothing."""

import numpy as np

from aisdf import query_messages
from helpers.submap_map import CELLS, band_points, engine_of, index


def test_an_index_without_a_held_submap_drops_it(submap_map):
    m = submap_map
    e = engine_of(m)
    gone = CELLS[2]
    keep = {c: 1 for c in CELLS if c != gone}
    pts = band_points(m, 500, np.random.default_rng(0))
    inside = m["grid"].inside(gone, pts)
    assert inside.any()
    before = e.answer_sdf(query_messages.SdfRequest(pts, source="implicit", observed=True))
    # an index older than the snapshot (version 1) cannot remove it
    assert e.set_index(index(m["grid"], keep, 0)) == [] and gone in e.state.submaps.submaps
    assert e.set_index(index(m["grid"], keep, 3)) == []
    assert set(e.state.submaps.submaps) == set(keep) and e.state.version == 3
    after = e.answer_sdf(query_messages.SdfRequest(pts, source="implicit", observed=True))
    assert after.map_version == 3
    far = ~m["grid"].inside(gone, pts, grow=1.5)  # beyond the removed submap's blend: the same answers
    np.testing.assert_allclose(after.sdf[far], before.sdf[far], atol=1e-5)
    assert not np.allclose(after.sdf[inside], before.sdf[inside], atol=1e-3)
    assert after.observed[inside].sum() < before.observed[inside].sum()  # its observed space went with it
