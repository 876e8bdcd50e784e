"""The services' malloc settings (``aisdf.memory``): on glibc, arenas capped and freed memory
handed back."""

import sys

import numpy as np
import pytest

from aisdf.memory import cap_arenas, trim


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and malloc_trim")
def test_arenas_cap_and_trim_take_effect_on_glibc():
    assert cap_arenas(2) is True
    junk = [np.ones(300_000) for _ in range(50)]  # 120 MB in many blocks, then freed
    del junk
    assert isinstance(trim(), bool)
