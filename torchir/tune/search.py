"""Which settings ``torchir tune`` measures, and in what order: a cheap coordinate search with
short trials and a longer look at the best few (the default), or the full grid (``--full``).

The score of a setting that keeps the config's loss is its *window error*: the relative error of
the gradient an optimiser averages over a window of ``T`` seconds (Adam's first moment averages
about ``1 / (1 - beta1)`` = :data:`OPTIMISER_WINDOW` steps; ``T`` is that many steps of the
config's own setting), :func:`window_error`. A trial splits its error into the part that
averaged out over its steps (the spread of one step's gradient, ``s``, at ``t`` seconds per step)
and the part that did not (``p``: bias, or error that persists from step to step, as a chain kept
across steps has): ``sqrt(p² + s² t / T)``. Treating every step's error as independent
(:func:`equal_time_error`, ``e sqrt(t / T)``) favoured settings whose error persists. The
evaluator is injected (``evaluate(setting, steps) -> row``), so the search runs on synthetic rows too.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any, Callable, Optional

from .space import Setting, Space

__all__ = ["BudgetSpent", "Clock", "Search", "OPTIMISER_WINDOW", "equal_time_error", "window_error", "row_window_error",
           "pareto_front", "coordinate_search", "grid_search", "training_candidates", "with_loss_choice"]

OPTIMISER_WINDOW = 10  # steps Adam's first moment averages over: 1 / (1 - beta1), beta1 = 0.9

Evaluator = Callable[[Setting, int, Optional[float]], dict[str, Any]]  # (setting, steps, deadline) -> trial row


def equal_time_error(error: float, step_seconds: float, budget_seconds: float) -> float:
    """The gradient error after ``budget_seconds`` of averaging steps of ``step_seconds`` each:
    ``error * sqrt(step_seconds / budget_seconds)`` (variance falls as 1/time)."""
    if not (step_seconds > 0 and budget_seconds > 0):
        raise ValueError(f"seconds must be > 0, got step {step_seconds!r}, budget {budget_seconds!r}")
    return error * math.sqrt(step_seconds / budget_seconds)


def window_error(persistent: float, spread: float, step_seconds: float, window_seconds: float) -> float:
    """The relative error of the mean gradient over ``window_seconds`` of steps of ``step_seconds``
    each: ``sqrt(persistent² + spread² * step_seconds / window_seconds)``. ``spread``: one step's
    error that averages out (independent from step to step); ``persistent``: the error that does
    not (a bias, or error kept from step to step). With ``persistent = 0`` it is
    :func:`equal_time_error` of ``spread``."""
    if not (step_seconds > 0 and window_seconds > 0):
        raise ValueError(f"seconds must be > 0, got step {step_seconds!r}, window {window_seconds!r}")
    return math.sqrt(persistent * persistent + spread * spread * step_seconds / window_seconds)


def row_window_error(row: dict[str, Any], window_seconds: float) -> float:
    """:func:`window_error` of a gradient trial's row: its ``persistent_error`` and ``step_spread``
    where it measured them (two steps or more), else its whole ``gradient_error`` taken as spread."""
    persistent, spread = row.get("persistent_error"), row.get("step_spread")
    if persistent is None or spread is None or not (math.isfinite(persistent) and math.isfinite(spread)):
        persistent, spread = 0.0, row["gradient_error"]
    return window_error(persistent, spread, row["seconds_per_step"], window_seconds)


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """Which of ``points`` ``(x, y)`` (both to be minimised: seconds per step, error) no other
    point dominates (as good in both and better in one); NaN points are never on the front."""
    finite = [not (math.isnan(x) or math.isnan(y)) for x, y in points]
    out = []
    for i, (x, y) in enumerate(points):
        if not finite[i]:
            out.append(False)
            continue
        dominated = any(finite[j] and qx <= x and qy <= y and (qx < x or qy < y) for j, (qx, qy) in enumerate(points) if j != i)
        out.append(not dominated)
    return out


class BudgetSpent(Exception):
    """The time budget ran out: the search stops and keeps what it measured."""


class Clock:
    """Seconds since the start against ``budget`` (``None``: no limit)."""

    def __init__(self, budget: Optional[float]) -> None:
        if budget is not None and not budget > 0:
            raise ValueError(f"--budget must be > 0 seconds, got {budget!r}")
        self.budget, self.start = budget, time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float:
        return math.inf if self.budget is None else self.budget - self.elapsed()

    def deadline(self, reserve: float = 0.0) -> Optional[float]:
        """The ``time.perf_counter()`` value at which ``reserve`` seconds of the budget are left."""
        return None if self.budget is None else self.start + self.budget - reserve

    def text(self) -> str:
        return f"{self.elapsed():.0f}s" + ("" if self.budget is None else f"/{self.budget:.0f}s")


class Search:
    """Gradient trials run through ``evaluate`` and remembered per setting (the longest one
    counts). ``reserve``: seconds of the budget kept for what comes after the search."""

    def __init__(self, evaluate: Evaluator, clock: Clock, reserve: float = 0.0,
                 progress: Optional[Callable[[dict[str, Any]], None]] = None, window_seconds: float = 1.0) -> None:
        self.evaluate, self.clock, self.reserve, self.progress = evaluate, clock, reserve, progress
        self.window_seconds = window_seconds  # the optimiser's averaging window the scores use (run sets it)
        self.rows: list[dict[str, Any]] = []  # every trial, in order
        self.best: dict[str, dict[str, Any]] = {}  # setting key -> its longest successful trial (or its failure)
        self.settings: dict[str, Setting] = {}
        self.unavailable: dict[str, str] = {}  # sampler (json) -> why it cannot be built here

    def measure(self, setting: Setting, steps: int) -> float:
        """Measure ``setting`` over ``steps`` steps (unless already measured as long) and return
        its score; ``BudgetSpent`` when the budget (less the reserve) is gone."""
        key = setting.key
        done = self.best.get(key)
        if done is not None and (done.get("status") != "ran" or done.get("steps", 0) >= steps):
            return self.score(setting)
        if self.clock.left() <= self.reserve:
            raise BudgetSpent
        self.settings[key] = setting
        sampler = _json(setting.sampler)
        if sampler in self.unavailable:
            row = {"kind": "gradient", "setting": setting.label(), "key": key, "status": "unavailable",
                   "error": self.unavailable[sampler]}
        else:
            row = self.evaluate(setting, steps, self.clock.deadline(self.reserve))
            if row.get("status") == "unavailable":
                self.unavailable[sampler] = row.get("error", "")
        self.rows.append(row)
        if row.get("status") == "ran" or done is None:
            self.best[key] = row
        if self.progress is not None:
            self.progress(row)
        return self.score(setting)

    def score(self, setting: Setting) -> float:
        """The window error over ``window_seconds`` (:func:`row_window_error`; inf when not
        measured or failed)."""
        row = self.best.get(setting.key)
        if row is None or row.get("status") != "ran":
            return math.inf
        return row_window_error(row, self.window_seconds)

    def ranked(self, min_steps: int = 0) -> list[Setting]:
        """Measured settings, best score first (those measured over at least ``min_steps``)."""
        ok = [self.settings[k] for k, r in self.best.items() if r.get("status") == "ran" and r.get("steps", 0) >= min_steps]
        return sorted(ok, key=self.score)


def _json(spec: Any) -> str:
    import json

    return json.dumps(spec, sort_keys=True, default=str)


def coordinate_search(space: Space, search: Search, short: int, long: int, finalists: int) -> Optional[Setting]:
    """The default search. Short trials of: the config's own setting, the plain one (no sampler,
    no denoiser), every sampler alone and every denoiser alone (at the config's spp); the best
    sampler with the best denoiser when both beat plain; then the spp ladder walked from the best
    so far, one rung at a time, while the score improves. The ``finalists`` best are measured
    again over ``long`` steps and the best of those is returned (``None``: nothing ran)."""
    spp = space.base.spp
    plain = space.setting(spp)
    for setting in _unique([space.base, plain, *[space.setting(spp, sampler=s) for s in space.samplers if s is not None],
                            *[space.setting(spp, denoiser=d) for d in space.denoisers if d is not None]]):
        search.measure(setting, short)
    best_sampler = min(space.samplers, key=lambda s: search.score(space.setting(spp, sampler=s)))
    best_denoiser = min(space.denoisers, key=lambda d: search.score(space.setting(spp, denoiser=d)))
    both = space.setting(spp, best_sampler, best_denoiser)
    if best_sampler is not None and best_denoiser is not None and not both.pixel:
        search.measure(both, short)
    ranked = search.ranked()
    if not ranked:
        return None
    incumbent = ranked[0]
    ladder = space.spps
    for direction in (1, -1):
        moved, j = False, ladder.index(incumbent.spp) + direction
        while 0 <= j < len(ladder):
            candidate = space.at_spp(incumbent, ladder[j])
            if search.measure(candidate, short) >= search.score(incumbent):
                break
            incumbent, moved, j = candidate, True, j + direction
        if moved:
            break
    top = search.ranked()[:finalists]
    for setting in top:
        search.measure(setting, long)
    confirmed = search.ranked(min_steps=long)
    return confirmed[0] if confirmed else search.ranked()[0]


def grid_search(space: Space, search: Search, long: int) -> Optional[Setting]:
    """Every setting of :meth:`Space.grid` over ``long`` steps; the best (``None``: nothing ran)."""
    for setting in _unique([space.base, *space.grid()]):
        search.measure(setting, long)
    ranked = search.ranked()
    return ranked[0] if ranked else None


def training_candidates(space: Space, search: Search, chosen: Optional[Setting], full: bool) -> list[Setting]:
    """Settings to train briefly: the grid's every measured setting and its loss variants
    (``full``), else the chosen one, the config's own (the training runs check the gradient
    score: :func:`with_loss_choice`) and the chosen one with each alternative loss (LOI; on the
    best measured setting without a pixel sampler when the chosen one has one)."""
    if full:
        measured = [search.settings[k] for k, r in search.best.items() if r.get("status") == "ran"]
        return _unique([*measured, *space.loss_variants(measured)])
    out = [] if chosen is None else [chosen, space.base]
    whole = chosen if chosen is not None and not chosen.pixel else next((s for s in search.ranked() if not s.pixel), None)
    if whole is not None:
        out += space.loss_variants([whole])
    return _unique(out)


def with_loss_choice(chosen: Setting, trained: Sequence[tuple[Setting, dict[str, Any]]], factor: float = 1.5,
                     base: Optional[Setting] = None) -> tuple[Setting, str]:
    """The final setting: ``chosen``, or a loss-changing variant (``trained``: settings and their
    training rows) whose run lowered the error at least ``factor`` times faster than
    ``chosen``'s; when ``chosen``'s run did not lower the error at all the runs were too short to
    compare, and ``chosen`` stays (gradient errors cannot compare them: the loss differs). The
    config's own setting ``base`` (when trained) wins back where its run lowered the error and
    ``chosen``'s did not, or ``factor`` times faster: the gradient score at the starting point
    did not hold in training (an error kept from step to step grows stale as the parameters
    move). Returns it and why."""
    rates = {s.key: r.get("decrease_per_second", math.nan) for s, r in trained if r.get("status") == "ran"}
    rate = rates.get(chosen.key, math.nan)
    own = rates.get(base.key, math.nan) if base is not None and base.key != chosen.key else math.nan
    if own > 0 and not math.isnan(rate) and rate * factor < own:
        against = (f"while {chosen.label()}'s (the lowest window error) {'rose' if rate < 0 else 'did not fall'}" if rate <= 0
                   else f"{own / rate:.1f}x faster than {chosen.label()}'s (the lowest window error)")
        return base, f"the config's own setting: its training run lowered the error {against}"
    best, why = chosen, "the lowest window error"
    for setting, row in trained:
        other = rates.get(setting.key, math.nan)
        if setting.gradient_scored or not (rate > 0 and other > factor * rate and other > rates[best.key]):
            continue
        best = setting
        why = (f"its training run lowered the {row.get('metric', 'error')} {other / rate:.1f}x faster than "
               f"{chosen.label()}'s (a loss change: no gradient error to compare)")
    return best, why


def _unique(settings: list[Optional[Setting]]) -> list[Setting]:
    seen: dict[str, Setting] = {}
    for s in settings:
        if s is not None:
            seen.setdefault(s.key, s)
    return list(seen.values())
