"""``torchir bench restir_antithetic``: its summary and claims from results (fast), and the quick
run end to end (slow: it compiles every method's kernels)."""
from __future__ import annotations

import json

import pytest

from torchir.bench import claims, restir_antithetic


def _results(errors: dict[str, float]) -> dict:
    methods = {name: {"seconds_per_step": 0.1, "relative_error": e, "raw_relative_error": e, "bias": 0.0,
                      "equal_time_error": e} for name, e in errors.items()}
    return {"resolution": 8, "scored_pixels": 3, "reference_error": 0.01, "budget_seconds": 0.1, "methods": methods}


def test_summary_and_claims_compare_against_shared_reservoirs(tmp_path):
    errors = {name: 1.0 for name in restir_antithetic.METHODS}
    errors.update({"material, ReSTIR": 50.0, "material, ReSTIR, antithetic": 2.0, "material, ReSTIR, antithetic, shared": 1.0})
    res = _results(errors)
    text = restir_antithetic.summarize(res, restir_antithetic.parse_args(["--blind", "0.25"]))
    assert "| material, ReSTIR | 0.100 | 50.0000 | 50.0000 | 50.00 |" in text
    assert "light size 1.0, 0 dome lights, blind 0.25)" in text
    (tmp_path / "restir_antithetic").mkdir()
    (tmp_path / "restir_antithetic" / "results.json").write_text(json.dumps(res))
    rows = [line.rsplit("|", 3)[1:3] for line in claims.claims_table(tmp_path).splitlines() if line.startswith("| restir_antithetic")]
    assert rows == [[" 2x ", " NO "], [" 50x ", " yes "]]


@pytest.mark.slow
def test_quick_run_writes_its_tables_and_plots(tmp_path):
    res = restir_antithetic.main(["--quick", "--resolution", "24", "--steps", "2", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "results.json").read_text())
    assert set(saved["methods"]) == set(restir_antithetic.METHODS)
    assert saved["scored_pixels"] > 0 and all(r["relative_error"] >= 0 for r in res["methods"].values())
    for name in ("summary.md", "antithetic.png", "derivative_images.png"):
        assert (tmp_path / name).stat().st_size > 0


def test_run_reads_each_method_s_error_less_the_reference_s_and_scales_it_to_equal_time(monkeypatch):
    """The numbers of the slow quick run, from known derivative images (the renders stood in
    for): a method's relative error is the RMS over its scored steps of ``|D - D_ref| / |D_ref|``
    on the scored pixels, the reference's own relative error removed in quadrature; warm-up
    steps are not scored; the equal-time error is that times ``sqrt(seconds per step / the
    slowest method's)`` (a faster method gets more samples in the slowest one's time), and the
    bias is the last step's summed difference over the summed |reference|."""
    import numpy as np

    ref = np.ones((4, 4, 3))
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False  # not scored: its errors below must not count
    ref_se = np.full((4, 4, 3), 0.01)
    noise = {name: 0.1 * (i + 1) for i, name in enumerate(restir_antithetic.METHODS)}  # relative error of a step
    seconds = {name: 0.1 * (i + 1) for i, name in enumerate(restir_antithetic.METHODS)}
    steps: list[tuple[str, int]] = []

    class Method:
        def __init__(self, scene, options, candidates):
            self.name = next(n for n, o in restir_antithetic.METHODS.items() if o is options)

        def step(self, spp, seed):
            steps.append((self.name, seed))
            d = ref.copy()
            d[1:] += noise[self.name] * (1 if seed % 2 else -1) * np.sqrt(45 / 36) * (1.0 + 0.5 * (seed == 101))
            d[0, 0] = 99.0  # outside the mask
            return d, seconds[self.name]

    monkeypatch.setattr(restir_antithetic, "Method", Method)
    monkeypatch.setattr(restir_antithetic, "scored_pixels", lambda scene: mask)
    monkeypatch.setattr(restir_antithetic, "reference", lambda scene, a: (ref, ref_se))
    res = restir_antithetic.run(restir_antithetic.parse_args(["--resolution", "4", "--steps", "3", "--warmup", "2"]))
    ref_error = 0.01  # |ref_se| / |ref| over the 45 scored entries
    assert res["reference_error"] == pytest.approx(ref_error) and res["scored_pixels"] == 15
    slowest = max(seconds.values())
    assert res["budget_seconds"] == pytest.approx(slowest)
    for name, r in res["methods"].items():
        # steps 100, 101, 102: relative errors c, 1.5 c, c (the 36 shifted entries of the 45 scored)
        raw = noise[name] * np.sqrt((1 + 2.25 + 1) / 3)
        assert r["raw_relative_error"] == pytest.approx(raw)
        assert r["relative_error"] == pytest.approx(np.sqrt(raw**2 - ref_error**2))
        assert r["equal_time_error"] == pytest.approx(r["relative_error"] * np.sqrt(seconds[name] / slowest))
        assert r["seconds_per_step"] == pytest.approx(seconds[name])
        assert r["bias"] == pytest.approx(-noise[name] * np.sqrt(45 / 36) * 36 / 45)  # step 102: shifted down
    assert [seed for name, seed in steps if name == "material, ReSTIR"] == [0, 1, 100, 101, 102]
