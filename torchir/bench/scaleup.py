#!/usr/bin/env python
"""Pixel sampling at the scale users work at: 512^2, 256^2 path tracing, 16 views.

Every run is the real trainer (:func:`torchir.bench.combined.run_configuration`:
``InverseRenderingModule`` + ``ViewDataModule`` + ``lightning.pytorch.Trainer``), 1 spp, and
every configuration of a workload trains for the wall time of that workload's full-image run of
the same seed (equal time; seeds are the outer loop, configurations interleaved within a seed).

Workloads (what the experiments of *Image-space Adaptive Sampling for Fast Inverse Rendering*
(SIGGRAPH 2025, "the paper" below) have and the 32^2-128^2 suites lack: a full render per step is
expensive):

* ``cbox_512``: Cornell box with an 8x8 canvas texture on the back wall (~3 % of the image) and
  the red-wall albedo, 512^2, ``prb`` (the 128^2 setting of ``torchir bench adaptive`` at 16x the
  pixels).
* ``textured_wall_256``: a 16x16 texture covering the whole image, lit by bounced light
  (``prb`` max_depth 5, heavy-tailed noise), 256^2: every pixel matters, so this is where pixel
  sampling has the least to gain.
* ``multiview_16``: a textured sphere (32x32 texture) seen by 16 sensors of 128^2 (4.2 M pixels
  a full step), the paper's multi-view setting: the pixel samplers draw their budget across all
  16 views each step (one global index), against the full render of all views and against view
  mini-batching (2 of 16 full views per step).

Configurations: the full render at a constant learning rate (``configs/*.yaml``, lr 0.02) and
with a decay, then uniform, Eq. 5 (``loss``) and adaptive pixel sampling at 5 % of the pixels,
each with a decay. Half-lives are counted in each method's own steps and were chosen by a sweep
at 512^2 (full: 30 / 75 / none over 150 steps, 75 best; pixels: 150 / 300): a pixel step costs
~0.15x a full one, so a pixel run takes ~7x the steps in the same time. With a constant rate a
5 % pixel run levels off at a higher error than the full render (its gradient is noisier per
second); the decay lowers that floor for every method.

Measured (seed 0, 2 cores; docs/pixel-sampling.md): adaptive reaches the decayed full render's final error in
0.47x its time at 512^2; on ``textured_wall_256`` and ``multiview_16`` the full render wins
(the parameters' footprint covers most pixels). A 16-view pixel step costs 0.19x a full step
(one wavefront over every view's draws).

Reported per workload and configuration (medians over seeds): seconds per step, steps, final and
best parameter RMSE, and the wall time at which the run first reaches each reference run's final
error (the full render, constant and decayed; uniform sampling), as a fraction of that
reference's time ("never" when it does not within the equal time).

Usage:
    torchir bench scaleup [--quick]       # or: python -m torchir.bench.scaleup
    (default: every workload, 150 full steps, 2 seeds; --quick: 64^2 / 32^2 / 4 views, 20 steps, 1 seed)

Writes ``<out>/results.json``, ``<out>/summary.md``, ``<out>/curves_<workload>.png`` (error
against steps and wall time) and ``<out>/pareto.png``.
"""
from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchir.bench import combined, save_results
from torchir.bench._common import median
from torchir.bench.combined import reach_fractions  # per seed, against a reference run

__all__ = ["CONFIGURATIONS", "WORKLOADS", "Workload", "main", "reach_fractions", "summarize", "tables"]

FULL_HALF_LIFE = 75  # steps; the 512^2 sweep's best of 30 / 75 / none over 150 steps
PIXEL_HALF_LIFE = 150  # steps; 150 beat 300 at 512^2 (a pixel run takes ~7x the steps)
BUDGET = 0.05


@dataclass(frozen=True)
class Workload:
    """A scene at a size: ``model`` and ``data`` are ``InverseRenderingModule`` and
    ``ViewDataModule`` arguments; ``mini_batch``: views per step of the view mini-batching run
    (``None``: no such run)."""

    name: str
    model: dict[str, Any]
    data: dict[str, Any]
    mini_batch: int | None = None


