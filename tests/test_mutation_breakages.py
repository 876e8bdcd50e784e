"""``make mutation``'s breakages still apply to the code as it is: each one's text occurs exactly
once in its file (else the check stops there) and each names tests that exist."""

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _check():
    spec = importlib.util.spec_from_file_location("run_mutation_check", ROOT / "tests" / "run_mutation_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, mod)  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_every_breakage_applies_once_and_names_existing_tests():
    check = _check()
    bad = []
    for b in check.BREAKAGES:
        if why := check.stale(ROOT, b):
            bad.append(why)
        for t in b.tests:
            if not (ROOT / t.split("::")[0]).exists():
                bad.append(f"{b.name}: no test file {t}")
    assert not bad, bad
