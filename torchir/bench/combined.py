#!/usr/bin/env python
"""Techniques combined: short runs of the real trainer, alone and together.

Every configuration is a real training run: :class:`~torchir.training.InverseRenderingModule` +
:class:`~torchir.training.ViewDataModule` + ``lightning.pytorch.Trainer`` (no logger, no
checkpoints), so what is measured is what ``torchir fit`` does. Seeds are the outer loop and
the configurations are interleaved within each seed (machine load drifts over the run, not
between configurations).

* ``oxalis_lite`` (the many-light canvas, ``configs/restir*.yaml``): recover the albedo texture
  with plain rendering, ReSTIR alone (Wang et al. 2023), the target-aware denoiser alone (Gu et al. 2024) and
  ReSTIR + target-aware denoiser (``configs/combined_restir_target_aware.yaml``; the denoiser
  paper reports its combination with a ReSTIR variant beating either alone). Its target is
  rendered at 4096 spp (quick: 256): at 256 spp the target's own noise set every run's final
  error (measured at 256², 600 steps: plain 0.0995, the denoiser back at 0.204 from 0.202).
* ``cbox`` with an 8x8 canvas texture (``configs/sampling_*.yaml``): the canvas texture and the
  red wall from a plain full render, uniform and adaptive pixel sampling (5% of the pixels per
  step; *Image-space Adaptive Sampling for Fast Inverse Rendering*, SIGGRAPH 2025) and a full
  render + target-aware denoiser.
* Combinations the pieces cannot do are attempted and listed with the error they raise:
  adaptive pixels + denoiser (a denoiser needs full images), adaptive pixels + LOI loss (a
  pixel-coupling loss) and LOI + ReSTIR on the moving-light problem ``glossy_highlight``
  (ReSTIR gives no light-position gradients; that scene uses Mitsuba's ``direct`` integrator).

Measured per configuration and seed: seconds per step (median after the first step, which
holds kernel compilation and ReSTIR's burn-in), paths per step (as the trainer logs
``paths_per_step``), peak resident memory of the run (``VmHWM`` after resetting it through
``/proc/self/clear_refs``), the parameter RMSE after every step against steps and wall time, and
the final image error (MSE of a ``preview_spp`` render of the final parameters against the
target). Tables give medians over seeds and ratios against the plain run of the same scene.

Usage:
    python -m torchir.bench.combined --quick   # 32^2, 40 steps, 2 seeds (a few minutes)
    python -m torchir.bench.combined           # 64^2, 150 steps, 3 seeds

Writes ``<out>/results.json``, ``<out>/summary.md``, ``<out>/curves_<scene>.png`` (parameter
error against steps and against wall time) and ``<out>/pareto.png`` (final parameter error
against total wall time, every configuration and seed, medians marked).
"""
from __future__ import annotations

import argparse
import logging
import platform
import statistics
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import backend
from ._common import fmt, markdown_table, median
from torchir.bench import save_results

__all__ = ["CONFIGURATIONS", "Configuration", "main", "plot_results", "reach_fractions", "summarize", "tables"]

OXALIS_PARAMETERS = {"canvas.bsdf.reflectance.data": {"init": 0.5, "bounds": [0.001, 1.0]}}
CBOX_PARAMETERS = {
    "canvas.bsdf.reflectance.data": {"init": 0.5, "bounds": [0.0, 1.0]},
    "red.reflectance.value": {"init": 0.3, "bounds": [0.0, 1.0]},
}
RESTIR = {"type": "restir", "candidates": 16, "neighbors": 8, "temporal": True, "spatial": True, "burn_in": 32, "grad_paths": "decorrelated"}
TARGET_AWARE = {"type": "target_aware", "radius": 7, "bandwidth": 0.1}
ADAPTIVE = {"type": "adaptive", "budget": 0.05, "refresh_every": 20, "levels": 4, "alpha": 0.1}
UNIFORM = {**ADAPTIVE, "type": "uniform"}
LR = 0.02  # every configs/*.yaml this suite mirrors (the module's own default is 0.05)


