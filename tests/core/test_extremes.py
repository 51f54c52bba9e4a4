"""The extremes matrix (torchir.extremes): each case gives a finite result or its clear error."""
from __future__ import annotations

import pytest

from torchir.extremes import CASES, FINITE, _context, run_case


@pytest.fixture(scope="module")
def context():
    return _context()


@pytest.mark.parametrize("case", CASES, ids=[f"{c.piece}: {c.condition}" for c in CASES])
def test_extreme_case(case, context):
    ok, outcome = run_case(case, context)
    expected = FINITE if case.expect is FINITE else f"{case.expect.__name__} containing {case.match!r}"
    assert ok, f"{case.piece} / {case.condition}: expected {expected}, got {outcome}"
