"""Fixtures of the query tests: the submap map (tests/helpers/submap_map.py), built once for
the folder's tests that use it (it takes a few seconds to fit)."""

import pytest

from helpers.submap_map import make_submap_map


@pytest.fixture(scope="package")
def submap_map():
    return make_submap_map()
