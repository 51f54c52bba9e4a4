"""``torchir tune CONFIG``: measure the settings that apply to a config, pick one, write it."""
from __future__ import annotations

import contextlib
import gc
import math
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from .config import UserConfig, read_config, write_tuned
from .measure import Bench, Reference
from .report import plot_pareto, setting_rows, table
from .search import OPTIMISER_WINDOW, BudgetSpent, Clock, Search, coordinate_search, grid_search, training_candidates, with_loss_choice
from .space import Setting, Space, config_spp, enumerate_space

__all__ = ["Effort", "EFFORTS", "tune", "default_out", "reference_batch_spp"]


@dataclass(frozen=True)
class Effort:
    """Trial lengths: gradient steps of a screening and of a confirming trial, untimed warm-up
    steps before them, finalists confirmed, seconds of each training run, and the reference's
    target relative error and time limit (seconds, at most a quarter of the budget)."""

    short: int
    long: int
    warmup: int
    finalists: int
    train_seconds: float
    ref_target_se: float
    ref_seconds: float


EFFORTS = {"default": Effort(4, 12, 2, 3, 2.0, 0.1, 30.0), "quick": Effort(3, 6, 2, 2, 1.0, 0.2, 8.0)}
REFERENCE_LANES = 2**21  # samples per reference batch (all views): its spp is this over the pixels, within [2 x top spp, 1024]


def default_out(config: Path) -> Path:
    """``<config dir>/<config stem>_tune/``."""
    return config.with_name(f"{config.stem}_tune")