@dataclass(frozen=True)
class Configuration:
    """One run of the trainer: ``model`` holds ``InverseRenderingModule`` arguments beyond the
    scene's (``sampler``, ``denoiser``, ``loss``, ``spp``); ``expect`` is ``"run"`` or
    ``"reject"`` (a combination the pieces cannot do: attempted, and its error reported)."""

    name: str
    scene: str
    model: dict[str, Any] = field(default_factory=dict)
    expect: str = "run"
    baseline: bool = False
    note: str = ""


CONFIGURATIONS: tuple[Configuration, ...] = (
    Configuration("plain", "oxalis_lite", {"spp": 4}, baseline=True),
    Configuration("ReSTIR", "oxalis_lite", {"spp": 4, "sampler": RESTIR}),
    Configuration("target-aware denoiser", "oxalis_lite", {"spp": 4, "denoiser": TARGET_AWARE}),
    Configuration("ReSTIR + target-aware denoiser", "oxalis_lite", {"spp": 4, "sampler": RESTIR, "denoiser": TARGET_AWARE}),
    Configuration("plain (full render)", "cbox", {"spp": 1}, baseline=True),
    Configuration("uniform pixels 5%", "cbox", {"spp": 1, "sampler": UNIFORM}),
    Configuration("adaptive pixels 5%", "cbox", {"spp": 1, "sampler": ADAPTIVE}),
    Configuration("full render + target-aware denoiser", "cbox", {"spp": 1, "denoiser": TARGET_AWARE}),
    Configuration("adaptive pixels + target-aware denoiser", "cbox", {"spp": 1, "sampler": ADAPTIVE, "denoiser": TARGET_AWARE},
                  expect="reject", note="a denoiser needs full images"),
    Configuration("adaptive pixels + LOI loss", "cbox", {"spp": 1, "sampler": ADAPTIVE, "loss": {"type": "loi"}},
                  expect="reject", note="LOI couples pixels"),
    Configuration("LOI + ReSTIR (moving light)", "glossy_highlight",
                  {"spp": 1, "sampler": {**RESTIR, "burn_in": 1}, "loss": {"type": "loi", "transform": "reinhard"}},
                  expect="reject", note="ReSTIR gives no light-position gradients; the scene uses Mitsuba's direct integrator"),
)


def scene_setup(scene: str, resolution: int, quick: bool) -> dict[str, Any]:
    """``InverseRenderingModule`` scene arguments and ``ViewDataModule`` arguments of a scene."""
    if scene == "oxalis_lite":
        return {"model": {"scene": scene, "resolution": resolution, "scene_options": {"texture": 16 if quick else 32},
                          "parameters": OXALIS_PARAMETERS}, "data": {"target_spp": 256 if quick else 4096}}
    if scene == "cbox":
        return {"model": {"scene": scene, "resolution": resolution, "scene_options": {"canvas": 8}, "parameters": CBOX_PARAMETERS},
                "data": {"target_spp": 256 if quick else 512}}
    if scene == "glossy_highlight":  # only probed (one step): keep it tiny
        return {"model": {"scene": scene, "resolution": 16, "parameters": {"light.azimuth": {"init": 0.9, "bounds": [-1.6, 1.6], "truth": 0.0}}},
                "data": {"target_spp": 16}}
    raise ValueError(f"no setup for scene {scene!r}")


