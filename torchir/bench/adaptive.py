#!/usr/bin/env python
"""Image-space adaptive pixel sampling against its baselines, at equal pixel budget.

The technique is that of *Image-space Adaptive Sampling for Fast Inverse Rendering* (SIGGRAPH 2025),
"the paper" below.

Three pixel samplers from :mod:`torchir.samplers` drive the same inverse-rendering estimator:

* ``uniform``: :class:`UniformPixelSampler` (``p_j = 1/m``);
* ``eq5``: :class:`LossPixelSampler` (``p_j ∝ sqrt(E[(∂L/∂I_j)^2])``, paper Eq. 5, Su & Gkioulekas);
* ``adaptive``: :class:`AdaptivePixelSampler` (``p_j ∝ sqrt(p1_j p2_j)``, paper Eq. 8);
* ``full`` (reference only): the full-image gradient, every pixel at 1 spp.

The estimator is the trainer's (:func:`torchir.samplers.sampled_loss`): draw ``N`` pixels, render them
with :func:`torchir.functions.render_pixels` (1 primal path and 1 independent replay path, so the
paper's Eq. 4 stays unbiased), loss ``(weight * L2Loss.pixel_terms(radiance, target, m)).sum()``,
backward. The loop is plain torch (Adam, projection to [0, 1]), not the Lightning trainer. Stage 1 runs when
``sampler.due(step, params)`` says so, and its time and paths count towards the method.

Scene: ``Scene.builtin("cbox", canvas=8)``, prb max_depth 4, an 8x8 textured canvas on
the back wall (~3% of the image). Optimised: ``canvas.bsdf.reflectance.data`` (init 0.5) and
``red.reflectance.value`` (init 0.3 grey); truth = the loaded values; L2 loss against a
high-spp target cached in ``--out``.

Parts (all by default, ``--parts`` selects):

* ``a``: trace of the gradient covariance at the initial parameters over ``--draws`` independent
  draws (fresh seeds and pixels, one pmf from one Stage 1), per budget, as ratios vs uniform;
  the full-image 1-spp gradient for reference, and ``tr x paths`` (equal-path efficiency);
  also a z-test of each sampler's mean gradient against the full-image mean (unbiasedness).
* ``b``: texture RMSE vs iterations, wall time (Stage 1 included) and paths traced, median and
  quartiles over seeds; iterations/time/paths to reach uniform's final error. The methods run
  interleaved step by step (round robin, order rotated) so machine load hits all alike.
* ``c``: Fig. 3 analogue: a rough-conductor sphere (GGX ``alpha``) behind three diffuse objects,
  box filter, prb; gradient variance of uniform, Eq. 5 and adaptive at the initial roughness.
* ``d``: the low-budget (1%) plateau: uniform vs adaptive (and mitigation knobs) for more
  iterations, per-step ESS fraction / max weight ratio from ``sampler.diagnostics()``, late
  parameter error; then gradient variances at the late parameters with a fresh and a stale pmf.

Usage:
    torchir bench adaptive            # 128x128, 5 seeds (~40 min on 2 cores)
    torchir bench adaptive --quick    # 64x64, 3 seeds (a few minutes)

Writes ``<out>/results.json`` and PNG plots.
"""
from __future__ import annotations

import json
import os
import time
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import drjit as dr
import numpy as np
import torch

import torchir
from torchir.bench import environment, save_results

from .adaptive_setup import (METHODS, RED, SMOOTH, TEX, VARIANTS, Config, Problem, VarianceResult, cbox_problem, draw_seed,
                             full_loss, glossy_problem, gradient_statistics, make_sampler, parse_args, pixel_loss,
                             ratio_interval, refresh, z_scores)

