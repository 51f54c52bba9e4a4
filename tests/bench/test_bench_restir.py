"""The `restir` bench suite: its quick mode end to end (a real run, under a minute) and the
arithmetic of the floor / gain / bound columns on synthetic runs (no renders)."""
from __future__ import annotations

import json
import math
import statistics

import pytest
import torch

from torchir.bench import SUITES
from torchir.bench.restir_report import error_at_spp
from torchir.bench.restir import (
    ALL_RESTIRS, BASELINES, DEFAULT_RESTIRS, ORACLE, ORACLE_LOW, bracketing_spps, camera_floor, equal_time_error, equal_time_spp, error_beyond_reference,
    methods_in, parse_args,
    resolve_scenes, restir_variants, summarize_scene, tables,
)

QUICK_SCENE = "oxalis_lite"  # always built in; the default quick scene (ajar_painting) may change under other work
QUICK_RESTIRS = ("ReSTIR (shadowed)", "ReSTIR (persistent)")  # two of the three: the budget goes to the slower
METHODS = (*BASELINES, *QUICK_RESTIRS)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    from torchir.bench.restir import main

    out = tmp_path_factory.mktemp("bench_restir")
    main(["--quick", "--scenes", QUICK_SCENE, "--restirs", "shadowed,persistent", "--out", str(out)])
    return out, json.loads((out / "results.json").read_text())


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_run_writes_every_output(quick):
    out, results = quick
    assert SUITES["restir"] == "torchir.bench.restir"
    for name in ("results.json", "tables.md", "summary.md", f"gradient_{QUICK_SCENE}.png", f"reconstruction_{QUICK_SCENE}.png"):
        assert (out / name).is_file(), name
    assert (out / f"gradient_{QUICK_SCENE}.png").read_bytes()[:4] == b"\x89PNG"
    assert results["config"]["resolution"] == 32 and results["config"]["spp"] == 1
    assert list(results["scenes"]) == [QUICK_SCENE]
    text = (out / "tables.md").read_text()
    assert f"#### {QUICK_SCENE}" in text and "#### Overview" in text and "of possible" in text
    header = next(line for line in text.splitlines() if line.startswith("| method | relerr"))
    rows = [line for line in text.splitlines() if line.startswith(tuple(f"| {m} |" for m in (*METHODS, ORACLE)))]
    assert len(rows) == 2 * (len(METHODS) + 1)  # the method table and the stage table
    assert all(r.count("|") == header.count("|") for r in rows[: len(METHODS) + 1])


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_run_numbers_are_sane(quick):
    _, results = quick
    scene = results["scenes"][QUICK_SCENE]
    rows = scene["rows"]
    assert set(rows) == {*METHODS, ORACLE}
    assert scene["best_baseline"] in BASELINES and scene["best_recon_baseline"] in BASELINES
    spp_eq = scene["calibration"]["equal_time_spp"]
    assert spp_eq[scene["calibration"]["budget_method"]] == 1 and all(1 <= spp_eq[m] <= 256 for m in METHODS)
    assert _finite(scene["reference"]["relative_se"]) and scene["reference"]["relative_se"] > 0
    for m in METHODS:
        r = rows[m]
        for field in ("relerr_equal_samples", "floor", "light", "relerr_equal_time", "seconds_equal_time", "gain",
                      "seconds_per_step", "step_ratio_to_B.2", "recon_rmse", "recon_initial_rmse", "train_step_seconds",
                      "train_step_ratio_to_direct", "recon_ratio_to_best_baseline"):
            assert _finite(r[field]) and r[field] >= 0, (m, field, r[field])
        assert r["relerr_equal_samples"] > 0 and r["seconds_per_step"] > 0 and r["recon_steps"] >= 1
        assert r["recon_rmse"] < 1.0  # a texture in [0, 1]
    for m in QUICK_RESTIRS:  # a frozen pass (dr.freeze) has one timer, "pass"; then an unfrozen run gives the stages
        assert rows[m]["burn_in_seconds"] > 0 and "backward" in rows[m]["stages"] and _finite(rows[m]["bound"])
        stages = {**rows[m]["stages"], **scene["unfrozen_stages"].get(f"{m}, unfrozen", {}).get("stages", {})}
        assert {"ris", "nn", "combine", "backward"} <= set(stages) and all(_finite(v) and v >= 0 for v in stages.values())
    # equal wall time: the budget method trains recon_steps steps, the others about its time
    budget = rows[scene["calibration"]["budget_method"]]
    assert budget["recon_steps"] == results["config"]["recon_steps"]
    assert all(rows[m]["recon_seconds"] >= 0.5 * budget["recon_seconds"] for m in METHODS)
    assert rows["direct"]["train_step_ratio_to_direct"] == 1.0 and rows["B.2"]["step_ratio_to_B.2"] == 1.0


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_run_floor_is_below_b2_at_equal_samples(quick):
    """The floor oracle (RIS, 256 shadowed candidates, no reuse) and B.2 (RIS, 8 candidates, no
    reuse) render step i with the same seed, hence the same camera rays: conditioned on them, both
    are unbiased with light noise that is independent of the camera part, so
    E[e_B2,i² − e_oracle,i²] = light_B2² − light_oracle² >= 0 (RIS variance does not grow with the
    candidate count). Neither reuses, so the per-step differences d_i are i.i.d.; we accept the
    mean of d down to 4 standard errors below 0 (one-sided; with 8 steps, a t distribution with
    7 degrees of freedom puts < 0.3 % there). The measured margin is far larger (B.2 ~ 2.7x the floor)."""
    _, results = quick
    scene = results["scenes"][QUICK_SCENE]
    runs = {(r["method"], r["spp"]): r for r in scene["gradient_runs"]}
    b2, oracle = runs[("B.2", 1)]["relerr_steps"], runs[(ORACLE, 1)]["relerr_steps"]
    assert len(b2) == len(oracle) == results["config"]["grad_steps"]
    d = [x * x - y * y for x, y in zip(b2, oracle)]
    se = statistics.stdev(d) / math.sqrt(len(d))
    assert statistics.fmean(d) >= -4 * se
    rows = scene["rows"]
    ref_sq = scene["reference"]["relative_se"] ** 2
    corrected = {m: math.sqrt(max(statistics.fmean([y * y - ref_sq for y in runs[(m, 1)]["relerr_steps"]]), 0.0))
                 for m in (ORACLE_LOW, ORACLE)}
    cfg = results["config"]
    assert rows[ORACLE]["floor"] == pytest.approx(
        camera_floor(corrected[ORACLE_LOW], cfg["oracle_low"], corrected[ORACLE], cfg["oracle_candidates"]))
    assert rows[ORACLE]["floor"] <= rows["B.2"]["relerr_equal_samples"] + 4 * se / (2 * rows["B.2"]["relerr_equal_samples"])


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_run_gain_and_bound_columns_match_the_errors(quick):
    _, results = quick
    scene = results["scenes"][QUICK_SCENE]
    rows = scene["rows"]
    e_best = rows[scene["best_baseline"]]["relerr_equal_time"]
    assert e_best == min(rows[m]["relerr_equal_time"] for m in BASELINES)
    for m in METHODS:
        r = rows[m]
        assert r["gain"] == pytest.approx(e_best / r["relerr_equal_time"])
        assert r["light"] == pytest.approx(math.sqrt(max(r["relerr_equal_samples"] ** 2 - r["floor"] ** 2, 0.0)))
        assert r["relerr_equal_samples"] ** 2 == pytest.approx(r["floor"] ** 2 + r["light"] ** 2) or r["light"] == 0.0
    for m in QUICK_RESTIRS:
        r = rows[m]
        floor_eq = scene["floors"][str(r["spp_equal_time"])]
        assert r["bound"] == pytest.approx(e_best / floor_eq)
        assert r["gain"] / r["bound"] == pytest.approx(floor_eq / r["relerr_equal_time"])  # gain <= bound iff error >= floor
    assert rows[scene["best_baseline"]]["gain"] == pytest.approx(1.0)


