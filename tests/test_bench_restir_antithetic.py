"""``torchir bench restir_antithetic --quick`` end to end (slow: it compiles every method's kernels)."""
from __future__ import annotations

import json

import pytest

from torchir.bench import restir_antithetic


@pytest.mark.slow
def test_quick_run_writes_its_tables_and_plots(tmp_path):
    res = restir_antithetic.main(["--quick", "--resolution", "24", "--steps", "2", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert set(saved["methods"]) == set(restir_antithetic.METHODS)
    assert saved["scored_pixels"] > 0 and all(r["relative_error"] > 0 for r in res["methods"].values())
    for name in ("summary.md", "antithetic.png", "derivative_images.png"):
        assert (tmp_path / name).stat().st_size > 0
