#!/usr/bin/env python
"""Time per training step against the pixel budget: what a pixel-sampling step costs.

Pixel sampling (*Image-space Adaptive Sampling for Fast Inverse Rendering*, SIGGRAPH 2025) exists
to make a step cheaper than rendering the whole image; that only holds if a step's cost scales
with the pixels traced, not with fixed costs (Python, the trainer, kernel launches, Stage 1).
Every run here is the real trainer
(:func:`torchir.bench.combined.run_configuration`: ``InverseRenderingModule`` +
``ViewDataModule`` + ``lightning.pytorch.Trainer``) on ``cbox`` with an 8x8 canvas texture,
1 spp, for the uniform and the adaptive sampler at budgets from 1% to 100% of the pixels, and
the full-image render. Repetitions are the outer loop and the runs are interleaved within each,
so machine load hits every configuration alike; a ratio is taken within one repetition.

Reported per resolution, sampler and budget: the median seconds of a step (steps without a
Stage-1 refresh), the mean over all steps (Stage 1 amortised over ``refresh_every`` steps), and
both as ratios to the full-image step of the same repetition (median over repetitions).

Usage:
    torchir bench stepcost [--quick]     # or: torchir bench stepcost
    (default: 256^2 and 512^2, 30 steps, 3 repetitions; --quick: 64^2, 12 steps, 1 repetition)

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/step_cost.png``.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchir.bench import combined, environment, save_results

BUDGETS = (0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0)
SAMPLERS = ("uniform", "adaptive")
FULL = "full image"
REFRESH_EVERY = combined.ADAPTIVE["refresh_every"]
SKIP = 3  # first steps of a run left out (kernel compilation, first Stage 1)


def configurations(budgets: Sequence[float]) -> list[combined.Configuration]:
    """The full-image run, then each sampler at each budget (cbox, 1 spp)."""
    out = [combined.Configuration(FULL, "cbox", {"spp": 1})]
    for sampler in SAMPLERS:
        base = combined.UNIFORM if sampler == "uniform" else combined.ADAPTIVE
        out += [combined.Configuration(f"{sampler} {b:g}", "cbox", {"spp": 1, "sampler": {**base, "budget": b}}) for b in budgets]
    return out


def step_times(run: dict[str, Any]) -> tuple[float, float]:
    """``(median step without Stage 1, mean step with Stage 1 amortised)`` of one run, seconds.
    Stage 1 runs at the steps ``k * refresh_every``; the first ``SKIP`` steps are left out."""
    seconds = run["step_seconds"]
    kept = [s for i, s in enumerate(seconds) if i >= SKIP and i % REFRESH_EVERY != 0]
    window = seconds[REFRESH_EVERY : 2 * REFRESH_EVERY] if len(seconds) >= 2 * REFRESH_EVERY else seconds[SKIP:]
    return statistics.median(kept), statistics.fmean(window)


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (resolution, configuration): medians over repetitions of the step times and
    of their per-repetition ratios to the full-image step."""
    rows = []
    for res in dict.fromkeys(r["resolution"] for r in runs):
        for name in dict.fromkeys(r["config"] for r in runs if r["resolution"] == res):
            mine = [r for r in runs if r["resolution"] == res and r["config"] == name]
            ratios, ratios_amortised = [], []
            for r in mine:
                full = next(f for f in runs if f["resolution"] == res and f["rep"] == r["rep"] and f["config"] == FULL)
                ratios.append(r["median_step"] / full["median_step"])
                ratios_amortised.append(r["mean_step"] / full["mean_step"])
            sampler, budget = (FULL, 1.0) if name == FULL else (name.split()[0], float(name.split()[1]))
            rows.append({
                "resolution": res, "config": name, "sampler": sampler, "budget": budget,
                "median_step_seconds": statistics.median(r["median_step"] for r in mine),
                "mean_step_seconds": statistics.median(r["mean_step"] for r in mine),
                "ratio_to_full": statistics.median(ratios), "ratio_to_full_amortised": statistics.median(ratios_amortised),
                "ratio_min": min(ratios), "ratio_max": max(ratios), "reps": len(mine),
            })
    return rows


def summary(results: dict[str, Any]) -> str:
    """The suite's Markdown, from its ``results.json`` alone (the docs' results page uses it)."""
    return tables(results["rows"], {"steps": results["config"]["steps"], "reps": results["config"]["reps"]})