# ------------------------------------------------------------------ synthetic (no renders)
def _run(method: str, spp: int, errors: list[float], seconds: float = 0.1, burn_in: float = 0.0) -> dict:
    squares = [e * e for e in errors]
    return {"method": method, "spp": spp, "relerr_steps": errors, "relerr": math.sqrt(statistics.fmean(squares)),
            "relerr_sq_se": 0.0, "seconds_per_step": seconds, "burn_in_seconds": burn_in,
            "charged_seconds_per_step": seconds + burn_in / len(errors), "stages": {}}


def test_summary_splits_floor_and_light_and_reads_gain_of_possible():
    spp_eq = {"direct": 8, "B.1": 8, "B.2": 4, "ReSTIR (shadowed)": 1, "ReSTIR (unshadowed)": 2, "ReSTIR (persistent)": 2}
    runs = [
        _run("direct", 1, [0.5, 0.5]), _run("direct", 8, [0.2, 0.2]),
        _run("B.1", 1, [0.6, 0.6]), _run("B.1", 8, [0.25, 0.25]),
        _run("B.2", 1, [0.3, 0.3]), _run("B.2", 4, [0.16, 0.16]),
        _run("ReSTIR (shadowed)", 1, [0.05, 0.05], 0.3, 0.6), _run("ReSTIR (unshadowed)", 1, [0.06, 0.06], 0.2, 0.4),
        _run("ReSTIR (unshadowed)", 2, [0.045, 0.045]),
        _run("ReSTIR (persistent)", 1, [0.045, 0.045], 0.1, 0.2), _run("ReSTIR (persistent)", 2, [0.032, 0.032]),
        _run(ORACLE, 1, [0.04, 0.04]), _run(ORACLE, 2, [0.03, 0.03]),
    ]
    def train_run(method: str, mode: str, rmse: float, steps: int) -> dict:
        return {"method": method, "grad_paths": mode, "seed": 0, "steps": steps, "step_seconds": [1.0] + [0.1] * (steps - 1),
                "elapsed": [0.1 * k for k in range(steps + 1)], "param_error": [0.2] * steps + [rmse],
                "final_param_error": rmse, "train_seconds": 0.1 * steps}

    recon = {mode: [train_run(m, mode, rmse, steps) for m, rmse, steps in
                    (("direct", 0.1, 20), ("B.1", 0.12, 18), ("B.2", 0.08, 10), ("ReSTIR (shadowed)", 0.04, 5),
                     ("ReSTIR (unshadowed)", 0.05 if mode == "shared" else 0.02, 6), ("ReSTIR (persistent)", 0.016, 9))]
             for mode in ("shared", "decorrelated")}
    s = summarize_scene(runs, 1, spp_eq, recon)
    rows = s["rows"]
    assert s["best_recon_baseline"] == "B.2" and rows["ReSTIR (shadowed)"]["recon_ratio_to_best_baseline"] == pytest.approx(0.5)
    assert s["reconstruction_summary"]["decorrelated"]["rows"]["ReSTIR (unshadowed)"]["recon_ratio_to_best_baseline"] == pytest.approx(0.25)
    assert rows["B.2"]["train_step_ratio_to_direct"] == pytest.approx(1.0) and rows["direct"]["recon_steps"] == 20
    assert s["best_baseline"] == "B.2" and rows["B.2"]["gain"] == pytest.approx(1.0)
    assert rows["ReSTIR (shadowed)"]["light"] == pytest.approx(0.03)  # sqrt(0.05² − 0.04²)
    assert rows["B.1"]["light"] == pytest.approx(math.sqrt(0.36 - 0.0016))
    assert rows["ReSTIR (shadowed)"]["gain"] == pytest.approx(3.2) and rows["ReSTIR (shadowed)"]["bound"] == pytest.approx(4.0)
    assert rows["ReSTIR (unshadowed)"]["bound"] == pytest.approx(0.16 / 0.03)  # the floor at its own equal-time spp
    assert rows["ReSTIR (persistent)"]["gain"] == pytest.approx(5.0)  # at its own equal-time spp: 0.16 / 0.032
    assert rows["ReSTIR (persistent)"]["recon_ratio_to_best_baseline"] == pytest.approx(0.2)
    assert rows["B.2"]["bound"] is None and rows[ORACLE]["light"] == 0.0
    assert rows["ReSTIR (shadowed)"]["charged_seconds_per_step"] == pytest.approx(0.6)
    text = tables({"config": {"spp": 1, "resolution": 32, "candidates": 8, "burn_in": 8, "oracle_candidates": 256, "grad_steps": 2,
                              "ref_spp": 64, "lr": 0.02, "recon_steps": 3, "recon_seeds": 1, "grad_paths": ["shared", "decorrelated"]},
                   "scenes": {"demo": {**s, "reference": {"relative_se": 0.001},
                                       "calibration": {"budget_seconds": 0.6, "budget_method": "ReSTIR (shadowed)"}}}})
    assert "gain 3.2x of possible 4x" in text and "1x (best)" in text
    assert "recon RMSE (eq. wall time, shared)" in text and "| decorrelated: RMSE (steps) |" in text and "0.02 (6)" in text
    assert len({line.count("|") for line in text.splitlines() if line.startswith("| ReSTIR (shadowed) |")}) == 3  # 3 tables
    assert "Reconstruction bound" not in text
    with_oracle = {mode: [*runs_, train_run(ORACLE, mode, 0.01, 5)] for mode, runs_ in recon.items()}
    first = summarize_scene(runs, 1, spp_eq, with_oracle)["reconstruction_summary"]["shared"]
    assert (first["floor_rmse"], first["floor_steps"], first["bound"]) == (0.01, 5.0, pytest.approx(8.0))  # B.2's 0.08 / 0.01
    assert ORACLE not in first["rows"]
    text = tables({"config": {"spp": 1, "resolution": 32, "candidates": 8, "burn_in": 8, "oracle_candidates": 256, "grad_steps": 2,
                              "ref_spp": 64, "lr": 0.02, "recon_steps": 3, "recon_seeds": 1, "grad_paths": ["shared", "decorrelated"]},
                   "scenes": {"demo": {**summarize_scene(runs, 1, spp_eq, with_oracle), "reference": {"relative_se": 0.001},
                                       "calibration": {"budget_seconds": 0.6, "budget_method": "ReSTIR (shadowed)"}}}})
    assert "reached RMSE 0.01: no light sampler gains more than 8x over the best baseline (B.2)" in text
    below = summarize_scene([*runs[:-2], _run(ORACLE, 1, [0.06, 0.06]), _run(ORACLE, 2, [0.03, 0.03])], 1, spp_eq)
    assert below["rows"]["ReSTIR (shadowed)"]["light"] == 0.0  # an error under the floor: no light part, not NaN


