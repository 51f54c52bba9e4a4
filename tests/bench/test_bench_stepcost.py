"""The step-cost suite's bookkeeping (no rendering): Stage-1 steps, ratios within a repetition."""
from __future__ import annotations

import pytest

from torchir.bench import stepcost


def _run(res: int, rep: int, config: str, step: float, stage1: float = 0.0, steps: int = 40) -> dict:
    seconds = [step * (1 + 5 * (i == 0)) + (stage1 if i % stepcost.REFRESH_EVERY == 0 else 0.0) for i in range(steps)]
    median, mean = stepcost.step_times({"step_seconds": seconds})
    return {"resolution": res, "rep": rep, "config": config, "median_step": median, "mean_step": mean, "step_seconds": seconds}


def test_step_times_leave_out_stage1_in_the_median_and_amortise_it_in_the_mean():
    median, mean = stepcost.step_times({"step_seconds": _run(64, 0, "x", 0.01, stage1=0.2)["step_seconds"]})
    assert median == pytest.approx(0.01)
    assert mean == pytest.approx(0.01 + 0.2 / stepcost.REFRESH_EVERY)  # one refresh in steps 20-39


def test_ratios_are_taken_within_a_repetition():
    # repetition 1 runs on a machine twice as slow: the ratio must not see it
    runs = [
        _run(256, 0, stepcost.FULL, 0.10), _run(256, 0, "uniform 0.05", 0.02),
        _run(256, 1, stepcost.FULL, 0.20), _run(256, 1, "uniform 0.05", 0.04),
    ]
    rows = stepcost.summarize(runs)
    uniform = next(r for r in rows if r["sampler"] == "uniform")
    assert uniform["budget"] == 0.05 and uniform["ratio_to_full"] == pytest.approx(0.2)
    assert uniform["ratio_min"] == pytest.approx(0.2) and uniform["ratio_max"] == pytest.approx(0.2)
    full = next(r for r in rows if r["sampler"] == stepcost.FULL)
    assert full["budget"] == 1.0 and full["ratio_to_full"] == 1.0
    text = stepcost.tables(rows, {"steps": 40, "reps": 2})
    assert "5% uniform step at 256²: 0.200x the full-image step" in text


def test_plot_is_written(tmp_path):
    runs = [_run(64, 0, stepcost.FULL, 0.1)] + [_run(64, 0, f"{s} {b:g}", 0.1 * b + 0.005) for s in stepcost.SAMPLERS for b in (0.01, 0.05, 1.0)]
    path = stepcost.plot(stepcost.summarize(runs), tmp_path)
    assert path.stat().st_size > 0


def test_main_writes_tables_its_json_rebuilds(tmp_path, monkeypatch):
    """``main`` with the trainer stubbed (a fixed step time per budget): summary.md is what
    ``summary(results.json)`` gives, so the docs' results page shows the JSON's figures."""
    import json

    def fake(config, seed, resolution, steps, quick, workdir, target_spp=None):
        step = 0.1 if config.name == stepcost.FULL else 0.02
        return {"status": "ran", "step_seconds": [step] * max(steps, stepcost.SKIP + 2)}

    monkeypatch.setattr(stepcost.combined, "run_configuration", fake)
    stepcost.main(["--resolutions", "16", "--reps", "1", "--steps", "8", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["environment"]["command"] and [r["sampler"] for r in saved["rows"]].count(stepcost.FULL) == 1
    assert stepcost.summary(saved).rstrip() == (tmp_path / "summary.md").read_text().rstrip()
