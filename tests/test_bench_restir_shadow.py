"""torchir bench restir_shadow: runs end to end on a tiny problem; equal time; the table."""
from __future__ import annotations

import json

import pytest

from torchir.bench import SUITES, restir_shadow


def test_restir_shadow_runs_at_equal_time_and_writes_its_outputs(tmp_path):
    """Three of the methods (the budget-setting ReSTIR, a sampler without reuse, Mitsuba's own
    integrator without a sampler): every method's sampler is checked below without running it."""
    methods = ["ReSTIR", "B.2", "direct_projective"]
    results = restir_shadow.main(["--resolution", "16", "--starts", "10", "--steps", "3", "--burn-in", "1",
                                  "--target-spp", "16", "--spread-steps", "2", "--methods", *methods, "--out", str(tmp_path)])
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
    assert SUITES["restir_shadow"] == "torchir.bench.restir_shadow"


def test_only_the_projective_variant_leaves_edge_sampling_off_and_the_paper_baselines_go_by_length():
    scene, _ = restir_shadow.shadow_problem(8)
    flags = {m: restir_shadow.sampler_for(m, scene, 1).integrator.shadow_edge_sampling
             for m in restir_shadow.METHODS if m != "direct_projective"}
    assert flags == {"ReSTIR": True, "forward-only": True, "B.2": True, "B.2, guided edges": True, "ReSTIR, projective edges": False}
    guided = {m: restir_shadow.sampler_for(m, scene, 1).integrator.edge_guiding for m in restir_shadow.METHODS if m != "direct_projective"}
    assert guided == {"ReSTIR": True, "forward-only": False, "B.2": False, "B.2, guided edges": True, "ReSTIR, projective edges": True}


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


def test_only_full_restir_keeps_shadow_edge_chains_across_steps():
    """The ablation the benchmark exists for: ReSTIR reuses its shadow-edge samples across steps
    (one chain per sensor and mesh, confidence gained from the second step on), forward-only and
    B.2 do not; the defaults start at the fixed starts inside the loss's basin."""
    import torch

    from torchir.functions import render

    scene, key = restir_shadow.shadow_problem(16)
    chains = {}
    for method in ("ReSTIR", "forward-only", "B.2"):
        sampler = restir_shadow.sampler_for(method, scene, 1)
        for step in range(3):
            theta = torch.tensor([10.0 + step], requires_grad=True)
            render(scene, {key: theta}, spp=1, seed=step, sampler=sampler).sum().backward()
            assert torch.isfinite(theta.grad).all() and theta.grad.abs().item() > 0
        chains[method] = sampler.integrator._edge_chains
    (per_mesh,) = chains["ReSTIR"].values()
    (chain,) = per_mesh.values()
    assert chain.confidence == 2.0 and chain.scale > 0  # step 1 has no floor: M = 0, 1, 2 after steps 1-3
    assert chains["forward-only"] == {} and chains["B.2"] == {}
    assert restir_shadow.parse_args([]).starts == [20.0, -20.0, 30.0, -30.0]
    assert restir_shadow.parse_args([]).methods == list(restir_shadow.METHODS)
    assert restir_shadow.parse_args(["--methods", "B.2, guided edges", "ReSTIR"]).methods == ["B.2, guided edges", "ReSTIR"]
    with pytest.raises(SystemExit):
        restir_shadow.parse_args(["--methods", "RIS"])


def test_spread_table_ranks_by_variance_times_time():
    spread = {"ReSTIR": {"mean": 2.0, "sd": 0.2, "seconds_per_step": 0.1, "var_x_time": 0.004},
              "B.2": {"mean": 2.0, "sd": 0.4, "seconds_per_step": 0.05, "var_x_time": 0.008}}
    table = restir_shadow.summarize_spread(spread, 10.0)
    assert "| ReSTIR | 2 | 0.2 | 0.10 | 0.100 | 0.004 | 1 |" in table and "| B.2 | 2 | 0.4 | 0.20 | 0.050 | 0.008 | 2 |" in table


def test_summary_counts_converged_starts():
    run = lambda final, ok: {"final": final, "converged": ok, "steps": 5, "seconds": 1.0}  # noqa: E731
    table = restir_shadow.summarize({"ReSTIR": [run(1.0, True), run(9.0, False)]}, 5.0)
    assert "| ReSTIR | 1 of 2 | 1.0, 9.0 | 5, 5 | 2.0 |" in table