def test_two_oracles_extrapolate_the_floor_at_each_spp_and_bound_each_variant_by_its_own():
    """The floor and bound columns of the slow quick run, from known errors: with RIS oracles over
    64 and 256 candidates, ``e(M)² = floor² + L / M`` gives the floor exactly, at 1 spp (the
    floor column, the oracle row's errors) and at 2 spp (a ReSTIR variant's equal-time spp,
    whose bound is the best baseline's equal-time error over that floor)."""
    def oracle(floor: float, light: float, m: int) -> float:
        return math.sqrt(floor**2 + light / m)

    floors, light = {1: 0.02, 2: 0.01}, {1: 0.0256, 2: 0.0064}
    spp_eq = {"direct": 2, "B.1": 2, "B.2": 2, "ReSTIR (persistent)": 2}
    runs = [_run(m, s, [e / math.sqrt(s)] * 2) for m, e in (("direct", 0.5), ("B.1", 0.6), ("B.2", 0.3)) for s in (1, 2)]
    runs += [_run("ReSTIR (persistent)", s, [0.05 / s] * 2) for s in (1, 2)]
    runs += [_run(name, s, [oracle(floors[s], light[s], m)] * 2) for name, m in ((ORACLE_LOW, 64), (ORACLE, 256)) for s in (1, 2)]
    summary = summarize_scene(runs, 1, spp_eq, oracle_candidates=(64, 256))
    rows = summary["rows"]
    assert summary["floors"] == {"1": pytest.approx(0.02), "2": pytest.approx(0.01)}
    assert rows["B.2"]["floor"] == pytest.approx(0.02) and rows[ORACLE]["relerr_equal_samples"] == pytest.approx(0.02)
    assert rows[ORACLE]["oracle_errors"] == {"256": pytest.approx(oracle(0.02, 0.0256, 256)), "64": pytest.approx(oracle(0.02, 0.0256, 64))}
    restir = rows["ReSTIR (persistent)"]
    assert restir["floor_equal_time"] == pytest.approx(0.01) and rows["B.2"]["floor_equal_time"] is None
    e_best = 0.3 / math.sqrt(2)  # B.2 at its equal-time 2 spp
    assert summary["best_baseline"] == "B.2" and restir["gain"] == pytest.approx(e_best / 0.025)
    assert restir["bound"] == pytest.approx(e_best / 0.01)  # >= gain: the variant's error is above its floor
    assert restir["light"] == pytest.approx(math.sqrt(0.05**2 - 0.02**2))  # at 1 spp, against the 1-spp floor


