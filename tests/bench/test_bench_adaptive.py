"""``torchir bench adaptive`` end to end at 16² (every part, the fewest draws and iterations it
takes): its tables, JSON and plots come out, every pixel sampler is in each part, and a
reference that reaches its own final error at the start (tiny runs do) gives no ratio instead of
dividing by zero."""
from __future__ import annotations

import json
import math

import pytest

from torchir.bench.adaptive import main

ARGS = ["--quick", "--resolution", "16", "--draws", "20", "--seeds", "1", "--iters", "10", "--plateau-iters", "10",
        "--plateau-seeds", "1", "--target-spp", "16"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("adaptive")
    main([*ARGS, "--out", str(out)])
    return out, json.loads((out / "results.json").read_text())


def test_every_part_reports_every_sampler(run):
    out, results = run
    assert set("abcd") <= set(results)
    methods = {"uniform", "eq5", "adaptive"}
    assert methods <= {r["method"] for r in results["a"]["rows"]} and "full" in {r["method"] for r in results["a"]["rows"]}
    assert methods | {"full"} == {r["method"] for r in results["b"]["rows"]}
    assert all(math.isfinite(r["trace_all"]) and r["trace_all"] > 0 for r in results["a"]["rows"])
    assert {p.name for p in out.glob("*.png")} >= {"a_pmfs.png", "b_rmse.png", "c_glossy_pmfs.png", "d_rmse_low_budget.png"}


def test_ratios_are_none_where_the_reference_took_no_time(run):
    _, results = run
    for row in results["b"]["rows"]:
        for key in ("time_ratio", "paths_ratio"):
            assert row[key] is None or (math.isfinite(row[key]) and row[key] >= 0)