# ------------------------------------------------------------------------------ part a / c
def variance_table(rows: list[VarianceResult], baseline: dict[float | None, VarianceResult],
                   full: VarianceResult | None, zref: VarianceResult | None, label_tex: str) -> tuple[str, list[dict]]:
    """Markdown table of variance results, ratios vs the uniform row of the same budget."""
    head = (f"| budget | method | pixels | tr Cov (all) | tr Cov ({label_tex}) | uniform/method (all) [90% CI] | uniform/method ({label_tex}) "
            f"| tr x paths rel. uniform | predicted gain | ESS frac | max w ratio | ms/draw | Stage 1 s | max abs z vs full | frac abs z>3 |")
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    records = []
    for r in rows:
        base = baseline.get(r.budget, next(iter(baseline.values())))  # full row: vs the first budget's uniform
        ratio_all = base.trace_all / r.trace_all if r.trace_all > 0 else float("inf")
        ratio_tex = base.trace_tex / r.trace_tex if r.trace_tex > 0 else float("inf")
        eff = (r.trace_all * r.paths_per_draw) / (base.trace_all * base.paths_per_draw)
        ci = ratio_interval(base, r)
        z = z_scores(r, zref) if zref is not None and r is not zref else np.array([])
        zmax = float(np.abs(z).max()) if z.size else float("nan")
        zfrac = float((np.abs(z) > 3).mean()) if z.size else float("nan")
        budget = "all (1 spp)" if r.budget is None else f"{r.budget:.0%}"
        lines.append(
            f"| {budget} | {r.method} | {r.pixels} | {r.trace_all:.3e} | {r.trace_tex:.3e} | {ratio_all:.2f}x [{ci[0]:.2f}, {ci[1]:.2f}] | {ratio_tex:.2f}x "
            f"| {eff:.3f} | {r.predicted_gain:.2f} | {r.ess_fraction:.2f} | {r.max_weight_ratio:.2f} | {r.seconds_per_draw * 1e3:.1f} "
            f"| {r.stage1_seconds:.2f} | {zmax:.2f} | {zfrac:.3f} |"
        )
        records.append({**{k: v for k, v in asdict(r).items() if k not in ("mean", "var")}, "ratio_vs_uniform_all": ratio_all,
                        "ratio_vs_uniform_first_param": ratio_tex, "ratio_vs_uniform_all_ci90": list(ci), "trace_x_paths_rel_uniform": eff, "max_abs_z_vs_full": zmax,
                        "frac_abs_z_gt_3": zfrac, "z_components": int(z.size)})
    return "\n".join(lines), records


def part_a(cfg: Config, problem: Problem, out: Path) -> dict[str, Any]:
    print(f"\n[a] gradient covariance at the initial parameters, {cfg.draws} draws per estimator", flush=True)
    rows: list[VarianceResult] = []
    pmfs: dict[str, np.ndarray] = {}
    full = gradient_statistics(problem, "full", None, cfg.draws, problem.init, seed=11)
    print(f"  full 1 spp: tr {full.trace_all:.3e}, {full.seconds_per_draw * 1e3:.1f} ms/draw", flush=True)
    for budget in cfg.budgets:
        for k, method in enumerate(METHODS):
            sampler = make_sampler(problem, method, budget, seed=100 + k)
            r = gradient_statistics(problem, method, budget, cfg.draws, problem.init, seed=100 + k, sampler=sampler)
            rows.append(r)
            if budget == cfg.budgets[0]:
                pmfs[method] = sampler.pdf_image()[0].cpu().numpy().copy()
            print(f"  {budget:.0%} {method:<9} tr {r.trace_all:.3e} (tex {r.trace_tex:.3e}), gain {r.predicted_gain:.2f}, "
                  f"{r.seconds_per_draw * 1e3:.1f} ms/draw, Stage 1 {r.stage1_seconds:.2f} s", flush=True)
    baseline = {r.budget: r for r in rows if r.method == "uniform"}
    table, records = variance_table(rows + [full], baseline, full, full, "tex")
    plot_pmfs(out / "a_pmfs.png", problem, pmfs, f"pmfs at the initial parameters, {cfg.budgets[0]:.0%} budget")
    return {"table": table, "rows": records}