def test_gradient_runs_take_every_step_s_error_less_the_reference_s_and_charge_the_burn_in():
    """``gradient_runs`` on a stand-in problem with known per-step errors and times: the
    relative error of a run is the RMS of its steps' errors with the reference's own relative
    s.e. removed in quadrature (every step, the first included), its step time the median of
    the steps after the first (compilation, burn-in), its charged time that plus the burn-in
    spread over the steps, and step ``i`` of every run has seed ``1000 + i`` (shared camera rays)."""
    from types import SimpleNamespace

    from torchir.bench.restir import gradient_runs

    errors = {("B.2", 1): [0.30, 0.40, 0.20, 0.50], (ORACLE, 1): [0.10, 0.12, 0.08, 0.11]}
    times = [9.0, 0.2, 0.4, 0.3]
    seeds = []

    def step(sampler, spp, seed):
        seeds.append((sampler, seed))
        i = seed - 1000
        diag = {"time_burn_in": 0.8 if i == 0 else 0.0, "time_ris": 0.1}
        return times[i], errors[sampler, spp][i], diag

    problem = SimpleNamespace(name="stand-in", ref_relative_se=0.05, sampler=lambda method, a: method, step=step)
    out = {r["method"]: r for r in gradient_runs(problem, SimpleNamespace(grad_steps=4), list(errors))}
    for (method, _), e in errors.items():
        r = out[method]
        assert r["relerr_steps"] == e
        assert r["relerr"] == pytest.approx(math.sqrt(statistics.fmean([x * x - 0.05**2 for x in e])))
        assert r["seconds_per_step"] == pytest.approx(0.3) and r["burn_in_seconds"] == 0.8
        assert r["charged_seconds_per_step"] == pytest.approx(0.3 + 0.8 / 4)
        assert r["stages"] == {"ris": pytest.approx(0.1), "other": pytest.approx(0.2)}
    assert [seed for _, seed in seeds] == [1000, 1000, 1001, 1001, 1002, 1002, 1003, 1003]  # interleaved, seeds shared


