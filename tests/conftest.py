"""The test suite's layout: tests/<folder>/ mirrors the package (shared/aisdf/<folder>/, the
services in tests/services/, the end-to-end tests that start real services in tests/e2e/).
Test files are imported with ``--import-mode=importlib`` (pyproject.toml), so no folder needs
an ``__init__.py`` and two folders may hold files of the same name.

Modules shared by tests in several folders live in tests/ (``stranger_client``, the
stranger's client) and in tests/helpers/ (``from helpers.small_map import ...``): tests/ is
put on sys.path here, for every folder."""

import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

# Plain asserts in the helpers report their values as the tests' own do.
pytest.register_assert_rewrite("helpers")