# ----------------------------------------------------------------------------- measuring
def _status_kb(field_name: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process; False where unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """Peak resident memory in MB: VmHWM (since the last reset), else getrusage's lifetime peak."""
    hwm = _status_kb("VmHWM")
    if hwm is not None:
        return hwm / 1024.0
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KB on Linux


def _recorder():
    import lightning.pytorch as pl

    class StepRecorder(pl.Callback):
        """Per step: seconds of the step, elapsed wall time, paths, and the parameter RMSE after
        the step (``param_error[k]``: after ``k`` steps; ``[0]`` is the initial error)."""

        def __init__(self) -> None:
            self.step_seconds: list[float] = []
            self.elapsed: list[float] = [0.0]
            self.paths: list[float] = []
            self.image_error: list[float] = []  # as logged (pixel mode: weighted error of the drawn pixels)
            self.param_error: list[float] = []

        def on_train_start(self, trainer, pl_module) -> None:
            self.truth = pl_module.ground_truth()
            self.param_error.append(pl_module.parameter_error(self.truth))
            self.start = time.perf_counter()

        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
            self.t0 = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            now = time.perf_counter()
            self.step_seconds.append(now - self.t0)
            self.elapsed.append(now - self.start)
            metrics = pl_module.step_metrics
            self.paths.append(float(metrics["paths_per_step"]) if "paths_per_step" in metrics else float("nan"))
            self.image_error.append(float(metrics["image_error"]) if "image_error" in metrics else float("nan"))
            pl_module.project_parameters()  # the error of the iterate the next step starts from
            self.param_error.append(pl_module.parameter_error(self.truth))

    return StepRecorder()


def _quiet() -> None:
    import lightning.pytorch  # noqa: F401 - it sets its loggers' levels on import: override them after

    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logging.getLogger(name).setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", module="lightning")
    warnings.filterwarnings("ignore", message=".*LOI loss.*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")


def start_trainer_suite(out: str | Path) -> Path:
    """What every suite of trainer runs does first: the variant, Lightning quiet, ``out`` made."""
    import torchir

    torchir.backend.set_variant("auto")
    _quiet()
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _error_text(error: BaseException, limit: int = 240) -> str:
    text = f"{type(error).__name__}: {error}".replace("\n", " ").replace("|", "/")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def run_configuration(
    config: Configuration, seed: int, resolution: int, steps: int, quick: bool, workdir: Path, target_spp: int | None = None,
    max_seconds: float | None = None, setup: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train ``config`` for ``steps`` steps (seed ``seed``) and return its measurements; a
    configuration that raises returns ``status`` ``"rejected"`` (construction failed) or
    ``"failed"`` (training failed) with the error. ``target_spp`` overrides the scene's;
    ``max_seconds`` stops training after that much wall time (Lightning's ``max_time``, from the
    start of training: the targets are rendered before). ``setup`` replaces
    :func:`scene_setup`'s ``{"model": ..., "data": ...}`` (other suites' workloads)."""
    import datetime

    import lightning.pytorch as pl
    import torch

    from torchir.training import InverseRenderingModule, ViewDataModule

    setup = scene_setup(config.scene, resolution, quick) if setup is None else {k: dict(v) for k, v in setup.items()}
    if target_spp is not None:
        setup["data"]["target_spp"] = target_spp
    model = {"lr": LR, **setup["model"], **config.model, "seed": seed}
    if isinstance(model.get("sampler"), dict) and model["sampler"].get("type") in ("uniform", "loss", "adaptive", "restir"):
        model["sampler"] = {**model["sampler"], "seed": seed}
    row: dict[str, Any] = {"config": config.name, "scene": config.scene, "seed": seed, "expect": config.expect, "note": config.note}
    rss_reset = _reset_peak_rss()
    rss_start = (_status_kb("VmRSS") or 0.0) / 1024.0
    try:
        module = InverseRenderingModule(**model)
    except (ValueError, TypeError) as error:
        return {**row, "status": "rejected", "stage": "construction", "error": _error_text(error)}
    pl.seed_everything(seed, verbose=False)
    recorder = _recorder()
    trainer = pl.Trainer(
        accelerator=backend.device(),
        max_steps=steps if config.expect == "run" else 1,
        max_time=None if max_seconds is None else datetime.timedelta(seconds=max_seconds),
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        log_every_n_steps=1,
        default_root_dir=str(workdir),
        callbacks=[recorder],
    )
    data = ViewDataModule(**setup["data"])
    started = time.perf_counter()
    try:
        trainer.fit(module, data)
    except Exception as error:  # noqa: BLE001 - reported, not hidden: the table shows it
        return {**row, "status": "failed", "stage": f"training step {len(recorder.step_seconds) + 1}", "error": _error_text(error)}
    fit_seconds = time.perf_counter() - started
    if module.nonfinite is not None:
        return {**row, "status": "failed", "stage": "training", "error": module.nonfinite}
    with torch.no_grad():
        image_error = statistics.fmean(
            float((module.preview(v) - target).square().mean()) for v, target in zip(data.views, data.targets)
        )
    result = {
        **row,
        "status": "ran",
        "steps": len(recorder.step_seconds),
        "step_seconds": recorder.step_seconds,
        "elapsed": recorder.elapsed,
        "paths_per_step": recorder.paths,
        "logged_image_error": recorder.image_error,
        "param_error": recorder.param_error,
        "final_param_error": module.parameter_error(module.ground_truth()),
        "final_image_error": image_error,
        "train_seconds": recorder.elapsed[-1],
        "fit_seconds": fit_seconds,
        "peak_rss_mb": _peak_rss_mb(),
        "rss_start_mb": rss_start,
        "peak_rss_is_per_run": rss_reset,
    }
    if config.expect == "reject":  # it ran although it cannot work: say so loudly
        result["status"] = "ran (expected an error)"
    return result


# --------------------------------------------------------------------------- summarising
def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians over seeds per (scene, configuration), with ratios against the scene's baseline
    (the first configuration of the scene marked ``baseline``, else its first one that ran).

    Returns ``{"scenes": {scene: [row, ...]}, "rejected": [row, ...]}``; a ran row has
    ``seconds_per_step`` (median of every seed's median step time after step 1),
    ``first_step_seconds``, ``paths_per_step``, ``peak_rss_mb``, ``final_param_error``,
    ``final_image_error``, ``train_seconds``, ``seeds`` and ``ratio_*`` entries."""
    scenes: dict[str, list[dict[str, Any]]] = {}
    rejected: list[dict[str, Any]] = []
    baselines = {c.scene: c.name for c in CONFIGURATIONS if c.baseline}
    order: list[tuple[str, str]] = []
    for run in runs:
        key = (run["scene"], run["config"])
        if run["status"] in ("rejected", "failed"):
            if not any(r["scene"] == run["scene"] and r["config"] == run["config"] for r in rejected):
                rejected.append({k: run[k] for k in ("scene", "config", "status", "stage", "error", "note", "expect") if k in run})
            continue
        if key not in order:
            order.append(key)
    for scene, name in order:
        mine = [r for r in runs if r["scene"] == scene and r["config"] == name and r["status"] not in ("rejected", "failed")]
        scenes.setdefault(scene, []).append({
            "config": name,
            "status": mine[0]["status"],
            "seeds": len(mine),
            "steps": mine[0]["steps"],
            "seconds_per_step": median([median(r["step_seconds"][1:] or r["step_seconds"]) for r in mine]),
            "first_step_seconds": median([r["step_seconds"][0] for r in mine]),
            "paths_per_step": median([median(r["paths_per_step"][1:] or r["paths_per_step"]) for r in mine]),
            "peak_rss_mb": median([r["peak_rss_mb"] for r in mine]),
            "rss_growth_mb": median([r["peak_rss_mb"] - r["rss_start_mb"] for r in mine]),
            "final_param_error": median([r["final_param_error"] for r in mine]),
            "initial_param_error": median([r["param_error"][0] for r in mine]),
            "best_param_error": median([min(r["param_error"]) for r in mine]),
            "best_step": median([float(r["param_error"].index(min(r["param_error"]))) for r in mine]),
            "final_image_error": median([r["final_image_error"] for r in mine]),
            "train_seconds": median([r["train_seconds"] for r in mine]),
        })
    for scene, rows in scenes.items():
        base = next((r for r in rows if r["config"] == baselines.get(scene)), rows[0])
        for r in rows:
            r["baseline"] = base["config"]
            reached = reach_fractions(runs, scene, r["config"], base["config"])
            r["time_to_baseline_error"] = median(reached) if reached and all(v == v for v in reached) else float("nan")
            r["reached_baseline_error"] = sum(v == v for v in reached)
            for k in ("seconds_per_step", "paths_per_step", "peak_rss_mb", "final_param_error", "final_image_error", "train_seconds"):
                r[f"ratio_{k}"] = r[k] / base[k] if base[k] else float("nan")
    return {"scenes": scenes, "rejected": rejected}


def reach_fractions(runs: list[dict[str, Any]], scene: str, config: str, baseline: str) -> list[float]:
    """Per seed: the wall time at which ``config`` first reaches the ``baseline`` run's final
    parameter error (same scene and seed), as a fraction of the baseline's training time; NaN
    if never."""
    out = []
    for run in runs:
        if run["scene"] != scene or run["config"] != config or run["status"] != "ran":
            continue
        base = next((b for b in runs if b["scene"] == scene and b["config"] == baseline and b["seed"] == run["seed"] and b["status"] == "ran"), None)
        if base is None:
            continue
        goal = base["final_param_error"]
        hit = next((t for t, e in zip(run["elapsed"], run["param_error"]) if e <= goal), None)
        out.append(hit / base["train_seconds"] if hit is not None and base["train_seconds"] else float("nan"))
    return out


def _clear(row: dict[str, Any]) -> str:
    """Whether a configuration that cannot work says so up front: a ValueError/TypeError when the
    module is built is clear; an error raised from inside a training step is not."""
    if row["status"] == "rejected":
        return "yes"
    inside = "inside Dr.Jit" if "drjit" in row.get("error", "").lower() else "during training"
    return f"no (raised {inside})"


COMBINATION = ("oxalis_lite", "ReSTIR + target-aware denoiser", ("ReSTIR", "target-aware denoiser"))


def _claim(summary: dict[str, Any]) -> list[str]:
    """The paper's claim about the combination beside our numbers (final errors, medians)."""
    scene, combined, alone = COMBINATION
    rows = {r["config"]: r for r in summary["scenes"].get(scene, [])}
    if combined not in rows or not all(a in rows for a in alone):
        return []
    table = [[name, rows[name]["final_param_error"], rows[name]["best_param_error"], rows[name]["final_image_error"],
              rows[name]["train_seconds"]] for name in (*alone, combined)]
    beats = {k: all(rows[combined][k] < rows[a][k] for a in alone) for k in ("final_param_error", "final_image_error")}
    return [
        "", f"#### Paper claim beside ours: {combined} ({scene})", "",
        ("Paper 002 (Fig. 8, TIRE scene, P-ReSTIR, relative L2 loss): the combination infers the parameters more "
        "accurately than either technique alone (shown as error maps; no number is given in the text). Ours "
        f"(direct-illumination ReSTIR, L2 loss, same steps): the combination has the lowest final parameter error: "
        f"{'yes' if beats['final_param_error'] else 'no'}; the lowest final image error: "
        f"{'yes' if beats['final_image_error'] else 'no'}."),
        "",
        *markdown_table(["configuration", "final param RMSE", "best param RMSE", "image MSE", "total s"], table),
    ]


def summary(results: dict[str, Any]) -> str:
    """The suite's Markdown, from its ``results.json`` alone (the docs' results page uses it)."""
    c = results["config"]
    meta = {"resolution": c["resolution"], "steps": c["steps"], "seeds": c["seeds"], "equal_time": c["equal_time"]}
    return tables(results["summary"], meta)


def tables(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The suite's Markdown: one table per scene (ratios against its plain run) and the table of
    rejected/unsupported combinations with their errors."""
    lines = [
        (f"### Combined techniques through the trainer ({meta['resolution']}x{meta['resolution']}, {meta['steps']} steps"
         f"{' for the baselines, their wall time for the others' if meta.get('equal_time') else ''}, "
         f"{meta['seeds']} seed(s), medians over seeds)"),
        "",
        ("Ratios are against the plain run of the same scene (time and error: < 1 is better). Seconds per step: median "
        "after the first step (which holds kernel compilation and ReSTIR's burn-in, counted in the total time). "
        "Peak RSS: the process's resident peak during the run; RSS growth: that peak minus the resident size when the "
        "run started (a warm-up pass ran every configuration first, so compilation is mostly cached). Image error: MSE of a preview render of the final parameters against the target. "
        "Best param RMSE: the lowest error along the run (needs the truth: a user cannot stop there) and its step. "
        "Paths/step: as the trainer logs it (camera paths of the primal and gradient passes; ReSTIR's light "
        "candidates, reuse and burn-in are not counted)."),
    ]
    for scene, rows in summary["scenes"].items():
        lines += ["", f"#### {scene}", ""]
        lines += markdown_table(
            ["configuration", "s/step", "x time/step", "1st step s", "total s", "x total", "x time to baseline's final error",
             "paths/step", "peak RSS MB", "RSS growth MB", "param RMSE (init -> final)", "x param err", "best param RMSE (step)",
             "image MSE", "x image err"],
            [[r["config"] + ("" if r["status"] == "ran" else f" ({r['status']})"), r["seconds_per_step"], r["ratio_seconds_per_step"],
              r["first_step_seconds"], r["train_seconds"], r["ratio_train_seconds"],
              f"{fmt(r.get('time_to_baseline_error', float('nan')))} ({r.get('reached_baseline_error', 0)}/{r['seeds']} seeds)",
              r["paths_per_step"], r["peak_rss_mb"], r["rss_growth_mb"],
              f"{fmt(r['initial_param_error'])} -> {fmt(r['final_param_error'])}", r["ratio_final_param_error"],
              f"{fmt(r['best_param_error'])} ({r['best_step']:.0f})",
              r["final_image_error"], r["ratio_final_image_error"]] for r in rows],
        )
    lines += _claim(summary)
    if summary["rejected"]:
        lines += ["", "#### Rejected / unsupported combinations", ""]
        lines += markdown_table(
            ["scene", "configuration", "outcome", "where", "clear error?", "why (expected)", "error"],
            [[r["scene"], r["config"], "rejected" if r["status"] == "rejected" else "unsupported (fails)",
              r.get("stage", ""), _clear(r), r.get("note", ""), f"`{r['error']}`"] for r in summary["rejected"]],
        )
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------- plots
def plot_results(runs: list[dict[str, Any]], out: Path) -> list[Path]:
    """``curves_<scene>.png`` (parameter RMSE against steps and wall time, one line per
    configuration and seed) and ``pareto.png`` (final parameter RMSE against total training
    time, every configuration and seed; medians as large markers). Returns the files written."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    ran = [r for r in runs if r["status"] not in ("rejected", "failed")]
    if not ran:
        return []
    names = list(dict.fromkeys(r["config"] for r in ran))
    colours = {name: plt.get_cmap("tab10")(i % 10) for i, name in enumerate(names)}
    written = []
    for scene in dict.fromkeys(r["scene"] for r in ran):
        fig, (by_step, by_time) = plt.subplots(1, 2, figsize=(11, 4))
        for r in (r for r in ran if r["scene"] == scene):
            label = r["config"] if r["seed"] == min(x["seed"] for x in ran if x["config"] == r["config"]) else None
            by_step.plot(range(len(r["param_error"])), r["param_error"], color=colours[r["config"]], alpha=0.8, label=label)
            by_time.plot(r["elapsed"], r["param_error"], color=colours[r["config"]], alpha=0.8)
        by_step.set(xlabel="step", ylabel="parameter RMSE", yscale="log", title=f"{scene}: parameter error vs steps")
        by_time.set(xlabel="wall time (s)", ylabel="parameter RMSE", yscale="log", title=f"{scene}: parameter error vs wall time")
        by_step.legend(fontsize=7)
        fig.tight_layout()
        path = out / f"curves_{scene}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(7.5, 5))
    markers = {scene: m for scene, m in zip(dict.fromkeys(r["scene"] for r in ran), "os^Dv")}
    for name in names:
        mine = [r for r in ran if r["config"] == name]
        scene = mine[0]["scene"]
        ax.scatter([r["train_seconds"] for r in mine], [r["final_param_error"] for r in mine], color=colours[name],
                   marker=markers[scene], alpha=0.45, s=22)
        ax.scatter([median([r["train_seconds"] for r in mine])], [median([r["final_param_error"] for r in mine])],
                   color=colours[name], marker=markers[scene], s=110, edgecolors="black", label=f"{scene}: {name}")
    ax.set(xlabel="total training wall time (s)", ylabel="final parameter RMSE", xscale="log", yscale="log",
           title="Pareto: error reached vs time spent (small: seeds, large: median)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "pareto.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


# ----------------------------------------------------------------------------------- main
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="32^2, 40 steps, 2 seeds")
    p.add_argument("--resolution", type=int, default=None, help="film size (default 64, quick 32)")
    p.add_argument("--steps", type=int, default=None, help="training steps per run (default 150, quick 40)")
    p.add_argument("--seeds", type=int, default=None, help="number of seeds (default 3, quick 2)")
    p.add_argument("--only", nargs="+", default=None, help="run only these scenes (oxalis_lite, cbox, glossy_highlight)")
    p.add_argument("--warmup", type=int, default=2, help="unrecorded steps per configuration before the seeds (0: none)")
    p.add_argument("--target-spp", type=int, default=None, help="samples per pixel of the targets (default: the scene's, 256-512)")
    p.add_argument("--equal-time", action="store_true",
                   help="every configuration trains for the wall time of its scene's baseline run of the same seed (at most 50x the steps)")
    p.add_argument("--out", default="results/bench_combined")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (32 if a.quick else 64)
    a.steps = a.steps or (40 if a.quick else 150)
    a.seeds = a.seeds or (2 if a.quick else 3)
    return a


def main(argv: Sequence[str] | None = None) -> None:
    a = parse_args(argv)
    out = start_trainer_suite(a.out)
    configs = [c for c in CONFIGURATIONS if a.only is None or c.scene in a.only]
    started = time.perf_counter()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="torchir_bench_combined_") as workdir:
        if a.warmup:  # compile every configuration's kernels once, so seed 0 is not charged for them
            t0 = time.perf_counter()
            for config in configs:
                if config.expect == "run":
                    run_configuration(config, 10_000, a.resolution, a.warmup, a.quick, Path(workdir), target_spp=a.target_spp)
            print(f"[combined] warm-up ({a.warmup} steps per configuration): {time.perf_counter() - t0:.1f} s", flush=True)
        for seed in range(a.seeds):
            budget: dict[str, float] = {}  # scene -> the baseline's training seconds of this seed
            for config in sorted(configs, key=lambda c: not c.baseline) if a.equal_time else configs:  # interleaved
                if config.expect == "reject" and seed > 0:
                    continue  # the error does not depend on the seed
                t0 = time.perf_counter()
                timed = a.equal_time and not config.baseline and config.scene in budget
                run = run_configuration(config, seed, a.resolution, 50 * a.steps if timed else a.steps, a.quick, Path(workdir),
                                        target_spp=a.target_spp, max_seconds=budget[config.scene] if timed else None)
                if config.baseline and run["status"] == "ran":
                    budget[config.scene] = run["train_seconds"]
                runs.append(run)
                what = (f"param RMSE {run['param_error'][0]:.4f} -> {run['final_param_error']:.4f}"
                        if "final_param_error" in run else run.get("error", ""))
                print(f"[combined] seed {seed} {config.scene} / {config.name}: {run['status']} "
                      f"({time.perf_counter() - t0:.1f} s) {what}", flush=True)
    summarized = summarize(runs)
    meta = {"resolution": a.resolution, "steps": a.steps, "seeds": a.seeds, "equal_time": a.equal_time, "wall_seconds": time.perf_counter() - started}
    text = tables(summarized, meta)
    print("\n" + text, flush=True)
    wall = time.perf_counter() - started
    results = {"config": vars(a), "machine": platform.platform(), "wall_seconds": wall, "summary": summarized, "runs": runs}
    save_results(out, results, text)
    plots = plot_results(runs, out)
    print(f"wrote {out}/results.json, summary.md and {len(plots)} plot(s) ({wall:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