def test_calibration_gives_each_method_the_spp_that_fills_the_slower_restir_s_step(monkeypatch):
    """The equal-time spp behind the slow quick run's equal-time columns, with step times known
    and affine in spp (the probes stood in for): the budget is the slower ReSTIR variant's charged
    step at equal samples (it keeps 1 spp), and every other method gets the spp whose step fills
    that budget, after probes at the spps the earlier probes point to."""
    from torchir.bench import restir as bench

    a = parse_args(["--quick", "--restirs", "shadowed,persistent", "--cal-rounds", "3"])
    times = {"direct": (0.05, 0.05), "B.1": (0.02, 0.03), "B.2": (0.1, 0.1), "ReSTIR (shadowed)": (0.2, 0.1),
             "ReSTIR (persistent)": (0.4, 0.1)}  # charged seconds per step: fixed + per spp

    def charged(method: str, spp: float) -> float:
        fixed, per_spp = times[method]
        return fixed + per_spp * spp

    probed = []

    def probe(problem, method, spp, a, seed0):
        probed.append((method, spp))
        return {"spp": spp, "step": charged(method, spp), "burn_in": 0.0, "charged": charged(method, spp)}

    monkeypatch.setattr(bench, "probe", probe)
    runs = [{"method": m, "spp": 1, "seconds_per_step": charged(m, 1), "burn_in_seconds": 0.0,
             "charged_seconds_per_step": charged(m, 1)} for m in times]
    cal = bench.calibrate(None, a, runs)
    assert cal["budget_method"] == "ReSTIR (persistent)" and cal["budget_seconds"] == pytest.approx(0.5)
    expected = {"direct": 9, "B.1": 16, "B.2": 4, "ReSTIR (shadowed)": 3, "ReSTIR (persistent)": 1}  # fixed + per_spp x spp = 0.5
    assert cal["equal_time_spp"] == expected
    assert cal["equal_time_spp_exact"] == {m: pytest.approx(float(s)) for m, s in expected.items()}
    assert all(charged(m, s) == pytest.approx(0.5) for m, s in expected.items() if m != "ReSTIR (persistent)")
    assert not any(m == "ReSTIR (persistent)" for m, _ in probed)  # the budget's owner is not probed


def test_reconstruction_trains_every_method_for_the_budget_method_s_wall_time(monkeypatch):
    """The slow quick run's "equal wall time" reconstructions, with training stood in for: per
    gradient-paths mode and seed, the budget method trains first (its steps, no time limit),
    then every other method for its wall time; the floor oracle, when asked, for the budget
    method's steps with no time limit."""
    from types import SimpleNamespace

    from torchir.bench import restir as bench

    a = parse_args(["--quick", "--restirs", "shadowed,persistent", "--grad-paths", "shared,decorrelated", "--recon-oracle"])
    a.recon_seeds = 2
    calls = []

    def train(name, key, method, a, seed, targets, workdir, max_seconds, grad_paths="decorrelated", steps=None):
        calls.append((grad_paths, seed, method, max_seconds, steps))
        seconds = 3.0 + seed + (0.5 if grad_paths == "shared" else 0.0)
        return {"method": method, "seed": seed, "steps": 7 + seed, "train_seconds": seconds if method == "ReSTIR (shadowed)" else 99.0,
                "step_seconds": [1.0], "param_error": [0.2, 0.1], "final_param_error": 0.1}, "targets"

    monkeypatch.setattr(bench, "train", train)
    monkeypatch.setattr(bench, "gc", SimpleNamespace(collect=lambda: 0))  # no modules to free (0.2 s a collection here)
    out = bench.reconstruction("oxalis_lite", "canvas.bsdf.reflectance.data", a, "ReSTIR (shadowed)")
    expected = []
    for mode in ("shared", "decorrelated"):
        for seed in (0, 1):
            budget = 3.0 + seed + (0.5 if mode == "shared" else 0.0)
            expected += [(mode, seed, "ReSTIR (shadowed)", None, None), (mode, seed, ORACLE, None, 7 + seed)]
            expected += [(mode, seed, m, budget, None) for m in a.methods if m != "ReSTIR (shadowed)"]
    assert calls == expected
    assert [len(out[mode]) for mode in ("shared", "decorrelated")] == [2 * (len(a.methods) + 1)] * 2


def test_equal_time_error_reads_the_effective_sample_count_at_the_budget():
    """Variance 0.04 / spp and a step of 0.1 s + 0.05 s per spp: 1 / e² is linear in time, so the
    error at any budget between (or beyond) two runs is exact."""
    def run(spp: int) -> tuple[float, float]:
        return 0.1 + 0.05 * spp, math.sqrt(0.04 / spp)

    pts = [run(1), run(3)]
    assert equal_time_error(pts, 0.2) == pytest.approx(run(2)[1])  # between the runs
    assert equal_time_error(pts, 0.35) == pytest.approx(run(5)[1])  # beyond them, along their line
    assert equal_time_error(pts, 0.1) == pts[0][1]  # below every run: the fastest (it had more time)
    assert equal_time_error([(0.2, 0.1)], 0.4) == pytest.approx(0.1 / math.sqrt(2))  # one run: proportional to time
    assert equal_time_error([], 0.4) == 0.0
    assert bracketing_spps(1.4, 1, 256) == (1, 2) and bracketing_spps(3.0, 1, 256) == (3,)
    assert bracketing_spps(0.4, 1, 256) == (1,) and bracketing_spps(300.5, 1, 256) == (256,)