def tune(config: str | Path, budget: Optional[float] = 600.0, out: Optional[str | Path] = None, full: bool = False,
         quick: bool = False, echo: Callable[[str], None] = print) -> dict[str, Any]:
    """Measure the settings of ``config`` (a ``torchir fit`` YAML), choose the one with the lowest
    window error (or a loss change that trains clearly faster), and write the
    outputs: ``<out>/summary.md`` (the table), ``results.json``, ``pareto.png`` and the tuned
    config ``<stem>.tuned.yaml`` beside ``config``. Returns the results (``results.json``'s content
    plus ``chosen_setting``, the :class:`~torchir.tune.space.Setting`, and ``out``).

    Args:
        config: the YAML file.
        budget: seconds for the whole run (``None``: no limit); the search stops when it is
            spent and keeps the best measured so far (the reference and the config's own
            setting are always measured).
        out: output folder (default :func:`default_out`).
        full: measure the whole grid (every combination, long trials, a training run each).
        quick: fewer options per key and shorter trials.
        echo: where the progress lines and the table go.
    """
    import torchir
    from ..bench import save_results
    from ..bench.combined import _quiet
    from ..training import ViewDataModule
    from ..training.cli import quiet_lightning

    clock = Clock(budget)
    user = read_config(config)
    effort = EFFORTS["quick" if quick else "default"]
    out = default_out(user.path) if out is None else Path(out)
    torchir.backend.set_variant("auto")
    _quiet()
    with quiet_lightning(), _young_garbage(), tempfile.TemporaryDirectory(prefix="torchir_tune_") as workdir:
        bench = Bench(user, Path(workdir))
        space, pixels = _space(bench, ViewDataModule, quick)
        for note in space.notes:
            echo(f"[tune] {note}")
        batch_spp = reference_batch_spp(pixels, max(space.spps))
        seconds = effort.ref_seconds if budget is None else min(effort.ref_seconds, budget / 4)
        reference = bench.make_reference(space.setting(space.base.spp), batch_spp, effort.ref_target_se, seconds)
        echo(f"[tune] reference: {reference.spp} spp in {reference.batches} batches ({reference.seconds:.1f} s), "
             f"its own relative error {reference.relative_se:.3f}; {clock.text()}")
        trials: list[dict[str, Any]] = []

        def progress(row: dict[str, Any]) -> None:
            trials.append(row)
            echo(_progress_line(len(trials), row, clock))

        def evaluate(setting: Setting, steps: int, deadline: Optional[float]) -> dict[str, Any]:
            return bench.gradient_trial(setting, steps, effort.warmup, deadline)

        reserve = 0.0 if full else (1 + len(space.losses)) * (effort.train_seconds + 2.0)  # the chosen's training runs
        search = Search(evaluate, clock, 0.0, progress)
        stopped = False
        chosen: Optional[Setting] = None
        try:
            search.measure(space.base, effort.short if not full else effort.long)  # always, whatever the budget
            base = search.best.get(space.base.key, {})
            if base.get("status") == "ran":  # scores: the gradient averaged over the optimiser's window of the config's steps
                search.window_seconds = OPTIMISER_WINDOW * base["seconds_per_step"]
            search.reserve = reserve
            chosen = grid_search(space, search, effort.long) if full else coordinate_search(
                space, search, effort.short, effort.long, effort.finalists)
        except BudgetSpent:
            stopped = True
            ranked = search.ranked()
            chosen = ranked[0] if ranked else None
        search_seconds = clock.elapsed()
        final, why = chosen, "the lowest window error"
        trained: list[tuple[Setting, dict[str, Any]]] = []
        for setting in training_candidates(space, search, chosen, full):
            if clock.left() <= 0:
                stopped = True
                break
            row = bench.training_trial(setting, effort.train_seconds, deadline=clock.deadline())
            trained.append((setting, row))
            progress(row)
        if chosen is not None:
            final, why = with_loss_choice(chosen, trained, base=space.base)
    base_row = search.best.get(space.base.key, {})
    budget_seconds = base_row.get("seconds_per_step") if base_row.get("status") == "ran" else None
    settings = {**search.settings, **{s.key: s for s, _ in trained}}
    rows = setting_rows(trials, settings, budget_seconds, final)
    lines = table(rows)
    tuned = _write_tuned(user, space, final, why, rows)
    summary = _summary(user.path, space, reference, rows, lines, final, why, tuned, clock, stopped, full, quick, budget_seconds)
    echo("\n" + summary)
    results = {"config": str(user.path), "options": {"budget": budget, "full": full, "quick": quick, "effort": effort.__dict__},
               "space": space.describe(), "reference": {"spp": reference.spp, "batches": reference.batches,
                                                         "relative_se": reference.relative_se, "seconds": reference.seconds},
               "budget_seconds_equal_time": budget_seconds, "trials": trials, "settings": rows,
               "chosen": None if final is None else {"setting": final.label(), "model": final.model_changes(), "why": why},
               "tuned_config": None if tuned is None else str(tuned), "stopped_by_budget": stopped,
               "search_seconds": search_seconds, "wall_seconds": clock.elapsed()}
    save_results(out, results, summary)
    plot = plot_pareto(rows, out / "pareto.png", f"{user.path.name}: window error vs cost")
    echo(f"[tune] wrote {out}/summary.md, results.json{', pareto.png' if plot else ''}"
         f"{'' if tuned is None else f' and {tuned}'} ({clock.elapsed():.0f} s)")
    return {**results, "chosen_setting": final, "out": out}


