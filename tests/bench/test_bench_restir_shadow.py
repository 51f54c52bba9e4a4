"""torchir bench restir_shadow: runs end to end on a tiny problem; equal time; the table."""
from __future__ import annotations

import json
import math

import pytest

from torchir.bench import SUITES, restir_shadow


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_restir_shadow_runs_at_equal_time_and_writes_its_outputs(tmp_path):
    """Three of the methods (the budget-setting ReSTIR, a sampler without reuse, Mitsuba's own
    integrator without a sampler): every method's sampler is checked below without running it."""
    methods = ["ReSTIR", "B.2", "direct_projective"]
    results = restir_shadow.main(["--resolution", "16", "--starts", "10", "--steps", "3", "--burn-in", "1",
                                  "--target-spp", "16", "--spread-steps", "4", "--methods", *methods, "--out", str(tmp_path)])
    assert list(results) == methods
    restir = results["ReSTIR"][0]
    assert restir["steps"] == 3 and len(restir["angles"]) == 3
    for name in methods[1:]:
        run = results[name][0]
        assert 1 <= run["steps"] <= 12  # stepped until ReSTIR's wall time, at most 4x its steps
        assert run["steps"] == 12 or run["seconds"] >= 0.5 * restir["seconds"]
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["args"]["starts"] == [10.0]
    assert (tmp_path / "shadow.png").stat().st_size > 0
    assert "| ReSTIR |" in (tmp_path / "summary.md").read_text() and "variance x time" in (tmp_path / "summary.md").read_text()
    spread = saved["spread"]
    assert list(spread) == methods
    assert all(r["sd"] >= 0 and r["seconds_per_step"] > 0 and r["var_x_time"] == pytest.approx(r["sd"] ** 2 * r["seconds_per_step"])
               for r in spread.values())
    assert all(r["settled"] is None or 0 < r["settled"] <= r["seconds"] for runs in results.values() for r in runs)
    assert all(r["converged"] == (r["last_quarter_rms"] < 5.0) for runs in results.values() for r in runs)
    assert SUITES["restir_shadow"] == "torchir.bench.restir_shadow"


def test_only_the_projective_variant_leaves_edge_sampling_off_and_the_paper_baselines_go_by_length():
    scene, _ = restir_shadow.shadow_problem(8)
    flags = {m: restir_shadow.sampler_for(m, scene, 1).integrator.shadow_edge_sampling
             for m in restir_shadow.METHODS if m != "direct_projective"}
    torchir_methods = [m for m in restir_shadow.METHODS if m != "direct_projective"]
    assert flags == {**dict.fromkeys(torchir_methods, True), "ReSTIR, projective edges": False}
    guided = {m: restir_shadow.sampler_for(m, scene, 1).integrator.edge_guiding for m in torchir_methods}
    assert guided == {"ReSTIR": "auto", "ReSTIR, edge chains": "auto", "ReSTIR, no edge chains": "auto", "forward-only": False,
                      "B.2": False, "B.2, guided edges": True, "ReSTIR, projective edges": "auto"}
    chains = {m: restir_shadow.sampler_for(m, scene, 1).integrator.edge_temporal for m in torchir_methods}
    assert (chains["ReSTIR"], chains["ReSTIR, edge chains"], chains["ReSTIR, no edge chains"]) == ("auto", True, False)


def test_blocker_and_edge_candidates_reach_the_scene_and_every_sampler():
    a = restir_shadow.parse_args(["--blocker", "crown", "--edge-candidates", "4"])
    assert (a.blocker, a.edge_candidates) == ("crown", 4)
    scene, key = restir_shadow.shadow_problem(8, blocker=a.blocker)
    assert key in scene.parameter_names() and scene.get("blocker.vertex_positions").numel() > 8 * 3 * 10
    counts = {m: restir_shadow.sampler_for(m, scene, 1, a.edge_candidates).integrator.edge_candidates
              for m in restir_shadow.METHODS if m != "direct_projective"}
    assert set(counts.values()) == {4}
    with pytest.raises(SystemExit):
        restir_shadow.parse_args(["--blocker", "tree"])