def test_summary_reads_baselines_at_exactly_the_budget():
    """A baseline run at 1 and 2 spp (0.1 s and 0.2 s) against a 0.15 s budget: its error is read
    at 1.5 spp, not at the rounded spp, which would give it a third more or less time."""
    spp_eq = {"direct": 2, "B.1": 2, "B.2": 2, **{m: 1 for m in ALL_RESTIRS}}
    runs = [_run(m, s, [e / math.sqrt(s)] * 2, 0.1 * s) for m, e in (("direct", 0.5), ("B.1", 0.6), ("B.2", 0.3)) for s in (1, 2)]
    runs += [_run(m, 1, [0.05, 0.05], 0.15) for m in ALL_RESTIRS] + [_run(ORACLE, 1, [0.04, 0.04])]
    rows = summarize_scene(runs, 1, spp_eq, budget=0.15)["rows"]
    assert rows["B.2"]["relerr_equal_time"] == pytest.approx(0.3 / math.sqrt(1.5))
    assert rows["B.2"]["relerr_equal_time_measured"] == pytest.approx(0.3 / math.sqrt(2))
    assert rows["B.2"]["seconds_equal_time"] == 0.15 and rows["ReSTIR (shadowed)"]["relerr_equal_time"] == 0.05
    assert rows["ReSTIR (persistent)"]["gain"] == pytest.approx(0.3 / math.sqrt(1.5) / 0.05)
    unread = summarize_scene(runs, 1, spp_eq)["rows"]  # without a budget: the run at the rounded spp
    assert unread["B.2"]["relerr_equal_time"] == pytest.approx(0.3 / math.sqrt(2))
    # with the calibration's fractional spp, the error is read there, whatever the runs' own step times say
    noisy = [{**r, "charged_seconds_per_step": 0.15} if r["method"] in BASELINES else r for r in runs]
    exact = {"direct": 1.5, "B.1": 1.5, "B.2": 1.25}
    rows = summarize_scene(noisy, 1, spp_eq, budget=0.15, spp_exact=exact)["rows"]
    assert rows["B.2"]["relerr_equal_time"] == pytest.approx(0.3 / math.sqrt(1.25))
    assert rows["direct"]["relerr_equal_time"] == pytest.approx(0.5 / math.sqrt(1.5))


def test_error_at_spp_is_exact_for_a_one_over_spp_variance():
    pts = [(1, 0.2), (4, 0.1)]
    assert error_at_spp(pts, 2.0) == pytest.approx(0.2 / math.sqrt(2))  # between the runs
    assert error_at_spp(pts, 8.0) == pytest.approx(0.2 / math.sqrt(8))  # beyond: proportional to the nearest
    assert error_at_spp(pts, 0.5) == pytest.approx(0.2 / math.sqrt(0.5))
    assert error_at_spp([(2, 0.0)], 1.0) == 0.0


def test_equal_time_spp_line_through_the_probes_and_limits():
    lo = {"spp": 1, "charged": 0.02}
    hi = {"spp": 5, "charged": 0.06}  # 0.01 s per spp on top of 0.01 s fixed
    assert equal_time_spp([lo, hi], 0.1, 1, 256) == 9
    assert equal_time_spp([lo, hi, {"spp": 9, "charged": 0.1}], 0.1, 1, 256) == 9
    assert equal_time_spp([lo], 0.1, 1, 256) == 5  # proportional from a single probe
    assert equal_time_spp([lo, hi], 10.0, 1, 64) == 64
    assert equal_time_spp([lo, {"spp": 5, "charged": 0.01}], 0.1, 1, 256) == 5  # no positive slope: proportional
    assert equal_time_spp([{"spp": 1, "charged": 0.2}], 0.1, 1, 256) == 1  # already slower: equal samples


def test_options_and_default_scenes():
    q, full = parse_args(["--quick"]), parse_args([])
    assert (q.resolution, q.spp, full.resolution, full.spp, full.burn_in) == (32, 1, 128, 1, 32)
    assert (full.oracle_low, full.oracle_candidates) == (256, 1024)
    one = parse_args(["--oracle-candidates", "512"])
    assert (one.oracle_low, one.oracle_candidates) == (None, 512)
    with pytest.raises(SystemExit):
        parse_args(["--oracle-candidates", "1,2,3"])
    assert full.grad_steps > q.grad_steps and full.recon_steps > q.recon_steps
    # decorrelated paths first (issue 39): they fill the main table and the gradient-error runs
    assert (q.grad_paths, full.grad_paths) == (["decorrelated"], ["decorrelated"])  # unbiased baselines by default
    assert parse_args(["--grad-paths", "decorrelated,shared"]).grad_paths == ["decorrelated", "shared"]
    assert parse_args(["--grad-paths", "shared"]).grad_paths == ["shared"]
    half = parse_args(["--lr-half-life", "150", "--recon-oracle"])  # the trainer takes whole steps only
    assert type(half.lr_half_life) is int and half.lr_half_life == 150 and half.recon_oracle
    assert parse_args([]).lr_half_life is None and not parse_args([]).recon_oracle
    from torchir.training import InverseRenderingModule

    InverseRenderingModule(scene="oxalis_lite", resolution=8, lr_half_life=half.lr_half_life)  # accepted as given
    from torchir import Scene
    from torchir.bench.restir import Problem

    problem = Problem("oxalis_lite", Scene.builtin("oxalis_lite", resolution=8), "", None, None, None, 0.0, 0.0)
    for a, want in ((q, "decorrelated"), (parse_args(["--grad-paths", "shared,decorrelated"]), "shared")):
        assert problem.sampler("direct", a) is None
        assert {problem.sampler(m, a).integrator.grad_paths for m in ("B.1", "B.2", *restir_variants(DEFAULT_RESTIRS))} == {want}
    import torchir

    present = [s for s in ("ajar_painting", "many_lights", "oxalis_lite") if s in torchir.scenes.available()]
    assert resolve_scenes(None)[0] == present and resolve_scenes(None, quick=True)[0] == present[:1]
    assert resolve_scenes("oxalis_lite, cbox")[0] == ["oxalis_lite", "cbox"]
    with pytest.raises(ValueError, match="unknown scene"):
        resolve_scenes("nope")