def part_c(cfg: Config, out: Path) -> dict[str, Any]:
    problem = glossy_problem(cfg, out)
    budget = cfg.budgets[0]
    print(f"\n[c] glossy Fig. 3 analogue: {cfg.glossy_resolution}x{cfg.glossy_resolution}, d/d alpha at alpha={cfg.glossy_init} "
          f"(truth {cfg.glossy_truth}), {budget:.0%} budget, {cfg.glossy_draws} draws", flush=True)
    rows, pmfs = [], {}
    for k, method in enumerate(METHODS):
        sampler = make_sampler(problem, method, budget, seed=300 + k)
        r = gradient_statistics(problem, method, budget, cfg.glossy_draws, problem.init, seed=300 + k, sampler=sampler)
        rows.append(r)
        pmfs[method] = sampler.pdf_image()[0].cpu().numpy().copy()
        print(f"  {method:<9} var {r.trace_all:.3e}, gain {r.predicted_gain:.2f}", flush=True)
    full = gradient_statistics(problem, "full", None, cfg.glossy_draws, problem.init, seed=31)
    table, records = variance_table(rows + [full], {budget: rows[0]}, full, full, "alpha")
    by = {r.method: r for r in rows}
    eq5_over_adaptive = by["eq5"].trace_all / by["adaptive"].trace_all
    ci = ratio_interval(by["eq5"], by["adaptive"])
    plot_pmfs(out / "c_glossy_pmfs.png", problem, pmfs, f"glossy scene pmfs, {budget:.0%} budget")
    return {"table": table, "rows": records, "eq5_over_adaptive": eq5_over_adaptive, "eq5_over_adaptive_ci90": list(ci),
            "target_seconds": problem.target_seconds, "init": cfg.glossy_init, "truth": cfg.glossy_truth}


# ------------------------------------------------------------------------------ optimisation
class Run:
    """One optimisation run: torch Adam on leaf tensors, projection to [0, 1], one estimator."""

    def __init__(self, problem: Problem, label: str, strategy: str, budget: float, seed: int, lr: float, **options: Any) -> None:
        self.problem, self.label, self.strategy, self.seed = problem, label, strategy, seed
        self.values = problem.leaves()
        self.opt = torch.optim.Adam(list(self.values.values()), lr=lr)
        self.sampler = None if strategy == "full" else make_sampler(problem, strategy, budget, seed, **options)
        self.rmse = [self.tex_rmse()]
        self.red_err = [self.red_error()]
        self.seconds, self.paths = [0.0], [0.0]  # cumulative, index 0 = before the first step
        self.stage1_seconds, self.refresh_steps = 0.0, []
        self.ess, self.max_weight, self.gain = [], [], []

    def tex_rmse(self) -> float:
        return float((self.values[TEX].detach() - self.problem.truth[TEX]).square().mean().sqrt())

    def red_error(self) -> float:
        return float((self.values[RED].detach() - self.problem.truth[RED]).abs().max())

    def step(self, it: int) -> None:
        p = self.problem
        dr.sync_thread()
        t0 = time.perf_counter()
        paths = 0.0
        if self.sampler is not None and self.sampler.due(it, self.values):
            refresh(p, self.sampler, self.values, it)
            stats = self.sampler.diagnostics()
            paths += stats.get("stage1_paths", 0.0)
            self.stage1_seconds += stats.get("stage1_seconds", 0.0)
            self.refresh_steps.append(it)
            self.gain.append(stats.get("predicted_gain", 1.0))
        seed = draw_seed(self.seed, it, zlib.crc32(self.label.encode()))
        if self.sampler is None:
            loss, n = full_loss(p, self.values, seed)
        else:
            loss, n = pixel_loss(p, self.sampler, self.values, seed)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        with torch.no_grad():
            for v in self.values.values():
                v.clamp_(0.0, 1.0)
        dr.sync_thread()
        self.seconds.append(self.seconds[-1] + time.perf_counter() - t0)
        self.paths.append(self.paths[-1] + paths + n)
        self.rmse.append(self.tex_rmse())
        self.red_err.append(self.red_error())
        if self.sampler is not None:
            d = self.sampler.diagnostics()
            self.ess.append(d.get("ess_fraction", 1.0))
            self.max_weight.append(d.get("max_weight_ratio", 1.0))