@pytest.mark.slow  # benchmark run (4 methods compiled); CI covers edge chains in tests/integrators/test_shape_gradients.py
def test_only_restir_with_edge_chains_keeps_shadow_edge_samples_across_steps():
    """The ablation the benchmark exists for: "ReSTIR, edge chains" reuses its shadow-edge samples
    across steps (one chain per sensor and mesh, confidence gained from the second step on);
    forward-only and B.2 do not, nor does the default ReSTIR on the box (36 (edge, light) pairs
    for 256 samples: "auto" guides fresh samples); the defaults start inside the loss's basin."""
    import torch

    from torchir.functions import render

    scene, key = restir_shadow.shadow_problem(16)
    chains = {}
    for method in ("ReSTIR, edge chains", "ReSTIR", "forward-only", "B.2"):
        sampler = restir_shadow.sampler_for(method, scene, 1)
        for step in range(3):
            theta = torch.tensor([10.0 + step], requires_grad=True)
            render(scene, {key: theta}, spp=1, seed=step, sampler=sampler).sum().backward()
            assert torch.isfinite(theta.grad).all() and theta.grad.abs().item() > 0
        chains[method] = sampler.integrator._edge_chains
    (per_mesh,) = chains["ReSTIR, edge chains"].values()
    (chain,) = per_mesh.values()
    assert chain.confidence == 2.0 and chain.scale > 0  # step 1 has no floor: M = 0, 1, 2 after steps 1-3
    assert chains["ReSTIR"] == {} and chains["forward-only"] == {} and chains["B.2"] == {}
    assert restir_shadow.parse_args([]).starts == [20.0, -20.0, 30.0, -30.0]
    assert restir_shadow.parse_args([]).methods == list(restir_shadow.METHODS)
    assert restir_shadow.parse_args(["--methods", "B.2, guided edges", "ReSTIR"]).methods == ["B.2, guided edges", "ReSTIR"]
    with pytest.raises(SystemExit):
        restir_shadow.parse_args(["--methods", "RIS"])


def test_spread_table_ranks_by_variance_times_time_per_step_and_through_adams_average():
    spread = {"ReSTIR": {"mean": 2.0, "sd": 0.2, "seconds_per_step": 0.1, "var_x_time": 0.004,
                         "momentum_var": 0.008, "momentum_x_independent": 3.8},
              "B.2": {"mean": 2.0, "sd": 0.4, "seconds_per_step": 0.05, "var_x_time": 0.008,
                      "momentum_var": 0.008, "momentum_x_independent": 0.95}}
    table = restir_shadow.summarize_spread(spread, 10.0, 0.5)
    assert "alternating with 10.5 degrees" in table
    assert "| ReSTIR | 2 | 0.2 | 0.10 | 0.100 | 0.004 | 1 | 0.0008 | 2 | 3.80 |" in table
    assert "| B.2 | 2 | 0.4 | 0.20 | 0.050 | 0.008 | 2 | 0.0004 | 1 | 0.95 |" in table
    old = {name: {k: v for k, v in r.items() if not k.startswith("momentum")} for name, r in spread.items()}  # results saved before
    assert "| ReSTIR | 2 | 0.2 | 0.10 | 0.100 | 0.004 | 1 | nan | nan | nan |" in restir_shadow.summarize_spread(old, 10.0)


def test_summary_counts_converged_starts_and_when_they_settled():
    run = lambda final, ok, settled: {"final": final, "converged": ok, "steps": 5, "seconds": 1.0, "settled": settled,  # noqa: E731
                                      "last_quarter_rms": abs(final) + 1}
    table = restir_shadow.summarize({"ReSTIR": [run(1.0, True, 0.25), run(9.0, False, None)]}, 5.0)
    assert "| ReSTIR | 1 of 2 | 2.0, 10.0 | 1.0, 9.0 | 5, 5 | 2.0 | 0.2, - |" in table