def test_error_beyond_reference_removes_the_references_own_error_in_quadrature():
    rms, se = error_beyond_reference([0.05, 0.05], 0.03)
    assert rms == pytest.approx(0.04) and se == 0.0  # 0.05² = 0.04² + 0.03²
    rms, se = error_beyond_reference([0.03, 0.05], 0.0)
    assert rms == pytest.approx(((0.03**2 + 0.05**2) / 2) ** 0.5) and se == pytest.approx((0.05**2 - 0.03**2) / 2)
    assert error_beyond_reference([0.01], 0.02) == (0.0, 0.0)  # below the reference's noise: 0, not NaN


def test_camera_floor_extrapolates_the_oracles():
    """e(M)² = floor² + L / M: two oracles give the floor exactly; one gives its own error."""
    floor, light = 0.01, 1.0
    e = {m: math.sqrt(floor**2 + light / m) for m in (256, 1024)}
    assert camera_floor(e[256], 256, e[1024], 1024) == pytest.approx(floor)
    assert camera_floor(None, None, e[1024], 1024) == e[1024]
    assert camera_floor(0.07, 256, 0.03, 1024) == 0.0  # noise that makes the extrapolation negative: 0, not NaN


def test_sweep_script_parses_option_sets():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "sweep_restir.py"
    spec = importlib.util.spec_from_file_location("sweep_restir", path)
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    assert sweep.keywords('burn_in=32,target="unshadowed",spp=2') == {"burn_in": 32, "target": "unshadowed", "spp": 2}
    assert sweep.keywords("") == {}
    with pytest.raises(ValueError):
        sweep.keywords("candidates=__import__('os')")  # literals only


@pytest.mark.slow
def test_chains_script_tiny_run():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "restir_chains.py"
    spec = importlib.util.spec_from_file_location("restir_chains", path)
    chains = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(chains)
    out = chains.main(["many_lights", "--resolution", "16", "--steps", "3", "--oracle-steps", "2", "--ref-spp", "64", "--chains", "2:0,4:64:2"])
    assert len(out) == 5 and all(math.isfinite(v) and v >= 0 for v in out.values())
    assert {"persistent, burn_in=2, m_cap=default", "persistent, burn_in=4, m_cap=64, candidates=2"} <= set(out)
    assert out["RIS 1024"] < out["RIS 256"]  # more candidates, less light noise


# ------------------------------------------------------------------------------ restir_views
@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_views_bench_tiny_run(tmp_path):
    """A tiny run of the multi-view bench writes its outputs, with one error per step and a
    clock that only grows; the summary's efficiency is (e_base^2 t_base) / (e^2 t)."""
    from torchir.bench import restir_views

    results = restir_views.main(["--resolution", "16", "--views", "2", "--steps", "4", "--burn-in", "1",
                                 "--ref-spp", "64", "--candidates", "2", "--out", str(tmp_path)])
    assert set(results) == {"B.2", "per-sensor (burn-in 1)", "carry-over (burn-in 1)"}
    for r in results.values():
        assert len(r["errors"]) == 4 and all(0 < e < 10 for e in r["errors"])
        assert all(b > a for a, b in zip(r["clock"], r["clock"][1:])) and r["seconds"] == r["clock"][-1]
    for name in ("summary.md", "results.json", "views.png"):
        assert (tmp_path / name).stat().st_size > 0
    table = restir_views.summarize({"per-sensor (burn-in 4)": {"rms_error": 0.2, "seconds": 2.0},
                                    "carry-over (burn-in 4)": {"rms_error": 0.1, "seconds": 4.0}}, [4])
    assert "| carry-over (burn-in 4) | 0.1000 | 4.00 | 2.00x |" in table


