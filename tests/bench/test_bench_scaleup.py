"""The scale-up suite's bookkeeping (no rendering, except one smoke run): reach fractions
against each reference of the same seed, medians, the claims read from its results."""
from __future__ import annotations

import json
import math

import pytest

from torchir.bench import claims, scaleup


def _run(config: str, seed: int, errors: list[float], seconds: float, workload: str = "cbox_512") -> dict:
    n = len(errors)
    return {"scene": workload, "config": config, "seed": seed, "status": "ran", "steps": n, "step_seconds": [seconds / n] * n,
            "elapsed": [seconds * (i + 1) / n for i in range(n)], "param_error": errors, "final_param_error": errors[-1],
            "train_seconds": seconds}


def _runs(seed: int, slow: float = 1.0) -> list[dict]:
    """The full render ends at 0.3 in 10 s, its decayed run at 0.2; uniform ends at 0.25; adaptive
    passes 0.3 at 2 s, 0.25 at 4 s and 0.2 at 6 s (times scaled by ``slow``)."""
    return [
        _run(scaleup.FULL, seed, [0.9, 0.5, 0.3], 10 * slow),
        _run(scaleup.FULL_DECAY, seed, [0.9, 0.4, 0.2], 10 * slow),
        _run(scaleup.UNIFORM, seed, [0.9, 0.5, 0.4, 0.3, 0.25], 10 * slow),
        _run("adaptive 5%, decay", seed, [0.9, 0.3, 0.28, 0.25, 0.22, 0.2, 0.19, 0.18, 0.17, 0.16], 10 * slow),
    ]


def test_reach_fractions_compare_runs_of_the_same_seed_only():
    runs = _runs(0) + _runs(1, slow=2.0)  # seed 1 on a machine twice as slow: fractions must not see it
    assert scaleup.reach_fractions(runs, "cbox_512", "adaptive 5%, decay", scaleup.FULL) == pytest.approx([0.2, 0.2])
    assert scaleup.reach_fractions(runs, "cbox_512", "adaptive 5%, decay", scaleup.UNIFORM) == pytest.approx([0.4, 0.4])
    assert scaleup.reach_fractions(runs, "cbox_512", "adaptive 5%, decay", scaleup.FULL_DECAY) == pytest.approx([0.6, 0.6])
    never = scaleup.reach_fractions(runs, "cbox_512", scaleup.UNIFORM, scaleup.FULL_DECAY)
    assert len(never) == 2 and all(math.isnan(v) for v in never)
    assert scaleup.reach_fractions(runs, "multiview_16", "adaptive 5%, decay", scaleup.FULL) == []


def test_summary_tables_and_claims(tmp_path):
    runs = _runs(0) + _runs(1) + [{"scene": "cbox_512", "config": "broken", "seed": 0, "status": "failed", "error": "boom"}]
    summary = scaleup.summarize(runs)
    rows = {r["config"]: r for r in summary["cbox_512"]}
    adaptive = rows["adaptive 5%, decay"]
    assert adaptive["final_param_error"] == pytest.approx(0.16) and adaptive["steps"] == 10
    assert adaptive[f"reach {scaleup.FULL_DECAY}"] == pytest.approx((0.6, 2, 2))
    assert rows[scaleup.UNIFORM][f"reach {scaleup.FULL_DECAY}"][1:] == (0, 2)
    assert rows["broken"]["status"] == "failed"
    text = scaleup.tables(summary, {"steps": 3, "seeds": 2})
    assert "| adaptive 5%, decay |" in text and "0.6x (2/2)" in text and "never (0/2)" in text and "boom" in text
    (tmp_path / "scaleup").mkdir()
    (tmp_path / "scaleup" / "results.json").write_text(json.dumps({"summary": summary}))
    table = claims.claims_table(tmp_path)
    assert "| scaleup | cbox_512: time for adaptive 5% to reach the full render's final error (decayed lr), / its time" in table
    lines = [line for line in table.splitlines() if line.startswith("| scaleup | cbox_512")]
    assert [line.rsplit("|", 3)[1:3] for line in lines] == [[" 0.6x ", " NO "], [" 0.4x ", " yes "]]


def test_every_workload_compares_the_four_methods_at_equal_time():
    for workload in scaleup.workloads(quick=False):
        names = [name for name, _, _ in scaleup.configurations(workload)]
        assert names[0] == scaleup.FULL  # the reference whose time every other run gets
        assert {scaleup.FULL_DECAY, scaleup.UNIFORM, "Eq. 5 5%, decay", "adaptive 5%, decay"} <= set(names)
        samplers = [model["sampler"]["type"] for _, model, _ in scaleup.configurations(workload) if "sampler" in model]
        assert samplers == ["uniform", "loss", "adaptive"]
    sizes = {w.name: (w.model["resolution"], w.model["scene_options"].get("views", 1)) for w in scaleup.workloads(quick=False)}
    assert sizes == {"cbox_512": (512, 1), "textured_wall_256": (256, 1), "multiview_16": (128, 16)}


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_run_writes_results_and_plots(tmp_path):
    """A 4-step smoke run of the multi-view workload at 32² (~15 s): every configuration trains."""
    results = scaleup.main(["--quick", "--only", "multiview_16", "--steps", "4", "--out", str(tmp_path)])
    ran = [r for r in results["runs"] if r["status"] == "ran"]
    assert len(ran) == len(scaleup.configurations(scaleup.workloads(True)[-1]))
    assert (tmp_path / "summary.md").is_file() and (tmp_path / "pareto.png").stat().st_size > 0
    saved = json.loads((tmp_path / "results.json").read_text())  # the docs' page rebuilds the tables from it
    assert scaleup.summary(saved).rstrip() == (tmp_path / "summary.md").read_text().rstrip()


def test_results_json_rebuilds_the_tables_and_step_times_leave_out_the_first_step():
    """What the slow run checks on a real run, from known runs: ``summary(results)`` (the docs'
    results page) rebuilds from the saved JSON (tuples become lists there) exactly the tables
    of ``summarize``; a configuration's seconds per step is the median over seeds of each run's
    median step after its first (the compiling one), and its steps the median step count."""
    runs = _runs(0) + _runs(1, slow=2.0)
    for r in runs:  # the first step compiles; the others take 1, 2, 3, ... tenths (twice that for seed 1)
        r["step_seconds"] = [30.0] + [0.1 * (1 + r["seed"]) * (i + 1) for i in range(r["steps"] - 1)]
    summarized = scaleup.summarize(runs)
    rows = {r["config"]: r for r in summarized["cbox_512"]}
    assert rows[scaleup.FULL]["seconds_per_step"] == pytest.approx((0.15 + 0.3) / 2)  # medians of (0.1, 0.2) and (0.2, 0.4)
    assert rows[scaleup.UNIFORM]["seconds_per_step"] == pytest.approx((0.25 + 0.5) / 2) and rows[scaleup.UNIFORM]["steps"] == 5
    results = {"config": {"steps": 3, "seeds": 2}, "summary": summarized}
    assert scaleup.summary(json.loads(json.dumps(results))) == scaleup.tables(summarized, {"steps": 3, "seeds": 2})
