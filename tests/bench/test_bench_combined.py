"""The `combined` bench suite's summary, tables and plots on synthetic results (no renders)."""
from __future__ import annotations

import json
import math

import pytest

from torchir.bench import SUITES
from torchir.bench.combined import (
    CONFIGURATIONS,
    parse_args,
    plot_results,
    summarize,
    tables,
)

META = {"resolution": 32, "steps": 4, "seeds": 2}


def _ran(scene: str, config: str, seed: int, seconds: float, final: float, rss: float = 500.0) -> dict:
    steps = 4
    errors = [0.2 - (0.2 - final) * k / steps for k in range(steps + 1)]
    return {
        "config": config, "scene": scene, "seed": seed, "expect": "run", "note": "", "status": "ran", "steps": steps,
        "step_seconds": [10 * seconds, seconds, seconds, 2 * seconds],  # the first holds compilation: excluded
        "elapsed": [k * seconds for k in range(steps + 1)],
        "paths_per_step": [4096.0] * steps, "logged_image_error": [0.1] * steps, "param_error": errors,
        "final_param_error": final, "final_image_error": 2 * final, "train_seconds": steps * seconds,
        "fit_seconds": steps * seconds + 1, "peak_rss_mb": rss, "rss_start_mb": rss - 20, "peak_rss_is_per_run": True,
    }


def _rejected(scene: str, config: str, status: str, stage: str, error: str) -> dict:
    return {"config": config, "scene": scene, "seed": 0, "expect": "reject", "note": "why", "status": status, "stage": stage, "error": error}


@pytest.fixture
def runs() -> list[dict]:
    out = []
    for seed in (0, 1):
        out += [
            _ran("oxalis_lite", "plain", seed, 0.1, 0.10),
            _ran("oxalis_lite", "ReSTIR", seed, 0.3, 0.05 if seed == 0 else 0.07),
            _ran("cbox", "uniform pixels 5%", seed, 0.2, 0.2),  # the scene's first row, before its baseline
            _ran("cbox", "plain (full render)", seed, 0.1, 0.1),
        ]
    out += [
        _rejected("cbox", "adaptive pixels + target-aware denoiser", "rejected", "construction", "ValueError: a denoiser needs full images"),
        _rejected("glossy_highlight", "LOI + ReSTIR (moving light)", "failed", "training step 1", "RuntimeError: drjit.backward(): no grad | here"),
    ]
    return out


def test_summary_medians_and_ratios_against_the_scene_baseline(runs):
    summary = summarize(runs)
    oxalis = {r["config"]: r for r in summary["scenes"]["oxalis_lite"]}
    assert oxalis["plain"]["ratio_final_param_error"] == 1.0 and oxalis["plain"]["seeds"] == 2
    assert math.isclose(oxalis["ReSTIR"]["final_param_error"], 0.06)  # median of 0.05 and 0.07
    assert math.isclose(oxalis["ReSTIR"]["ratio_final_param_error"], 0.6)
    assert math.isclose(oxalis["ReSTIR"]["seconds_per_step"], 0.3)  # the slow first step is left out
    assert math.isclose(oxalis["ReSTIR"]["ratio_seconds_per_step"], 3.0)
    assert math.isclose(oxalis["ReSTIR"]["rss_growth_mb"], 20.0)
    cbox = {r["config"]: r for r in summary["scenes"]["cbox"]}
    assert all(r["baseline"] == "plain (full render)" for r in cbox.values())  # the marked baseline, not the first row
    assert math.isclose(cbox["uniform pixels 5%"]["ratio_final_param_error"], 2.0)
    assert [r["config"] for r in summary["rejected"]] == ["adaptive pixels + target-aware denoiser", "LOI + ReSTIR (moving light)"]
    assert "glossy_highlight" not in summary["scenes"]


def test_tables_list_rejected_configurations_with_their_errors(runs):
    text = tables(summarize(runs), META)
    rows = [line for line in text.splitlines() if line.startswith("|")]
    rejected = next(r for r in rows if "adaptive pixels + target-aware denoiser" in r)
    assert "| rejected |" in rejected and "| yes |" in rejected and "ValueError: a denoiser needs full images" in rejected
    failed = next(r for r in rows if "LOI + ReSTIR" in r)
    assert "unsupported (fails)" in failed and "no (raised inside Dr.Jit)" in failed
    assert failed.count("|") == rejected.count("|")  # the error's own "|" does not add a column
    header = next(r for r in rows if r.startswith("| configuration"))
    assert all(r.count("|") == header.count("|") for r in rows if "ReSTIR | " in r or r.startswith("| plain"))
    assert "#### oxalis_lite" in text and "#### cbox" in text and "#### Rejected / unsupported combinations" in text


def test_tables_show_nan_as_na():
    run = _ran("cbox", "plain (full render)", 0, 0.1, 0.1)
    run["paths_per_step"] = [float("nan")] * 4
    assert "n/a" in tables(summarize([run]), META)