def test_views_bench_errors_and_efficiency_from_known_gradients(monkeypatch):
    """The numbers of the slow tiny run, from known inputs: ``run_method`` steps the views in
    turn, each step's error is ``||g - g_ref(view)|| / ||g_ref(view)||`` against that view's
    reference, the RMS over the steps is reported with the summed step times; ``summarize``'s
    efficiency of carry-over against per-sensor chains of the same burn-in is
    ``(e_base² t_base) / (e² t)`` (> 1: carry-over better at equal time)."""
    from types import SimpleNamespace

    from torchir.bench import restir_views

    refs = [torch.tensor([3.0, 4.0]), torch.tensor([0.0, 2.0])]
    grads = [torch.tensor([3.0, 5.0]), torch.tensor([0.0, 3.0]), torch.tensor([6.0, 8.0])]
    views = []

    def gradient(scene, texture, weights, view, spp, seed, sampler=None):
        views.append((view, seed))
        return grads[seed]

    monkeypatch.setattr(restir_views, "_gradient", gradient)
    monkeypatch.setattr("torchir.samplers.ReSTIRSampler", lambda scene, **options: options)
    r = restir_views.run_method(None, None, [None, None], refs, {"candidates": 2}, SimpleNamespace(steps=3, views=2, spp=1))
    assert views == [(0, 0), (1, 1), (0, 2)]
    assert r["errors"] == pytest.approx([1 / 5, 1 / 2, 1.0])
    assert r["rms_error"] == pytest.approx(math.sqrt((0.04 + 0.25 + 1.0) / 3))
    assert r["seconds"] == r["clock"][-1] and all(b >= a for a, b in zip(r["clock"], r["clock"][1:]))
    table = restir_views.summarize({"per-sensor (burn-in 4)": {"rms_error": 0.2, "seconds": 2.0},
                                    "carry-over (burn-in 4)": {"rms_error": 0.1, "seconds": 4.0},
                                    "carry-over (burn-in 8)": {"rms_error": 0.1, "seconds": 1.0}}, [4, 8])
    assert "| carry-over (burn-in 4) | 0.1000 | 4.00 | 2.00x |" in table  # (0.04 x 2) / (0.01 x 4)
    assert "| per-sensor (burn-in 4) | 0.2000 | 2.00 | - |" in table
    assert "| carry-over (burn-in 8) | 0.1000 | 1.00 | - |" in table  # no per-sensor run of its burn-in


def test_restir_variants_can_be_run_alone():
    """``--restirs persistent``: the variant alone, so its own cost sets the equal-time budget;
    summaries and tables follow the variants a run has, whatever the module constants list."""
    from torchir.bench import restir as bench

    assert parse_args([]).restirs == ["shadowed", "unshadowed", "persistent"] and parse_args([]).restir_methods == ALL_RESTIRS[:3]
    alone = parse_args(["--restirs", "persistent"])
    assert alone.restir_methods == ("ReSTIR (persistent)",) and alone.methods == (*BASELINES, "ReSTIR (persistent)")
    assert restir_variants(["persistent", "shadowed"]) == ("ReSTIR (shadowed)", "ReSTIR (persistent)")  # table order
    with pytest.raises(SystemExit):
        parse_args(["--restirs", "fast"])
    with pytest.raises(ValueError, match="--restirs takes some of shadowed, unshadowed, persistent"):
        restir_variants(["persistent", "fast"])
    assert bench.sampler_options("ReSTIR (persistent)", alone)["preset"] == "persistent"
    assert bench.sampler_options("ReSTIR (persistent)", alone)["m_cap"] is None  # the preset's own cap
    long = parse_args(["--restirs", "persistent", "--chain-cap", "16384"])
    assert bench.sampler_options("ReSTIR (persistent)", long)["m_cap"] == 16384 and "m_cap" not in bench.sampler_options("ReSTIR (shadowed)", long)
    assert bench.sampler_options("ReSTIR (persistent)", alone)["light_guide"] == 0.0  # off unless asked
    guided = parse_args(["--restirs", "persistent", "--light-guide", "0.5"])
    assert bench.sampler_options("ReSTIR (persistent)", guided)["light_guide"] == 0.5
    assert "light_guide" not in bench.sampler_options("ReSTIR (shadowed)", guided)
    cheap = parse_args(["--restirs", "persistent", "--chain-candidates", "4"])
    assert bench.sampler_options("ReSTIR (persistent)", cheap)["candidates"] == 4
    assert bench.sampler_options("B.2", cheap)["candidates"] == 16  # the baselines keep --candidates
    assert bench.sampler_options("ReSTIR (persistent)", alone)["candidates"] == 16
    with pytest.raises(SystemExit):
        parse_args(["--chain-candidates", "0"])
    spp_eq = {"direct": 2, "B.1": 2, "B.2": 2, "ReSTIR (persistent)": 1}
    runs = [_run(m, s, [0.3 / math.sqrt(s)] * 2, 0.1 * s) for m in BASELINES for s in (1, 2)]
    runs += [_run("ReSTIR (persistent)", 1, [0.05, 0.05], 0.15), _run(ORACLE, 1, [0.04, 0.04])]
    summary = summarize_scene(runs, 1, spp_eq, budget=0.15)
    assert set(summary["rows"]) == {*BASELINES, "ReSTIR (persistent)", ORACLE}
    assert methods_in(summary["rows"]) == ((*BASELINES, "ReSTIR (persistent)"), ("ReSTIR (persistent)",))
    text = tables({"config": {"spp": 1, "resolution": 32, "candidates": 8, "burn_in": 8, "oracle_candidates": 256, "grad_steps": 2,
                              "ref_spp": 64, "lr": 0.02, "recon_steps": 3, "recon_seeds": 1, "grad_paths": ["shared"]},
                   "scenes": {"demo": {**summary, "reference": {"relative_se": 0.001},
                                       "calibration": {"budget_seconds": 0.15, "budget_method": "ReSTIR (persistent)"}}}})
    assert "| ReSTIR (persistent) |" in text and "ReSTIR (shadowed)" not in text