def run_interleaved(runs: list[Run], iters: int, tag: str) -> None:
    """All runs advance one step at a time, round robin, the order rotated every step."""
    t0 = time.perf_counter()
    for it in range(iters):
        k = it % len(runs)
        for run in runs[k:] + runs[:k]:
            run.step(it)
        if (it + 1) % max(1, iters // 5) == 0:
            groups: dict[str, list[float]] = {}
            for r in runs:
                groups.setdefault(r.label, []).append(r.rmse[-1])
            print(f"  [{tag}] it {it + 1}/{iters} ({time.perf_counter() - t0:.0f} s): "
                  + ", ".join(f"{k} {np.median(v):.4f}" for k, v in groups.items()), flush=True)


def smooth(curve: np.ndarray, window: int = SMOOTH) -> np.ndarray:
    """Trailing moving average (the first entries average what is there)."""
    c = np.cumsum(np.insert(curve, 0, 0.0))
    idx = np.arange(1, len(curve) + 1)
    lo = np.maximum(0, idx - window)
    return (c[idx] - c[lo]) / (idx - lo)


@dataclass
class Curves:
    """Per-method curves over seeds: (seeds, iters + 1) arrays."""

    rmse: np.ndarray
    seconds: np.ndarray
    paths: np.ndarray

    @property
    def median(self) -> np.ndarray:
        return np.median(np.stack([smooth(r) for r in self.rmse]), 0)

    def quartiles(self) -> tuple[np.ndarray, np.ndarray]:
        s = np.stack([smooth(r) for r in self.rmse])
        return np.percentile(s, 25, 0), np.percentile(s, 75, 0)


def curves_of(runs: list[Run], label: str) -> Curves:
    mine = [r for r in runs if r.label == label]
    return Curves(np.array([r.rmse for r in mine]), np.array([r.seconds for r in mine]), np.array([r.paths for r in mine]))


def reach(c: Curves, level: float) -> int | None:
    """First iteration whose smoothed median RMSE is <= ``level`` (None if never)."""
    hit = np.nonzero(c.median <= level)[0]
    return int(hit[0]) if hit.size else None


def optimisation_table(runs: list[Run], labels: Sequence[str], reference: str = "uniform") -> tuple[str, list[dict], float]:
    """Markdown table: final error (median, IQR), time per iteration, and iterations / time /
    paths to reach the reference's final smoothed median error, as ratios."""
    curves = {lab: curves_of(runs, lab) for lab in labels}
    ref = curves[reference]
    level = float(ref.median[-1])
    ref_it = reach(ref, level)
    ref_time = float(np.median(ref.seconds[:, ref_it]))
    ref_paths = float(np.median(ref.paths[:, ref_it]))
    head = ("| method | seeds | RMSE init | final RMSE median [q25, q75] | min RMSE (median) | s/iter | Stage 1 share | paths/iter "
            f"| it to {reference} final | time to it (s) | time ratio vs {reference} | paths ratio vs {reference} | red albedo max abs err |")
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    records = []
    for lab in labels:
        c, mine = curves[lab], [r for r in runs if r.label == lab]
        q25, q75 = (float(v[-1]) for v in c.quartiles())
        it = reach(c, level)
        t = float(np.median(c.seconds[:, it])) if it is not None else None
        pth = float(np.median(c.paths[:, it])) if it is not None else None
        iters = c.rmse.shape[1] - 1
        s_iter = float(np.median(c.seconds[:, -1])) / iters
        share = float(np.median([r.stage1_seconds / r.seconds[-1] for r in mine]))
        p_iter = float(np.median(c.paths[:, -1])) / iters
        rec = {
            "method": lab, "seeds": len(mine), "rmse_init": float(c.rmse[0, 0]), "final_rmse_median": float(c.median[-1]),
            "final_rmse_q25": q25, "final_rmse_q75": q75, "min_rmse_median": float(c.median.min()), "seconds_per_iter": s_iter,
            "stage1_share": share, "paths_per_iter": p_iter, "iters_to_reference_final": it, "seconds_to_reference_final": t,
            "paths_to_reference_final": pth, "time_ratio": None if t is None or not ref_time else t / ref_time,
            "paths_ratio": None if pth is None or not ref_paths else pth / ref_paths,  # 0: reached at the start
            "final_red_abs_err_median": float(np.median([r.red_err[-1] for r in mine])),
            "reference_total_seconds": float(np.median(ref.seconds[:, -1])),
        }
        records.append(rec)
        fmt = lambda v, f: "never" if v is None else format(v, f)
        lines.append(
            f"| {lab} | {len(mine)} | {rec['rmse_init']:.4f} | {rec['final_rmse_median']:.4f} [{q25:.4f}, {q75:.4f}] "
            f"| {rec['min_rmse_median']:.4f} | {s_iter:.4f} | {share:.2f} | {p_iter:.0f} | {fmt(it, 'd')} | {fmt(t, '.1f')} "
            f"| {fmt(rec['time_ratio'], '.2f')} | {fmt(rec['paths_ratio'], '.2f')} | {rec['final_red_abs_err_median']:.4f} |"
        )
    lines.append(f"(reference level: {reference}'s final smoothed median RMSE {level:.4f}, reached at it {ref_it} "
                 f"in {ref_time:.1f} s; smoothing: trailing mean over {SMOOTH} iterations per seed, then median over seeds)")
    return "\n".join(lines), records, level


def part_b(cfg: Config, problem: Problem, out: Path) -> dict[str, Any]:
    budget = cfg.budgets[0]
    print(f"\n[b] parameter error, {budget:.0%} budget, {cfg.seeds} seeds x {cfg.iters} iterations, methods interleaved", flush=True)
    runs: list[Run] = []
    labels = (*METHODS, "full")
    for seed in range(cfg.seeds):
        seed_runs = [Run(problem, lab, lab, budget, 1000 + seed, cfg.lr) for lab in labels]
        run_interleaved(seed_runs, cfg.iters, f"seed {seed}")
        runs += seed_runs
    table, records, level = optimisation_table(runs, labels)
    plot_error(out / "b_rmse.png", runs, labels, level, f"cbox canvas {cfg.resolution}², {budget:.0%} budget, {cfg.seeds} seeds")
    goal = next(r for r in records if r["method"] == "adaptive")["time_ratio"]
    return {"table": table, "rows": records, "reference_level": level, "adaptive_time_ratio": goal,
            "curves": {r.label + f"/seed{r.seed}": {"rmse": r.rmse, "seconds": r.seconds, "paths": r.paths, "red_abs_err": r.red_err}
                       for r in runs}}


def part_d(cfg: Config, problem: Problem, out: Path) -> dict[str, Any]:
    budget = cfg.low_budget
    labels = ("uniform", *cfg.plateau_variants)
    print(f"\n[d] low-budget plateau: {budget:.0%} budget, {cfg.plateau_seeds} seeds x {cfg.plateau_iters} iterations: "
          f"{', '.join(labels)}", flush=True)
    runs: list[Run] = []
    for seed in range(cfg.plateau_seeds):
        seed_runs = [Run(problem, lab, VARIANTS[lab][0], budget, 2000 + seed, cfg.lr, **VARIANTS[lab][1]) for lab in labels]
        run_interleaved(seed_runs, cfg.plateau_iters, f"seed {seed}")
        runs += seed_runs
    table, records, level = optimisation_table(runs, labels)
    # late-run behaviour: last quarter of the run
    late = cfg.plateau_iters * 3 // 4
    head = "| method | late RMSE median (last 25%) | late RMSE / uniform | ESS frac (median, late) | ESS frac min | max w ratio (median) | max w ratio max | predicted gain at refreshes (first -> last, median) | refreshes |"
    diag = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    uni_late = float(np.median([np.mean(r.rmse[late:]) for r in runs if r.label == "uniform"]))
    diag_records = []
    for lab in labels:
        mine = [r for r in runs if r.label == lab]
        late_rmse = float(np.median([np.mean(r.rmse[late:]) for r in mine]))
        ess = np.array([r.ess[late:] for r in mine]) if mine[0].ess else np.ones(1)
        mw = np.array([r.max_weight[late:] for r in mine]) if mine[0].max_weight else np.ones(1)
        gains = [(r.gain[0], r.gain[-1]) for r in mine if r.gain]
        g0 = float(np.median([g[0] for g in gains])) if gains else 1.0
        g1 = float(np.median([g[1] for g in gains])) if gains else 1.0
        refreshes = int(np.median([len(r.refresh_steps) for r in mine]))
        rec = {"method": lab, "late_rmse_median": late_rmse, "late_rmse_over_uniform": late_rmse / uni_late,
               "late_ess_fraction_median": float(np.median(ess)), "late_ess_fraction_min": float(np.min(ess)),
               "late_max_weight_ratio_median": float(np.median(mw)), "late_max_weight_ratio_max": float(np.max(mw)),
               "gain_first": g0, "gain_last": g1, "refreshes": refreshes}
        diag_records.append(rec)
        diag.append(f"| {lab} | {late_rmse:.4f} | {late_rmse / uni_late:.3f} | {rec['late_ess_fraction_median']:.3f} "
                    f"| {rec['late_ess_fraction_min']:.3f} | {rec['late_max_weight_ratio_median']:.2f} | {rec['late_max_weight_ratio_max']:.2f} "
                    f"| {g0:.2f} -> {g1:.2f} | {refreshes} |")
    plot_error(out / "d_rmse_low_budget.png", runs, labels, level, f"cbox canvas {cfg.resolution}², {budget:.0%} budget, {cfg.plateau_seeds} seeds")
    plot_diagnostics(out / "d_diagnostics.png", runs, labels)

    # Gradient variance late in the run: at the final parameters of uniform's median seed.
    uni = sorted((r for r in runs if r.label == "uniform"), key=lambda r: r.rmse[-1])
    late_values = {k: v.detach().clone() for k, v in uni[len(uni) // 2].values.items()}
    print(f"  [d] gradient variance at uniform's final parameters (RMSE {uni[len(uni) // 2].rmse[-1]:.4f}), "
          f"{cfg.late_draws} draws each", flush=True)
    late_rows = []
    for k, method in enumerate(METHODS):
        r = gradient_statistics(problem, method, budget, cfg.late_draws, late_values, seed=500 + k)
        late_rows.append(r)
    for lab in cfg.plateau_variants:
        if lab == "adaptive":
            continue
        strategy, options = VARIANTS[lab]
        sampler = make_sampler(problem, strategy, budget, 520, **options)
        late_rows.append(gradient_statistics(problem, strategy, budget, cfg.late_draws, late_values, seed=520, sampler=sampler, label=lab))
    # stale pmf: adaptive pmf from the initial parameters, used at the late parameters
    stale = make_sampler(problem, "adaptive", budget, 530)
    refresh(problem, stale, problem.leaves(), 0)
    late_rows.append(gradient_statistics(problem, "adaptive", budget, cfg.late_draws, late_values, seed=530, sampler=stale,
                                         stage1=False, label="adaptive (stale pmf from init)"))
    full = gradient_statistics(problem, "full", None, cfg.late_draws, late_values, seed=540)
    late_table, late_records = variance_table(late_rows + [full], {budget: late_rows[0]}, full, full, "tex")
    return {"table": table, "rows": records, "reference_level": level, "late_table": "\n".join(diag), "late_rows": diag_records,
            "variance_late_table": late_table, "variance_late_rows": late_records,
            "curves": {r.label + f"/seed{r.seed}": {"rmse": r.rmse, "seconds": r.seconds, "paths": r.paths, "ess_fraction": r.ess,
                                                     "max_weight_ratio": r.max_weight, "refresh_steps": r.refresh_steps, "gain": r.gain}
                       for r in runs}}


# ------------------------------------------------------------------------------ plots
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_error(path: Path, runs: list[Run], labels: Sequence[str], level: float, title: str) -> None:
    """Texture RMSE (smoothed, median and quartiles over seeds) vs iterations, wall time, paths."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), dpi=110)
    for lab in labels:
        c = curves_of(runs, lab)
        med, (q25, q75) = c.median, c.quartiles()
        xs = (np.arange(len(med)), np.median(c.seconds, 0), np.median(c.paths, 0))
        for ax, x in zip(axes, xs):
            (line,) = ax.plot(x, med, label=lab, lw=1.4)
            ax.fill_between(x, q25, q75, color=line.get_color(), alpha=0.2, lw=0)
    for ax, xl in zip(axes, ("iteration", "wall time incl. Stage 1 (s)", "paths traced (primal + replay + Stage 1)")):
        ax.axhline(level, color="k", ls=":", lw=0.8)
        ax.set_xlabel(xl)
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[2].set_xscale("log")
    axes[0].set_ylabel(f"texture RMSE (trailing mean over {SMOOTH} it)")
    axes[0].legend(fontsize=8)
    fig.suptitle(title + "  (median, IQR shaded; dotted: uniform's final error)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_diagnostics(path: Path, runs: list[Run], labels: Sequence[str]) -> None:
    """Per-step ESS fraction and max weight ratio (median over seeds, 20-step mean)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), dpi=110)
    for lab in labels:
        mine = [r for r in runs if r.label == lab]
        if not mine[0].ess:
            continue
        for ax, key in zip(axes, ("ess", "max_weight")):
            y = np.median(np.array([smooth(np.array(getattr(r, key)), 20) for r in mine]), 0)
            ax.plot(np.arange(1, len(y) + 1), y, label=lab, lw=1.2)
    axes[0].set_ylabel("ESS fraction (Σw)²/Σw²/N")
    axes[1].set_ylabel("max weight / uniform weight")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_pmfs(path: Path, problem: Problem, pmfs: dict[str, np.ndarray], title: str) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(pmfs) + 1, figsize=(3.2 * (len(pmfs) + 1), 3.4), dpi=110)
    img = problem.target.permute(1, 2, 0).cpu().numpy()
    axes[0].imshow(np.clip(img, 0, 1) ** (1 / 2.2))
    axes[0].set_title("target", fontsize=9)
    for ax, (name, pmf) in zip(axes[1:], pmfs.items()):
        ax.imshow(pmf * pmf.size, cmap="magma")
        ax.set_title(f"{name}: p·m (max {pmf.max() * pmf.size:.1f})", fontsize=9)
    for ax in axes:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------ main
