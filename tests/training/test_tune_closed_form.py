"""``torchir tune``'s arithmetic against values worked out by hand, on synthetic gradients of
known error (``g_i = g_ref + e_i``, ``|e_i|`` chosen) and batches of known spread: the relative
errors, the reference's relative standard error and when its batches stop, the reference's own
error removed in quadrature (also where a trial measures less than it), the seconds charged per
step, the split of a trial's error into what persists and what averages out, the window score and the ranking. The trainer is replaced by fakes that hand the
recorders these gradients and timings: no scene is rendered.

(tests/training/test_tune.py already pins ``equal_time_error``, ``pareto_front`` and straight-line
``decrease_per_second``; tests/bench/test_bench_restir.py the two-step cases of
``error_beyond_reference``.)"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import pytest
import torch

from torchir.bench.restir_report import error_beyond_reference
from torchir.tune import measure
from torchir.tune.config import UserConfig
from torchir.tune.measure import Bench, Reference, _relative_se, decrease_per_second, relative_errors
from torchir.tune.search import Clock, Search
from torchir.tune.space import Setting

REF = torch.tensor([3.0, 4.0, 0.0, 0.0], dtype=torch.float64)  # |g_ref| = 5
D = torch.tensor([0.0, 0.0, 0.6, 0.8], dtype=torch.float64)  # a unit error, orthogonal to g_ref


def errors_of(norms: list[float]) -> list[torch.Tensor]:
    """Gradients ``g_ref + e_i`` with ``|e_i|`` = ``norms`` (directions varied)."""
    directions = [D, -D, torch.tensor([0.6, -0.8, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0, 0.0],
                                                                                               dtype=torch.float64)]
    return [REF + n * directions[i % 4] for i, n in enumerate(norms)]


def test_relative_errors_are_distances_over_the_reference_norm():
    """``|g_i - g_ref| / |g_ref|``: error norms 1.5, 2, 0.5, 0 against |g_ref| = 5."""
    got = relative_errors(errors_of([1.5, 2.0, 0.5, 0.0]), REF)
    assert got == pytest.approx([0.3, 0.4, 0.1, 0.0], rel=1e-12, abs=1e-15)


def test_relative_se_of_batches_of_known_spread():
    """``|sd| / sqrt(n) / |mean|`` with the unbiased sd: batches ``g_ref ± d`` alternating
    (|d| = 1, orthogonal to g_ref): n = 2: per-entry variance 2 d², |sd| / sqrt(2) = 1 -> 1/5;
    n = 4: variance 4 d²/3 -> 1 / (sqrt(3) 5); n = 5: mean g_ref + d/5, squared deviations
    3 (4/5)² + 2 (6/5)² = 4.8, variance 1.2 -> sqrt(1.2 / 5) / |g_ref + d/5|; one batch: inf."""
    def batches(n: int) -> torch.Tensor:
        return torch.stack([REF + (D if i % 2 == 0 else -D) for i in range(n)])

    assert _relative_se(batches(2)) == pytest.approx(1 / 5, rel=1e-12)
    assert _relative_se(batches(4)) == pytest.approx(1 / (math.sqrt(3) * 5), rel=1e-12)
    assert _relative_se(batches(5)) == pytest.approx(math.sqrt(1.2 / 5) / math.sqrt(25 + 1 / 25), rel=1e-12)
    assert _relative_se(batches(1)) == math.inf


@pytest.mark.parametrize("norms, ref_se", [
    ([1.5, 2.0, 0.5, 1.0], 0.15),  # one step below the reference's own error, the mean above it
    ([0.5, 0.6], 0.15),  # every step below it: no error beyond the reference's
    ([1.0, 0.25, 0.25, 0.25], 0.15),  # the mean square below it, one step above
    ([1.5, 2.0, 0.5, 1.0], 0.0),  # an exact reference
])
def test_error_beyond_reference_removes_it_in_quadrature(norms, ref_se):
    """E|g - g_ref|² = |g - g|² + |g_ref - g|² (independent errors): the trial's RMS relative
    error is sqrt(mean(e_i²) - ref_se²), 0 (not NaN) where the reference's own error is larger,
    and the s.e. is that of the mean of (e_i² - ref_se²) over the steps."""
    errors = relative_errors(errors_of(norms), REF)
    squares = [(n / 5) ** 2 - ref_se**2 for n in norms]
    mean = sum(squares) / len(squares)
    se = math.sqrt(sum((s - mean) ** 2 for s in squares) / (len(squares) - 1) / len(squares))
    rms, rms_se = error_beyond_reference(errors, ref_se)
    assert rms == pytest.approx(math.sqrt(max(mean, 0.0)), rel=1e-12, abs=0)
    assert rms_se == pytest.approx(se, rel=1e-12)
    if mean <= 0:
        assert rms == 0.0


def test_decrease_per_second_of_uneven_runs():
    """The first and last fifths (``n // 5`` points, at least one): 7 points -> the first and
    the last point; 12 -> two each; the fall over the time between their centres; NaN when that
    time is not positive or the lists differ in length."""
    times = [0.0, 1.0, 2.0, 4.0, 5.0, 7.0, 8.0]
    values = [9.0, 7.0, 8.0, 3.0, 4.0, 1.0, 2.0]
    assert decrease_per_second(times, values) == pytest.approx((9.0 - 2.0) / (8.0 - 0.0), rel=1e-12)
    times = [0.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 12.0, 16.0]
    values = [10.0, 8.0, 9.0, 9.0, 7.0, 5.0, 6.0, 3.0, 4.0, 2.0, 3.0, 1.0]
    assert decrease_per_second(times, values) == pytest.approx(((10 + 8) / 2 - (3 + 1) / 2) / ((12 + 16) / 2 - (0 + 2) / 2),
                                                               rel=1e-12)
    assert math.isnan(decrease_per_second([1.0, 1.0, 1.0], [3.0, 2.0, 1.0]))
    assert math.isnan(decrease_per_second([0.0, 1.0, 2.0], [3.0, 2.0]))


# ------------------------------------------------------------------------------ the bench, with a fake trainer
class FakeRecorder:
    """What the bench reads of ``GradientRecorder``: the gradients, the timed steps'
    seconds, the sampler's diagnostics and Stage-1 seconds; ``enough`` as the reference gives it."""

    def __init__(self, warmup: int, deadline: Optional[float], enough: Any = None) -> None:
        self.warmup, self.deadline, self.enough = warmup, deadline, enough
        self.grads: list[torch.Tensor] = []
        self.seconds: list[float] = []
        self.diagnostics: dict[str, float] = {}
        self.stage1_seconds: Optional[float] = None


def bench(monkeypatch, tmp_path: Path, max_steps: int = 50) -> Bench:
    monkeypatch.setattr(measure, "_callbacks", lambda: (FakeRecorder, None))
    return Bench(UserConfig(tmp_path / "run.yaml", {}, {"seed": 3}, {}, max_steps), tmp_path)


def fake_reference(monkeypatch, b: Bench, batches: list[torch.Tensor], seconds: float = 0.0,
                   **limits: Any) -> tuple[Reference, list[int]]:
    """``make_reference`` with the trainer replaced: step ``i`` records ``batches[i]``, and the
    run stops where the reference's ``enough`` says (or at ``max_steps``)."""
    fits = []

    def fit(module, data, callbacks, max_steps):
        (recorder,) = callbacks
        for batch in batches[:max_steps]:
            recorder.grads.append(batch)
            if recorder.enough(recorder.grads, seconds):
                break
        fits.append(len(recorder.grads))

    monkeypatch.setattr(b, "config_module", lambda setting, seed=None: object())
    monkeypatch.setattr(b, "datamodule", lambda all_views: object())
    monkeypatch.setattr(b, "_fit", fit)
    args = {"batch_spp": 4, "target_se": 0.095, "max_seconds": 60.0, **limits}
    return b.make_reference(Setting(4), **args), fits


def alternating(n: int) -> list[torch.Tensor]:
    return [REF + (D if i % 2 == 0 else -D) for i in range(n)]


def test_reference_batches_stop_at_the_target_relative_se(monkeypatch, tmp_path):
    """Batches g_ref ± d (|d| = 1, |g_ref| = 5): relative s.e. 0.1155 after 4, 0.0979 after 5,
    0.0894 after 6 (see above): a 0.095 target stops at 6 batches, with g_ref as the mean; a
    spent time limit at the 4 batches of ``min_batches``; ``max_batches`` caps the batches."""
    b = bench(monkeypatch, tmp_path)
    ref, fits = fake_reference(monkeypatch, b, alternating(64))
    assert fits == [6] and ref.batches == 6 and ref.spp == 4 * 6
    assert ref.relative_se == pytest.approx(1 / (math.sqrt(5) * 5), rel=1e-12)
    assert torch.allclose(ref.grad, REF, rtol=0, atol=1e-15) and b.reference is ref
    ref, fits = fake_reference(monkeypatch, b, alternating(64), seconds=61.0)
    assert fits == [4] and ref.relative_se == pytest.approx(1 / (math.sqrt(3) * 5), rel=1e-12)
    ref, fits = fake_reference(monkeypatch, b, alternating(64), target_se=1e-3, max_batches=8)
    assert fits == [8] and ref.relative_se == pytest.approx(1 / (math.sqrt(7) * 5), rel=1e-12)  # variance 8/7 d²


def test_a_zero_gradient_reference_gets_its_message_not_a_division_by_zero(monkeypatch, tmp_path):
    """At a starting point whose gradient is zero (the init equals the truth), the stopping rule's
    relative s.e. is infinite (never "enough": the batches run to ``max_batches``), and the
    reference stops with its own message instead of a ZeroDivisionError inside the trainer."""
    b = bench(monkeypatch, tmp_path)
    assert _relative_se(torch.zeros(4, 3, dtype=torch.float64)) == math.inf
    with pytest.raises(ValueError, match="gradient at the starting point is zero"):
        fake_reference(monkeypatch, b, [torch.zeros_like(REF) for _ in range(64)], max_batches=8)


def fake_trial(monkeypatch, b: Bench, setting: Setting, grads: list[torch.Tensor], seconds: list[float],
               diagnostics: dict[str, float] | None = None, stage1: Optional[float] = None) -> dict[str, Any]:
    """``gradient_trial`` with the trainer replaced: the recorder gets ``grads`` and ``seconds``."""
    def attempt(setting, row, recorder, all_views, max_steps):
        recorder.grads.extend(grads)
        recorder.seconds.extend(seconds)
        recorder.diagnostics = dict(diagnostics or {})
        recorder.stage1_seconds = stage1
        return None, 0.0

    monkeypatch.setattr(b, "_attempt", attempt)
    return b.gradient_trial(setting, len(grads))


def test_gradient_trial_reports_the_error_beyond_the_reference_and_the_charged_step(monkeypatch, tmp_path):
    """Through ``make_reference`` and ``gradient_trial``: six reference batches (relative s.e.
    1 / (sqrt(5) 5)) and trial gradients with error norms 1.5, 2, 0.5, 1 (relative errors 0.3, 0.4,
    0.1, 0.2): gradient_error = sqrt(mean(e²) - se²); a step is charged its median seconds plus
    ReSTIR's burn-in over the config's max_steps, or a pixel sampler's Stage 1 over its
    ``refresh_every`` (20 unless set); the error's split into a persistent part and a spread, and
    the search's score, the spread's window error."""
    b = bench(monkeypatch, tmp_path, max_steps=50)
    ref, _ = fake_reference(monkeypatch, b, alternating(64))
    se2 = 1 / 125  # (1 / (sqrt(5) 5))²
    errors = [0.3, 0.4, 0.1, 0.2]
    squares = [e * e - se2 for e in errors]
    mean = sum(squares) / 4
    want_se = math.sqrt(sum((s - mean) ** 2 for s in squares) / 3 / 4)

    restir = Setting(4, {"type": "restir", "preset": "persistent"})
    row = fake_trial(monkeypatch, b, restir, errors_of([1.5, 2.0, 0.5, 1.0]), [0.2, 0.1, 0.5, 0.3], {"time_burn_in": 3.0})
    assert row["status"] == "ran" and row["steps"] == 4
    assert row["relative_errors"] == pytest.approx(errors, rel=1e-12)
    assert row["gradient_error"] == pytest.approx(math.sqrt(mean), rel=1e-12)
    assert row["gradient_error_sq_se"] == pytest.approx(want_se, rel=1e-12)
    assert row["median_step_seconds"] == pytest.approx(0.25, rel=1e-12)
    assert row["seconds_per_step"] == pytest.approx(0.25 + 3.0 / 50, rel=1e-12)

    for sampler, period in (({"type": "adaptive", "refresh_every": 10}, 10), ({"type": "adaptive"}, 20)):
        pixel = fake_trial(monkeypatch, b, Setting(4, sampler), errors_of([1.0]), [0.1], stage1=0.4)
        assert pixel["seconds_per_step"] == pytest.approx(0.1 + 0.4 / period, rel=1e-12)
    below = fake_trial(monkeypatch, b, Setting(8), errors_of([0.5, 0.25]), [0.1, 0.1])  # mean of 0.1², 0.05² < 0.0894²
    assert below["gradient_error"] == 0.0

    # the split (split_error): the errors 1.5 D, -2 D, 0.5 (0.6, -0.8, 0, 0), (0, 1, 0, 0) have the mean
    # (0.075, 0.15, -0.075, -0.1), |mean|² = 0.04375; their spread² = (7.5 - 4 x 0.04375) / 3 / 25; nothing
    # persists beyond spread² / 4 and the reference's se², so the score is the spread's window error
    spread_sq = (7.5 - 4 * 0.04375) / 3 / 25
    assert row["step_spread"] == pytest.approx(math.sqrt(spread_sq), rel=1e-12) and row["persistent_error"] == 0.0
    search = Search(lambda setting, steps, deadline: row, Clock(None), window_seconds=2.0)
    search.measure(restir, 4)
    assert search.score(restir) == pytest.approx(math.sqrt(spread_sq * (0.25 + 0.06) / 2.0), rel=1e-12)


def test_split_error_separates_a_kept_error_from_one_that_averages_out():
    """Steps ``g_ref + b u + (-1)^i d`` (u ⟂ d, |u| = |d| = 1, |g_ref| = 5): the mean's error is
    ``b u``, the spread² about it ``n / (n - 1) |d|² / 25``; the persistent part is what the mean
    keeps beyond ``spread² / n`` and the reference's ``se²``: ``b² / 25 - 1 / ((n - 1) 25) - se²``.
    One step has no split (NaN); with b = 0 nothing persists (floored at 0)."""
    from torchir.tune.measure import split_error

    u = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    d = torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    for n, b, se in ((4, 2.0, 0.0), (6, 1.5, 0.05), (4, 0.0, 0.0)):
        grads = [REF + b * u + (d if i % 2 == 0 else -d) for i in range(n)]
        persistent, spread = split_error(grads, REF, se)
        assert spread == pytest.approx(math.sqrt(n / (n - 1) / 25), rel=1e-12)
        assert persistent == pytest.approx(math.sqrt(max(b * b / 25 - 1 / ((n - 1) * 25) - se * se, 0.0)), rel=1e-12, abs=1e-15)
    assert all(math.isnan(x) for x in split_error([REF + u], REF, 0.0))


def test_the_window_error_ranks_an_error_kept_across_steps_below_one_that_averages_out():
    """Two settings with the same per-step RMS error at the same cost: ``steady`` keeps one error
    on every step (as chains carried across steps do), ``fresh`` draws a new one each step. Their
    equal-time errors are equal; over an optimiser's window of 10 steps only ``fresh``'s averages
    out: window errors ``sqrt(p² + s² / 10)`` worked out by hand, and ``fresh`` ranks first."""
    from torchir.tune.search import OPTIMISER_WINDOW, equal_time_error, row_window_error

    b = 1.0  # |error| of every step: 0.2 relative
    u = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    d = torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    steady = [REF + b * u for _ in range(8)]
    fresh = [REF + b * (d if i % 2 == 0 else -d) for i in range(8)]
    from torchir.tune.measure import split_error

    rows = {}
    for name, grads in (("steady", steady), ("fresh", fresh)):
        errors = relative_errors(grads, REF)
        p, s_ = split_error(grads, REF, 0.0)
        rows[name] = {"gradient_error": error_beyond_reference(errors, 0.0)[0], "persistent_error": p, "step_spread": s_,
                      "seconds_per_step": 0.1}
    assert rows["steady"]["gradient_error"] == pytest.approx(rows["fresh"]["gradient_error"], rel=1e-12)
    assert equal_time_error(rows["steady"]["gradient_error"], 0.1, 1.0) == pytest.approx(equal_time_error(rows["fresh"]["gradient_error"], 0.1, 1.0))
    window = OPTIMISER_WINDOW * 0.1
    steady_p = math.sqrt(0.2**2 - 0.0)  # spread 0: all of it persists
    fresh_s = math.sqrt(8 / 7 * (b / 5) ** 2)
    fresh_p = math.sqrt(max(0.0, 0.0 - fresh_s**2 / 8))
    assert rows["steady"]["step_spread"] == 0.0 and rows["steady"]["persistent_error"] == pytest.approx(steady_p, rel=1e-12)
    assert row_window_error(rows["steady"], window) == pytest.approx(steady_p, rel=1e-12)
    assert row_window_error(rows["fresh"], window) == pytest.approx(math.sqrt(fresh_p**2 + fresh_s**2 / OPTIMISER_WINDOW), rel=1e-12)
    search = Search(lambda setting, steps, deadline: dict(rows["steady" if setting.spp == 1 else "fresh"], status="ran", steps=steps,
                                                          key=setting.key, setting=setting.label(), kind="gradient"),
                    Clock(None), window_seconds=window)
    search.measure(Setting(1), 8)
    search.measure(Setting(2), 8)
    assert search.ranked() == [Setting(2), Setting(1)]


# ------------------------------------------------------------------------------ the search's score and ranking
def test_search_scores_rank_and_keep_the_longest_successful_trial():
    """Score = error x sqrt(seconds per step) (the equal-time error at 1 s): a (0.4 at 0.04 s:
    0.08), b (0.3 at 0.09 s: 0.09), c (0.1 at 1 s: 0.1); a failed trial scores inf and is not
    ranked; a setting already measured as long is not measured again; a later failure does not
    replace a success; ``min_steps`` ranks only the trials that long."""
    a, b, c, bad = Setting(1), Setting(2), Setting(4), Setting(8)
    table = {a.key: [(0.4, 0.04)], b.key: [(0.3, 0.09), None], c.key: [(0.1, 1.0)], bad.key: [None]}
    calls = []

    def evaluate(setting: Setting, steps: int, deadline: Optional[float]) -> dict[str, Any]:
        calls.append((setting.spp, steps))
        result = table[setting.key].pop(0)
        row = {"kind": "gradient", "setting": setting.label(), "key": setting.key, "steps": steps}
        if result is None:
            return {**row, "status": "failed", "error": "boom"}
        return {**row, "status": "ran", "gradient_error": result[0], "seconds_per_step": result[1]}

    search = Search(evaluate, Clock(None))
    assert search.measure(c, 4) == pytest.approx(0.1, rel=1e-12)
    assert search.measure(b, 8) == pytest.approx(0.09, rel=1e-12)
    assert search.measure(a, 4) == pytest.approx(0.08, rel=1e-12)
    assert search.measure(bad, 4) == math.inf
    assert search.measure(a, 2) == pytest.approx(0.08, rel=1e-12)  # measured over 4 already
    assert search.measure(bad, 8) == math.inf  # a failure is not tried again
    assert search.measure(b, 16) == pytest.approx(0.09, rel=1e-12)  # failed over 16 steps: the 8-step trial stays
    assert calls == [(4, 4), (2, 8), (1, 4), (8, 4), (2, 16)]
    assert search.ranked() == [a, b, c]
    assert search.ranked(min_steps=8) == [b]
    assert search.score(Setting(32)) == math.inf