@contextlib.contextmanager
def _young_garbage() -> Iterator[None]:
    """Everything alive now (the imported libraries) left out of the garbage collector's scans
    for the run: each trial collects the last one's scene (a reference cycle; a live scene slows
    every later render), and a full scan of torch and Lightning took 0.2 s a trial."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def reference_batch_spp(pixels: int, top_spp: int) -> int:
    """Samples per pixel of one reference batch: :data:`REFERENCE_LANES` samples over ``pixels``
    (all views), raised to twice the largest spp tried while a batch stays within 8x that many
    samples, as a power of two in ``[1, 1024]``."""
    def floor2(n: int) -> int:
        return 2 ** max(0, max(1, n).bit_length() - 1)

    pixels = max(1, pixels)
    spp = max(floor2(REFERENCE_LANES // pixels), min(2 * top_spp, floor2(8 * REFERENCE_LANES // pixels)))
    return max(1, min(1024, spp))


def _space(bench: Bench, data_class: type, quick: bool) -> tuple[Space, int]:
    """The options for the config (its own module's scene and loss, and its targets, decide)
    and its pixel count over all views."""
    module = bench.config_module(_as_is(bench))
    pixel_ok = data_class(**bench.user.data).saturation is None
    space = enumerate_space(bench.user.model, module.scene, module.loss_fn, pixel_ok, quick)
    h, w = module.scene.resolution
    pixels = h * w * module.scene.sensor_count
    del module
    return space, pixels


def _as_is(bench: Bench) -> Setting:
    """The config's own setting (its module must build: a config error stops here)."""
    model = bench.user.model
    return Setting(config_spp(model), model.get("sampler"), model.get("denoiser"), None, model.get("spp_grad"))


def _write_tuned(user: UserConfig, space: Space, final: Optional[Setting], why: str, rows: list[dict[str, Any]]) -> Optional[Path]:
    """The tuned config beside the original, and a check that it builds (``None``: nothing chosen)."""
    if final is None:
        return None
    from ..training import InverseRenderingModule
    from .config import read_config as _read

    base = space.base.model_changes()
    changes = {k: v for k, v in final.model_changes().items() if base.get(k) != v or k not in base}
    changes = {k: v for k, v in changes.items() if not (v is None and user.model.get(k) is None)}
    row = next((r for r in rows if r["key"] == final.key), {})
    header = (f"Tuned by `torchir tune` from {user.path.name}: {final.label()} ({why}).\n"
              f"Changed: {', '.join(f'model.{k}' for k in changes) or 'nothing (the config was already the best measured)'}; "
              f"window error {row.get('window_error', math.nan):.3g}, "
              f"{row.get('seconds_per_step', math.nan):.3g} s/step.")
    path = write_tuned(user, changes, header)
    InverseRenderingModule(**{**_read(path).model, "preview_spp": 1})  # it must load as torchir fit loads it
    return path


def _progress_line(n: int, row: dict[str, Any], clock: Clock) -> str:
    """One line per trial: its number, time spent (of the budget), the setting and what it measured."""
    if row.get("status") != "ran":
        what = f"{row.get('status')}: {row.get('error', '')}"
    elif row["kind"] == "gradient":
        what = (f"{row['seconds_per_step']:.4f} s/step, gradient error {row['gradient_error']:.3g} "
                f"({row['steps']} steps)")
    else:
        what = f"{row['steps']} training steps, {row['metric']} falls {row['decrease_per_second']:.3g}/s"
    return f"[tune {n:3d}] {clock.text():>10s}  {row['kind']:8s} {row['setting']}: {what}"


def _summary(path: Path, space: Space, reference: Reference, rows: list[dict[str, Any]], lines: list[str],
             final: Optional[Setting], why: str, tuned: Optional[Path], clock: Clock, stopped: bool, full: bool, quick: bool,
             budget_seconds: Optional[float]) -> str:
    """The Markdown ``summary.md`` holds and the run prints: what was measured, the table, the choice."""
    mode = ("full grid" if full else "coordinate search") + (", quick" if quick else "")
    head = [f"### `torchir tune {path.name}` ({mode}, {clock.elapsed():.0f} s{', stopped by --budget' if stopped else ''})", ""]
    text = [
        f"Gradient error: relative norm error of the parameters' gradient at the starting point against the config's "
        f"own setting at {reference.spp} spp ({reference.batches} batches; its own error {reference.relative_se:.3f}, "
        f"removed in quadrature), RMS over the steps. Persistent: the part of it that did not average out over the "
        f"trial's steps (a bias, or error kept from step to step). Window error: the error of the gradient an optimiser "
        f"averages over {OPTIMISER_WINDOW} steps of the config as is "
        f"({'of ' + format(budget_seconds, '.3g') + ' s each' if budget_seconds else 'one second'}), "
        f"sqrt(persistent² + spread² x s/step / that time): the score. Decrease/s: how fast a short training run "
        f"lowered the error (parameter RMSE where the truth is known, else image MSE).",
        "",
        *lines, "",
        *([] if full else ["Screened only: measured over the short trial alone; the choice is made among the best few, "
                           "measured again over more steps.", ""]),
        f"Chosen: **{final.label()}** ({why})." if final is not None else "Nothing could be measured.",
    ]
    if tuned is not None:
        text.append(f"Tuned config: `{tuned}`.")
    if space.notes:
        text += ["", *[f"- {n}" for n in space.notes]]
    return "\n".join(head + text) + "\n"