def workloads(quick: bool) -> list[Workload]:
    """The suite's workloads (``quick``: small sizes for a smoke run)."""
    texture = {"init": 0.5, "bounds": [0.0, 1.0]}
    return [
        Workload("cbox_512", {"scene": "cbox", "resolution": 64 if quick else 512, "scene_options": {"canvas": 8},
                              "parameters": combined.CBOX_PARAMETERS}, {"target_spp": 64 if quick else 256}),
        Workload("textured_wall_256", {"scene": "textured_wall", "resolution": 32 if quick else 256, "scene_options": {"texture": 16},
                                       "parameters": {"back.bsdf.reflectance.data": texture}}, {"target_spp": 64 if quick else 256}),
        Workload("multiview_16", {"scene": "multiview", "resolution": 32 if quick else 128,
                                  "scene_options": {"views": 4 if quick else 16, "texture": 32},
                                  "parameters": {"object.bsdf.reflectance.data": texture}}, {"target_spp": 64 if quick else 256},
                 mini_batch=2),
    ]


WORKLOADS = tuple(w.name for w in workloads(False))
FULL, FULL_DECAY, UNIFORM = "full render", "full render, decay", "uniform 5%, decay"


def configurations(workload: Workload) -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    """``(name, model overrides, data overrides)`` per configuration; the first is the reference
    whose training time every other one gets."""
    pixel = {"lr_half_life": PIXEL_HALF_LIFE}
    out = [
        (FULL, {}, {}),
        (FULL_DECAY, {"lr_half_life": FULL_HALF_LIFE}, {}),
    ]
    if workload.mini_batch:
        out.append((f"{workload.mini_batch} full views per step, decay", {"lr_half_life": FULL_HALF_LIFE},
                    {"views_per_step": workload.mini_batch}))
    out += [
        (UNIFORM, {**pixel, "sampler": {**combined.UNIFORM, "budget": BUDGET}}, {}),
        ("Eq. 5 5%, decay", {**pixel, "sampler": {**combined.ADAPTIVE, "type": "loss", "budget": BUDGET}}, {}),
        ("adaptive 5%, decay", {**pixel, "sampler": {**combined.ADAPTIVE, "budget": BUDGET}}, {}),
    ]
    return out


CONFIGURATIONS = tuple(name for name, _, _ in configurations(workloads(True)[-1]))
REFERENCES = (FULL, FULL_DECAY, UNIFORM)


def run(workload: Workload, name: str, model: dict[str, Any], data: dict[str, Any], seed: int, steps: int,
        max_seconds: float | None, workdir: Path) -> dict[str, Any]:
    """One training run of ``workload`` with a configuration's overrides."""
    config = combined.Configuration(name, workload.model["scene"], {"spp": 1, **model})
    setup = {"model": workload.model, "data": {**workload.data, **data}}
    result = combined.run_configuration(config, seed, 0, steps, False, workdir, max_seconds=max_seconds, setup=setup)
    return {**result, "scene": workload.name}


