"""``torchir bench restir_antithetic``: its summary and claims from results (fast), and the quick
run end to end (slow: it compiles every method's kernels)."""
from __future__ import annotations

import json

import pytest

from torchir.bench import claims, restir_antithetic


def _results(errors: dict[str, float]) -> dict:
    methods = {name: {"seconds_per_step": 0.1, "relative_error": e, "raw_relative_error": e, "bias": 0.0,
                      "equal_time_error": e} for name, e in errors.items()}
    return {"resolution": 8, "scored_pixels": 3, "reference_error": 0.01, "budget_seconds": 0.1, "methods": methods}


def test_summary_and_claims_compare_against_shared_reservoirs(tmp_path):
    errors = {name: 1.0 for name in restir_antithetic.METHODS}
    errors.update({"material, ReSTIR": 50.0, "material, ReSTIR, antithetic": 2.0, "material, ReSTIR, antithetic, shared": 1.0})
    res = _results(errors)
    text = restir_antithetic.summarize(res, restir_antithetic.parse_args(["--blind", "0.25"]))
    assert "| material, ReSTIR | 0.100 | 50.0000 | 50.0000 | 50.00 |" in text
    assert "light size 1.0, 0 dome lights, blind 0.25)" in text
    (tmp_path / "restir_antithetic").mkdir()
    (tmp_path / "restir_antithetic" / "results.json").write_text(json.dumps(res))
    rows = [line.rsplit("|", 3)[1:3] for line in claims.claims_table(tmp_path).splitlines() if line.startswith("| restir_antithetic")]
    assert rows == [[" 2x ", " NO "], [" 50x ", " yes "]]


@pytest.mark.slow
def test_quick_run_writes_its_tables_and_plots(tmp_path):
    res = restir_antithetic.main(["--quick", "--resolution", "24", "--steps", "2", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert set(saved["methods"]) == set(restir_antithetic.METHODS)
    assert saved["scored_pixels"] > 0 and all(r["relative_error"] >= 0 for r in res["methods"].values())
    for name in ("summary.md", "antithetic.png", "derivative_images.png"):
        assert (tmp_path / name).stat().st_size > 0