def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    cfg = parse_args(argv)
    torchir.backend.variant()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    load0 = os.getloadavg()[0]
    print(f"[bench_adaptive] {torchir.backend.describe()}, {os.cpu_count()} CPUs, load {load0:.1f}; "
          f"{'quick' if cfg.quick else 'full'} mode, parts {cfg.parts}")
    results: dict[str, Any] = {"config": asdict(cfg), "environment": environment()}
    tables: list[tuple[str, str]] = []
    problem = None
    if set(cfg.parts) & set("abd"):
        problem = cbox_problem(cfg, out)
        m = problem.m
        print(f"[bench_adaptive] cbox canvas=8 {cfg.resolution}x{cfg.resolution} ({m} px), target {cfg.target_spp} spp "
              f"({'cached' if problem.target_seconds == 0 else f'{problem.target_seconds:.1f} s'}); budgets "
              + ", ".join(f"{b:.0%} = {max(1, round(b * m))} px" for b in cfg.budgets)
              + f"; texture RMSE at init {float((problem.init[TEX] - problem.truth[TEX]).square().mean().sqrt()):.4f}")
    def done(part: str, *new_tables: tuple[str, str]) -> None:
        """Record a finished part: print its tables now and save partial results."""
        tables.extend(new_tables)
        for title, table in new_tables:
            print(f"\n### {title}\n\n{table}\n", flush=True)
        results["wall_seconds_so_far"] = time.perf_counter() - started
        (out / "results.json").write_text(json.dumps(results, indent=1))

    if "a" in cfg.parts:
        results["a"] = part_a(cfg, problem, out)
        done("a", ("(a) trace of the gradient covariance at the initial parameters", results["a"]["table"]))
    if "c" in cfg.parts:
        results["c"] = part_c(cfg, out)
        lo, hi = results["c"]["eq5_over_adaptive_ci90"]
        title = (f"(c) glossy Fig. 3 analogue (rough conductor alpha); Eq. 5 / adaptive variance = "
                 f"{results['c']['eq5_over_adaptive']:.2f}x, 90% CI [{lo:.2f}, {hi:.2f}] (paper: 3.35x)")
        done("c", (title, results["c"]["table"]))
    if "b" in cfg.parts:
        results["b"] = part_b(cfg, problem, out)
        goal = results["b"]["adaptive_time_ratio"]
        verdict = "not reached" if goal is None else ("met" if goal <= 0.5 else "NOT met")
        title = (f"(b) texture RMSE, {cfg.budgets[0]:.0%} budget; goal adaptive time-to-uniform-final <= 0.5x: "
                 f"{'n/a' if goal is None else f'{goal:.2f}x'} -> {verdict}")
        done("b", (title, results["b"]["table"]))
    if "d" in cfg.parts:
        results["d"] = part_d(cfg, problem, out)
        done("d", (f"(d) low budget {cfg.low_budget:.0%}: parameter error", results["d"]["table"]),
             (f"(d) low budget {cfg.low_budget:.0%}: late-run diagnostics (last 25% of iterations)", results["d"]["late_table"]),
             (f"(d) gradient covariance at uniform's final parameters, {cfg.low_budget:.0%} budget", results["d"]["variance_late_table"]))
    total = time.perf_counter() - started
    results["wall_seconds"] = total
    results["environment"]["load_average_end"] = list(os.getloadavg())
    summary = "\n".join(f"### {title}\n\n{table}\n" for title, table in tables)
    save_results(out, results, summary)
    print("\n## all tables\n")
    print(summary)
    print(f"total wall time {total:.0f} s; load average at start {load0:.1f}, at end {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} CPUs")
    print(f"wrote {out / 'results.json'} and PNG plots in {out}")
    return results


if __name__ == "__main__":
    main()