def test_a_start_converges_by_its_last_quarter_not_its_last_step():
    clock = [float(t) for t in range(1, 9)]  # the last quarter: t >= 6, the last three steps
    assert restir_shadow.last_quarter_rms([30, 20, 10, 5, 1, 6, -8, 0.5], clock) == pytest.approx(math.sqrt((36 + 64 + 0.25) / 3))
    assert restir_shadow.last_quarter_rms([7.0], [0.5]) == 7.0
    assert restir_shadow.last_quarter_rms([3.0, -4.0], [0.0, 0.0]) == pytest.approx(math.sqrt(12.5))  # no time: every step


def test_settled_is_when_the_angle_entered_the_band_for_good():
    clock = [1.0, 2.0, 3.0, 4.0, 5.0]
    assert restir_shadow.settled_at([9.0, 4.0, 6.0, 3.0, 1.0], clock, 5.0) == 4.0  # left the band once: the last entry
    assert restir_shadow.settled_at([4.0, 3.0, 2.0, 1.0, 0.5], clock, 5.0) == 1.0
    assert restir_shadow.settled_at([9.0, 4.0, 3.0, 2.0, 6.0], clock, 5.0) is None  # outside at the end
    assert restir_shadow.settled_at([-4.9, 5.0], clock[:2], 5.0) is None  # the band is open: |angle| < tolerance
    assert restir_shadow.settled_at([], [], 5.0) is None


def test_adams_average_keeps_the_noise_that_steps_share():
    """Independent steps: the exponential average (beta 0.9) has (1 - beta) / (1 + beta) of their
    variance, and the same as the shuffled steps: ratio 1. Steps correlated as AR(1) with rho:
    (1 + rho beta) / (1 - rho beta) more (2.64 at rho 0.5). 4 000 steps: the variance estimate's
    relative s.e. is about 10 % (about 200 effective samples of the average), so +-30 % is 3 s.e."""
    torch = pytest.importorskip("torch")
    gen = torch.Generator(device="cpu").manual_seed(4)
    noise = torch.randn(4000, generator=gen, dtype=torch.float64, device="cpu")  # host numbers for a host function
    window, ratio = restir_shadow.momentum_variance(noise.tolist(), shuffles=4)
    assert ratio == pytest.approx(1.0, rel=0.3) and window == pytest.approx(0.1 / 1.9, rel=0.3)
    rho, ar = 0.5, torch.empty_like(noise)
    ar[0] = noise[0]
    for i in range(1, len(noise)):
        ar[i] = rho * ar[i - 1] + (1 - rho * rho) ** 0.5 * noise[i]  # unit variance, correlation rho^k
    _, ratio = restir_shadow.momentum_variance(ar.tolist(), shuffles=4)
    assert ratio == pytest.approx((1 + rho * 0.9) / (1 - rho * 0.9), rel=0.3)
    alternating = [(-1.0) ** i for i in range(200)]  # anticorrelated steps: the average cancels them
    assert restir_shadow.momentum_variance(alternating)[1] < 0.2
    assert all(math.isnan(v) for v in restir_shadow.momentum_variance([1.0, 2.0, 3.0]))  # too few steps
    assert restir_shadow.momentum_variance([2.0] * 40)[0] == 0.0  # no noise: nothing to keep


def test_sgd_steps_by_the_gradient_and_adam_by_about_its_learning_rate():
    import torch

    for argv, expected in ((["--optimizer", "sgd"], 10.0 - restir_shadow.SGD_LR * 2e-3), ([], 9.0), (["--optimizer", "sgd", "--lr", "50"], 9.9)):
        a = restir_shadow.parse_args(argv)
        theta = torch.tensor([10.0], requires_grad=True)
        opt = restir_shadow.optimizer_for(theta, a)
        theta.grad = torch.tensor([2e-3])
        opt.step()
        assert theta.item() == pytest.approx(expected, rel=1e-6), argv  # Adam's first step: lr x sign
    with pytest.raises(SystemExit):
        restir_shadow.parse_args(["--optimizer", "lbfgs"])


