"""``torchir bench restir_silhouette``: its gains and table from results (fast), and the quick run
end to end (slow: it compiles every method's kernels)."""
from __future__ import annotations

import argparse
import json

import pytest

from torchir.bench import restir_silhouette


def test_gains_are_variance_and_variance_x_time_against_direct_projective():
    rows = {"direct_projective": {"mean": 10.0, "sd": 2.0, "seconds": 0.1, "se": 0.5},
            "RIS, 4 candidates": {"mean": 10.0, "sd": 1.0, "seconds": 0.2, "se": 0.25},
            "empty": {"mean": 0.0, "sd": 0.0, "seconds": 0.1, "se": 0.0}}
    out = restir_silhouette.compare(rows)
    assert out["direct_projective"]["variance_gain"] == pytest.approx(1.0)
    assert out["RIS, 4 candidates"]["variance_gain"] == pytest.approx(4.0)
    assert out["RIS, 4 candidates"]["equal_time_gain"] == pytest.approx(2.0)
    assert out["empty"]["variance_gain"] == float("inf")
    a = argparse.Namespace(resolution=8, samples=64, calls=3)
    text = restir_silhouette.summarize({"64": out}, a)
    assert "| 64 | RIS, 4 candidates | 10 | 0.100 | 200.0 | 4.00 | 2.00 |" in text
    assert "| 64 | empty | 0 | inf |" in text


def test_methods_and_arguments():
    names = list(restir_silhouette.methods([1, 4]))
    assert names == ["direct_projective", "RIS, 1 candidates", "RIS, 4 candidates", "ReSTIR (Alg. 5), 4 candidates",
                     f"light oracle, {restir_silhouette.ORACLE} candidates"]
    a = restir_silhouette.parse_args(["--quick"])
    assert (a.resolution, a.dome_lights, a.samples, a.calls) == (32, [0, 64], 32 * 32, 4)


@pytest.mark.slow
def test_quick_run_writes_its_tables_and_plot(tmp_path):
    res = restir_silhouette.main(["--quick", "--resolution", "24", "--calls", "3", "--dome-lights", "0", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert set(saved["results"]["0"]) == set(restir_silhouette.methods([4, 16]))
    assert all(r["sd"] > 0 and r["mean"] != 0 for r in res["0"].values())
    for name in ("summary.md", "silhouette.png"):
        assert (tmp_path / name).stat().st_size > 0


def test_measure_takes_the_spread_and_time_of_the_calls_after_the_warm_up(monkeypatch):
    """The rows ``compare`` turns into the gains of the slow quick run, from known estimates
    (the silhouette term and the clock stood in for): the mean, sd (n - 1) and s.e. of the
    ``--calls`` estimates after ``--warmup`` untimed ones (seeds ``100 + i``), and the median
    seconds of those calls; the blob is left at its lift."""
    from types import SimpleNamespace

    import drjit as dr
    import numpy as np

    import torchir.integrators._silhouettes as silhouettes

    values = {100 + i: 3.0 + 0.5 * ((7 * i) % 5) for i in range(7)}
    seconds = {100 + i: 0.01 * (1 + i % 3) for i in range(7)}
    clock, poses = [0.0], []

    def silhouette_backward(integrator, scene, sensor, adjoint, mesh, samples, seed, prev):
        assert prev is None  # RIS: no reservoirs of a step
        clock[0] += seconds[seed]
        dr.backward(poses[-1] * values[seed])

    monkeypatch.setattr(silhouettes, "silhouette_backward", silhouette_backward)
    monkeypatch.setattr(restir_silhouette, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    problem = SimpleNamespace(scene=None, adjoint=None, mesh=None, pose=poses.append)
    a = argparse.Namespace(samples=16, calls=4, warmup=3)
    row = restir_silhouette.measure(problem, {"kind": "ris", "candidates": 4}, a)
    scored = [values[s] for s in range(103, 107)]
    assert row["mean"] == pytest.approx(np.mean(scored)) and row["sd"] == pytest.approx(np.std(scored, ddof=1))
    assert row["se"] == pytest.approx(np.std(scored, ddof=1) / 2.0)
    assert row["seconds"] == pytest.approx(np.median([seconds[s] for s in range(103, 107)]))
    assert float(poses[-1][0]) == pytest.approx(restir_silhouette.LIFT) and not dr.grad_enabled(poses[-1])
