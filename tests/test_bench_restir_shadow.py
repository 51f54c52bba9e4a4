"""torchir bench restir_shadow: runs end to end on a tiny problem; equal time; the table."""
from __future__ import annotations

import json

from torchir.bench import SUITES, restir_shadow


def test_restir_shadow_runs_at_equal_time_and_writes_its_outputs(tmp_path):
    results = restir_shadow.main(["--resolution", "16", "--starts", "10", "--steps", "3", "--burn-in", "1",
                                  "--target-spp", "16", "--out", str(tmp_path)])
    assert set(results) == set(restir_shadow.METHODS)
    restir = results["ReSTIR"][0]
    assert restir["steps"] == 3 and len(restir["angles"]) == 3
    for name in ("forward-only", "B.2", "direct_projective"):
        run = results[name][0]
        assert 1 <= run["steps"] <= 12  # stepped until ReSTIR's wall time, at most 4x its steps
        assert run["steps"] == 12 or run["seconds"] >= 0.5 * restir["seconds"]
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["args"]["starts"] == [10.0]
    assert (tmp_path / "shadow.png").stat().st_size > 0
    assert "| ReSTIR |" in (tmp_path / "summary.md").read_text()
    assert SUITES["restir_shadow"] == "torchir.bench.restir_shadow"


def test_summary_counts_converged_starts():
    run = lambda final, ok: {"final": final, "converged": ok, "steps": 5, "seconds": 1.0}  # noqa: E731
    table = restir_shadow.summarize({"ReSTIR": [run(1.0, True), run(9.0, False)]}, 5.0)
    assert "| ReSTIR | 1 of 2 | 1.0, 9.0 | 5, 5 | 2.0 |" in table