def tables(rows: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    lines = [
        f"# Time per step against the pixel budget (cbox, 1 spp, {meta['steps']} steps, {meta['reps']} repetition(s))", "",
        "Ratios are to the full-image step of the same repetition (median over repetitions, min-max in brackets); "
        f"'with Stage 1' averages steps {REFRESH_EVERY}-{2 * REFRESH_EVERY - 1}, one refresh included.", "",
        "| resolution | sampler | budget | s/step | ratio to full | s/step with Stage 1 | ratio with Stage 1 |", "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['resolution']}² | {r['sampler']} | {100 * r['budget']:g}% | {r['median_step_seconds']:.4f} | "
            f"{r['ratio_to_full']:.3f} [{r['ratio_min']:.3f}-{r['ratio_max']:.3f}] | {r['mean_step_seconds']:.4f} | {r['ratio_to_full_amortised']:.3f} |"
        )
    for res in dict.fromkeys(r["resolution"] for r in rows):
        five = [r for r in rows if r["resolution"] == res and r["budget"] == 0.05 and r["sampler"] != FULL]
        for r in five:
            lines.append(f"\n5% {r['sampler']} step at {res}²: {r['ratio_to_full']:.3f}x the full-image step (goal <= 0.2x at 256²)")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for res in dict.fromkeys(r["resolution"] for r in rows):
        full = next(r for r in rows if r["resolution"] == res and r["sampler"] == FULL)
        ax.axhline(full["median_step_seconds"], linestyle=":", color="grey")
        ax.annotate(f"full image {res}²", (0.011, full["median_step_seconds"] * 1.05), fontsize=8, color="grey")
        for sampler, marker in zip(SAMPLERS, "os"):
            mine = [r for r in rows if r["resolution"] == res and r["sampler"] == sampler]
            ax.plot([r["budget"] for r in mine], [r["median_step_seconds"] for r in mine], marker=marker, label=f"{sampler} {res}²")
        budgets = sorted({r["budget"] for r in rows if r["sampler"] != FULL})
        ax.plot(budgets, [b * full["median_step_seconds"] for b in budgets], "k--", linewidth=0.8, alpha=0.5,
                label="proportional to pixels" if res == rows[0]["resolution"] else None)
    ax.set(xscale="log", yscale="log", xlabel="pixel budget (fraction of the image per step)", ylabel="seconds per step (median)",
           title="Pixel-sampling step cost through the trainer (cbox, 1 spp)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "step_cost.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="64^2, 12 steps, 1 repetition, budgets 1%%, 5%%, 100%%")
    p.add_argument("--resolutions", type=int, nargs="+", default=None, help="film sizes (default 256 512)")
    p.add_argument("--steps", type=int, default=None, help="steps per run (default 30)")
    p.add_argument("--reps", type=int, default=None, help="repetitions (default 3)")
    p.add_argument("--out", default="results/bench_stepcost")
    a = p.parse_args(argv)
    a.resolutions = a.resolutions or ([64] if a.quick else [256, 512])
    a.steps = a.steps or (12 if a.quick else 2 * REFRESH_EVERY)
    a.reps = a.reps or (1 if a.quick else 3)
    a.budgets = (0.01, 0.05, 1.0) if a.quick else BUDGETS
    return a


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    out = combined.start_trainer_suite(a.out)
    configs = configurations(a.budgets)
    started = time.perf_counter()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="torchir_bench_stepcost_") as workdir:
        for res in a.resolutions:
            for config in configs:  # compile every configuration's kernels once
                combined.run_configuration(config, 10_000, res, SKIP, True, Path(workdir), target_spp=4)
            for rep in range(a.reps):
                for config in configs:
                    run = combined.run_configuration(config, rep, res, a.steps, True, Path(workdir), target_spp=4)
                    if run["status"] != "ran":
                        raise RuntimeError(f"{config.name} at {res}^2: {run.get('error')}")
                    median_step, mean_step = step_times(run)
                    runs.append({"resolution": res, "rep": rep, "config": config.name, "median_step": median_step,
                                 "mean_step": mean_step, "step_seconds": run["step_seconds"]})
                    print(f"[stepcost] {res}^2 rep {rep} {config.name}: {median_step:.4f} s/step "
                          f"({mean_step:.4f} with Stage 1)", flush=True)
    rows = summarize(runs)
    meta = {"steps": a.steps, "reps": a.reps}
    text = tables(rows, meta)
    print("\n" + text, flush=True)
    results = {"config": vars(a), "environment": environment(), "wall_seconds": time.perf_counter() - started, "rows": rows, "runs": runs}
    save_results(out, results, text)
    path = plot(rows, out)
    print(f"wrote {out}/results.json, summary.md and {path.name}", flush=True)
    return results


if __name__ == "__main__":
    main()