# --------------------------------------------------------------------------- summarising
def summarize(runs: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per workload, one row per configuration: medians over seeds and reach fractions."""
    out: dict[str, list[dict[str, Any]]] = {}
    for workload in dict.fromkeys(r["scene"] for r in runs):
        for config in dict.fromkeys(r["config"] for r in runs if r["scene"] == workload):
            mine = [r for r in runs if r["scene"] == workload and r["config"] == config and r["status"] == "ran"]
            if not mine:
                failed = next(r for r in runs if r["scene"] == workload and r["config"] == config)
                out.setdefault(workload, []).append({"config": config, "status": failed["status"], "error": failed.get("error", "")})
                continue
            row = {
                "config": config, "status": "ran", "seeds": len(mine),
                "seconds_per_step": median([median(r["step_seconds"][1:]) for r in mine]),
                "steps": median([r["steps"] for r in mine]),
                "initial_param_error": median([r["param_error"][0] for r in mine]),
                "final_param_error": median([r["final_param_error"] for r in mine]),
                "best_param_error": median([min(r["param_error"]) for r in mine]),
                "train_seconds": median([r["train_seconds"] for r in mine]),
            }
            for ref in REFERENCES:
                fractions = reach_fractions(runs, workload, config, ref)
                row[f"reach {ref}"] = (median(fractions), sum(f == f for f in fractions), len(fractions))
            out.setdefault(workload, []).append(row)
    return out


def _cell(reach: tuple[float, int, int]) -> str:
    value, hit, total = reach
    if total == 0:
        return "-"
    return f"never (0/{total})" if hit == 0 else f"{value:.3g}x ({hit}/{total})"


def summary(results: dict[str, Any]) -> str:
    """The suite's Markdown, from its ``results.json`` alone (the docs' results page uses it)."""
    return tables(results["summary"], {"steps": results["config"]["steps"], "seeds": results["config"]["seeds"]})


def tables(summary: dict[str, list[dict[str, Any]]], meta: dict[str, Any]) -> str:
    """The suite's Markdown: one table per workload."""
    lines = [
        f"### Pixel sampling at scale, through the trainer (equal wall time, {meta['seeds']} seed(s), medians)",
        "",
        ("Every configuration trains for the wall time of the workload's full-render run (constant learning rate, "
         f"{meta['steps']} steps) of the same seed. \"x time to reach <ref>\": the wall time at which the run first "
         "reaches that reference run's final parameter RMSE, over the reference's training time (< 1: sooner; "
         "seeds that reached it in brackets). Half-lives: full renders "
         f"{FULL_HALF_LIFE} steps, pixel samplers {PIXEL_HALF_LIFE} steps; budget {BUDGET:.0%} of all pixels."),
    ]
    for workload, rows in summary.items():
        lines += ["", f"#### {workload}", "", "| configuration | s/step | steps | param RMSE init -> final | best | "
                  + " | ".join(f"x time to reach {ref}" for ref in REFERENCES) + " |", "|" + "---|" * (5 + len(REFERENCES))]
        for r in rows:
            if r["status"] != "ran":
                lines.append(f"| {r['config']} ({r['status']}) | {r['error']} |")
                continue
            lines.append(
                f"| {r['config']} | {r['seconds_per_step']:.4f} | {r['steps']:.0f} | {r['initial_param_error']:.4f} -> "
                f"{r['final_param_error']:.4f} | {r['best_param_error']:.4f} | " + " | ".join(_cell(r[f"reach {ref}"]) for ref in REFERENCES) + " |"
            )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------- main
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small sizes, 20 steps, 1 seed (a smoke run)")
    p.add_argument("--only", nargs="+", choices=WORKLOADS, default=None, help="run only these workloads")
    p.add_argument("--steps", type=int, default=None, help="steps of the full-render reference (default 150, quick 20)")
    p.add_argument("--seeds", type=int, default=None, help="number of seeds (default 2, quick 1)")
    p.add_argument("--out", default="results/bench_scaleup")
    a = p.parse_args(argv)
    a.steps = a.steps or (20 if a.quick else 150)
    a.seeds = a.seeds or (1 if a.quick else 2)
    return a


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    out = combined.start_trainer_suite(a.out)
    started = time.perf_counter()
    runs: list[dict[str, Any]] = []
    chosen = [w for w in workloads(a.quick) if a.only is None or w.name in a.only]
    with tempfile.TemporaryDirectory(prefix="torchir_bench_scaleup_") as workdir:
        for seed in range(a.seeds):
            for workload in chosen:
                budget = None
                for name, model, data in configurations(workload):
                    t0 = time.perf_counter()
                    steps = a.steps if budget is None else 50 * a.steps
                    result = run(workload, name, model, data, seed, steps, budget, Path(workdir))
                    if budget is None and result["status"] == "ran":
                        budget = result["train_seconds"]
                    runs.append(result)
                    what = (f"{result['steps']} steps, param RMSE {result['param_error'][0]:.4f} -> {result['final_param_error']:.4f}"
                            if result["status"] == "ran" else result.get("error", ""))
                    print(f"[scaleup] seed {seed} {workload.name} / {name}: {result['status']} ({time.perf_counter() - t0:.1f} s) {what}",
                          flush=True)
                (out / "results.json").write_text(json.dumps({"config": vars(a), "runs": runs}))  # nothing lost if stopped
    summarized = summarize(runs)
    text = tables(summarized, {"steps": a.steps, "seeds": a.seeds})
    print("\n" + text, flush=True)
    wall = time.perf_counter() - started
    results = {"config": vars(a), "machine": platform.platform(), "wall_seconds": wall, "summary": summarized, "runs": runs}
    save_results(out, results, text)
    plots = combined.plot_results(runs, out)
    print(f"wrote {out}/results.json, summary.md and {len(plots)} plot(s) ({wall:.0f} s)", flush=True)
    return results


if __name__ == "__main__":
    main()