class _StandIn:
    """The renderer and the clock of the bench, stood in for: the image of pose ``theta`` at
    seed ``s`` is ``theta * k(s)`` (so the L2 gradient against a zero target is ``2 theta
    k(s)²``), and each render takes ``dt(s)`` seconds of a clock only renders advance."""

    def __init__(self) -> None:
        self.now, self.seeds = 0.0, []

    @staticmethod
    def k(seed: int) -> float:
        return 1.0 + 0.1 * (seed % 3)

    @staticmethod
    def dt(seed: int) -> float:
        return 0.01 * (1 + seed % 4)

    def render(self, scene, values, spp, seed, sampler=None):
        self.seeds.append(seed)
        self.now += self.dt(seed)
        (theta,) = values.values()
        return theta * self.k(seed)

    def perf_counter(self) -> float:
        return self.now


def test_spread_and_equal_time_fits_read_the_steps_the_slow_run_times(monkeypatch):
    """What the slow run's spread table and equal-time fits rest on, with known gradients and
    step times: the spread drops the first two steps (burn-in, kernels), takes the mean and sd of
    the gradients at ``--spread-angle`` only (the pose alternates), the median step time, and
    ``var_x_time = sd² x seconds``; a fit with a budget steps until its clock reaches it (the
    equal time of every method after the first), its rms over the last quarter of its time
    deciding convergence."""
    import statistics
    from types import SimpleNamespace

    import torch

    fake = _StandIn()
    monkeypatch.setattr(restir_shadow, "render", fake.render)
    monkeypatch.setattr(restir_shadow, "time", SimpleNamespace(perf_counter=fake.perf_counter))
    monkeypatch.setattr(restir_shadow, "sampler_for", lambda method, scene, burn_in, edge_candidates=1: None)
    a = restir_shadow.parse_args(["--methods", "B.2", "--spread-steps", "8", "--optimizer", "sgd", "--lr", "0.25"])
    target = torch.zeros(1)
    (row,) = restir_shadow.gradient_spread({"B.2": (None, "pose")}, target, a).values()
    seeds = range(5002, 5010)  # steps 2..9
    at_angle = [2 * 10.0 * fake.k(s) ** 2 for s in seeds if s % 2 == 0]  # even steps: 10 degrees, odd: 10.5
    assert row["mean"] == pytest.approx(statistics.fmean(at_angle)) and row["sd"] == pytest.approx(statistics.stdev(at_angle))
    assert row["seconds_per_step"] == pytest.approx(float(torch.tensor([fake.dt(s) for s in seeds]).median()))
    assert row["var_x_time"] == pytest.approx(row["sd"] ** 2 * row["seconds_per_step"])
    every = [2 * (10.0 + 0.5 * (s % 2)) * fake.k(s) ** 2 for s in seeds]
    assert (row["momentum_var"], row["momentum_x_independent"]) == pytest.approx(restir_shadow.momentum_variance(every), nan_ok=True)

    fake.now, fake.seeds = 0.0, []
    run = restir_shadow.fit(None, "pose", target, 8.0, None, a, 50, 0.1)
    clock, angles, theta = [], [], 8.0
    for step in range(50):
        theta -= 0.25 * 2 * theta * fake.k(1000 + step) ** 2  # SGD on theta² k²
        clock.append((clock[-1] if clock else 0.0) + fake.dt(1000 + step))
        angles.append(theta)
        if clock[-1] >= 0.1:
            break
    assert run["steps"] == len(angles) < 50 and clock[-1] >= 0.1 and run["seconds"] == pytest.approx(clock[-1])
    assert run["angles"] == pytest.approx(angles) and run["clock"] == pytest.approx(clock)
    assert run["last_quarter_rms"] == pytest.approx(restir_shadow.last_quarter_rms(angles, clock))
    assert run["converged"] == (run["last_quarter_rms"] < a.tolerance)
