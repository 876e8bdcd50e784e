"""Modules the tests of several folders import (tests/conftest.py puts tests/ on sys.path)."""