def test_plots_written(runs, tmp_path):
    pytest.importorskip("matplotlib")
    written = plot_results(runs, tmp_path)
    assert sorted(p.name for p in written) == ["curves_cbox.png", "curves_oxalis_lite.png", "pareto.png"]
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in written)
    assert plot_results([r for r in runs if r["status"] != "ran"], tmp_path) == []


def test_suite_registered_and_configurations_cover_issue_8():
    assert SUITES["combined"] == "torchir.bench.combined"
    names = {(c.scene, c.name): c.expect for c in CONFIGURATIONS}
    assert names[("oxalis_lite", "ReSTIR + target-aware denoiser")] == "run"
    assert names[("cbox", "adaptive pixels + target-aware denoiser")] == "reject"
    assert names[("glossy_highlight", "LOI + ReSTIR (moving light)")] == "reject"
    assert {c.scene for c in CONFIGURATIONS if c.baseline} == {"oxalis_lite", "cbox"}
    quick, full = parse_args(["--quick"]), parse_args([])
    assert (quick.resolution, quick.steps, quick.seeds) == (32, 40, 2) and (full.resolution, full.steps, full.seeds) == (64, 150, 3)


def test_best_error_and_its_step():
    run = _ran("cbox", "plain (full render)", 0, 0.1, 0.15)
    run["param_error"] = [0.2, 0.1, 0.05, 0.12, 0.15]
    row = summarize([run])["scenes"]["cbox"][0]
    assert row["best_param_error"] == 0.05 and row["best_step"] == 2.0
    assert "| 0.05 (2) |" in tables(summarize([run]), META)


def test_paper_claim_line_compares_the_combination_with_each_technique_alone():
    runs = [_ran("oxalis_lite", "plain", 0, 0.1, 0.10), _ran("oxalis_lite", "ReSTIR", 0, 0.3, 0.05),
            _ran("oxalis_lite", "target-aware denoiser", 0, 0.1, 0.08),
            _ran("oxalis_lite", "ReSTIR + target-aware denoiser", 0, 0.3, 0.06)]
    text = tables(summarize(runs), META)
    assert "lowest final parameter error: no" in text  # 0.06 loses to ReSTIR's 0.05
    runs[3] = _ran("oxalis_lite", "ReSTIR + target-aware denoiser", 0, 0.3, 0.04)
    assert "lowest final parameter error: yes" in tables(summarize(runs), META)
    assert "Paper claim" not in tables(summarize(runs[:2]), META)  # nothing to compare


def test_time_to_the_baselines_final_error_per_seed():
    # plain ends at 0.10 after 0.4 s; ReSTIR (0.3 s/step, linear from 0.2 to 0.05) first reaches
    # 0.10 after 3 of 4 steps (0.2 - 0.15 * 3/4 = 0.0875 <= 0.10; after 2: 0.125): 0.9 s = 2.25x;
    # a run that never gets there counts as not reached
    runs = [_ran("oxalis_lite", "plain", 0, 0.1, 0.10), _ran("oxalis_lite", "ReSTIR", 0, 0.3, 0.05),
            _ran("oxalis_lite", "plain", 1, 0.1, 0.10), _ran("oxalis_lite", "ReSTIR", 1, 0.3, 0.15)]
    rows = {r["config"]: r for r in summarize(runs)["scenes"]["oxalis_lite"]}
    assert rows["plain"]["time_to_baseline_error"] == pytest.approx(1.0) and rows["plain"]["reached_baseline_error"] == 2
    assert rows["ReSTIR"]["reached_baseline_error"] == 1 and math.isnan(rows["ReSTIR"]["time_to_baseline_error"])
    runs[3] = _ran("oxalis_lite", "ReSTIR", 1, 0.3, 0.05)
    rows = {r["config"]: r for r in summarize(runs)["scenes"]["oxalis_lite"]}
    assert rows["ReSTIR"]["time_to_baseline_error"] == pytest.approx(2.25)
    assert "2.25 (2/2 seeds)" in tables(summarize(runs), META)


def test_equal_time_gives_every_configuration_the_baselines_wall_time(tmp_path, monkeypatch):
    from torchir.bench import combined

    calls = []

    def fake(config, seed, resolution, steps, quick, workdir, target_spp=None, max_seconds=None):
        calls.append((config.name, steps, max_seconds))
        if config.expect == "reject":
            return _rejected(config.scene, config.name, "rejected", "construction", "ValueError: no")
        return _ran(config.scene, config.name, seed, 0.5 if config.baseline else 0.1, 0.1)

    monkeypatch.setattr(combined, "run_configuration", fake)
    combined.main(["--only", "cbox", "--seeds", "1", "--steps", "4", "--warmup", "0", "--equal-time", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())  # the docs' page rebuilds the tables from it
    assert combined.summary(saved).rstrip() == (tmp_path / "summary.md").read_text().rstrip()
    assert calls[0] == ("plain (full render)", 4, None)  # the baseline first, for its step count
    timed = [c for c in calls[1:] if c[0] in ("uniform pixels 5%", "adaptive pixels 5%")]
    assert timed and all(steps == 200 and seconds == pytest.approx(4 * 0.5) for _, steps, seconds in timed)
