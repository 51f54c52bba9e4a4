#!/usr/bin/env python
"""LOI loss (Mehta et al. 2025) against L2 and multi-scale baselines on motion-type inverse problems.

The loss is that of Mehta et al. 2025, "Locally Orderless Images for Optimization in Differentiable
Rendering" (CVPR 2025), "the paper" below. Every loop is plain torch (Adam), not the Lightning trainer:

* **B1 glossy highlight** (paper's Envlight / Fig. 1 analogue): recover a point light's
  azimuth from the highlight on a shiny sphere (built-in scene ``glossy_highlight``, rendered
  with ``torchir.functions.render``; C++ ``direct`` integrator, 4 spp per step, a fresh seed per
  step, reference at 64 spp with an independent seed). Starts +-0.5, +-0.9, +-1.3 rad, truth 0;
  Adam lr 0.02; success = |theta| < 0.05 rad.
* **B2 2-D toys** (paper Figs. 3-5): grey disks (r = 4) on 64x64, positions optimised with
  Adam lr 0.5 px: a single displaced disk (6 starts 12-35 px away), the same with a noisy
  reference (N(0, 0.1^2)), and two disks of intensity 0.9 and 0.35 (additive) whose bright
  disk starts beyond the dim target (8 starts). Success = every disk within 1 px of its target.
* **B3 known-colour disks** (Table 1 analogue): n disks (r = 6 for n = 4, r = 4 for n = 16)
  with saturated palette colours, composited over black in a fixed order, targets on a grid,
  random init, Adam lr 0.5 px; mean PSNR and fraction of disks within 2 px, over seeds.
* **Cost**: forward + backward of each loss at 256x256x3 next to one render step
  (forward + backward, 4 spp) of ``glossy_highlight`` at 256x256, interleaved, as ratios.

Methods: ``l2`` (pixel-wise; B1 on raw HDR), ``gp`` (Gaussian pyramid, MSE per level),
``ms_l2`` (MSE of blurred images, sigma in {0, 1, 5, 15, 45} px: the paper's Gaussian-pyramid "GP" baseline),
``sigma_w1`` (LOI with alpha = 0: the sigma-space-only ablation = multi-scale L1),
``loi`` (the default: large-alpha terms on cells of 0.15 alpha), ``loi_exact`` (every pixel)
and ``loi_cells`` (LOI with ``cell_fraction=0.5``: large-alpha terms on cell means, faster).
The cost table also gives each ``cell_fraction`` setting's loss and gradient error against the
exact LOI, ``ndtr_floor``: the point CDFs alone, and, where the native banded kernel is
available (a C compiler), ``loi_dense_products`` / ``loi_exact_dense_products``: the same
losses with every blur a dense matrix product, as on a machine without one.
B1 applies Reinhard ``x/(1+x)`` to both images for every method except ``l2``; B2/B3 use the
paper's section 4.1 scales x 0.5 (64 px instead of 128 px images).

Usage:
    torchir bench loi            # full: B1 150 steps, B2 200, B3 n=4,16 x 10 seeds 300 steps
    torchir bench loi --quick    # a few minutes: fewer steps, B3 n=4 x 5 seeds

Writes ``<out>/results.json`` (summary + one record per run), ``<out>/runs.jsonl`` and
``<out>/loi_bench.png``.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

import torchir
from torchir.modules import GaussianPyramidLoss, LOILoss, MultiScaleL2Loss
from torchir.modules._banded import native_available, native_products
from ._common import median
from torchir.bench import save_results

LossFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
METHODS = ("l2", "gp", "ms_l2", "sigma_w1", "loi", "loi_exact", "loi_cells")
CELL_FRACTIONS = (0.1, 0.25, 0.5, 1.0)  # the cost table's speed-for-accuracy settings; "loi_cells" uses 0.5
ERROR_AZIMUTHS = (0.05, 0.4, 1.2)  # rendered images the cost table's errors are the largest over

# ------------------------------------------------------------------------------- losses


def make_losses(alphas: Sequence[float], sigmas: Sequence[float], transform: str | None, reduction: str = "mean") -> dict[str, LossFn]:
    """The compared losses; ``reduction`` applies over a batch of independent problems."""
    ms = [0.0, *sigmas] if 0 not in sigmas else list(sigmas)

    def l2(x, y):
        per = (x - y).square().flatten(1).mean(1)
        return per.sum() if reduction == "sum" else per.mean()

    return {
        "l2": l2,
        "gp": GaussianPyramidLoss(transform=transform, reduction=reduction),
        "ms_l2": MultiScaleL2Loss(sigmas=ms, transform=transform, reduction=reduction),
        "sigma_w1": LOILoss(alphas=(0,), sigmas=sigmas, transform=transform, reduction=reduction),
        "loi": LOILoss(alphas=alphas, sigmas=sigmas, transform=transform, reduction=reduction),
        "loi_exact": LOILoss(alphas=alphas, sigmas=sigmas, transform=transform, reduction=reduction, exact=True),
        "loi_cells": LOILoss(alphas=alphas, sigmas=sigmas, transform=transform, reduction=reduction, cell_fraction=0.5),
    }


# ----------------------------------------------------------------------------- B1 highlight


def bench_b1(args, methods: Sequence[str]) -> list[dict[str, Any]]:
    res, steps = args.b1_resolution, args.b1_steps
    scene = torchir.Scene.builtin("glossy_highlight", resolution=res, azimuth=0.0)
    render = torchir.functions.render
    with torch.no_grad():
        target = render(scene, {"light.azimuth": torch.zeros(1)}, spp=64, seed=999_999)[None]
    losses = make_losses((1, 5, 15, 45), (1, 5), "reinhard")
    losses["l2"] = make_losses((1,), (1,), None)["l2"]  # raw HDR, as the paper's L2 baseline
    starts = [s * v for v in (0.5, 0.9, 1.3) for s in (1, -1)]
    runs = []
    for start in starts:
        for method in methods:  # interleaved: every method sees the same machine state per start
            theta = torch.tensor([start], requires_grad=True)
            opt = torch.optim.Adam([theta], lr=0.02)
            t0, t_loss = time.perf_counter(), 0.0
            for step in range(steps):
                opt.zero_grad()
                img = render(scene, {"light.azimuth": theta}, spp=4, seed=1 + step)[None]
                t1 = time.perf_counter()
                loss = losses[method](img, target)
                loss.backward()
                t_loss += time.perf_counter() - t1
                opt.step()
                with torch.no_grad():
                    theta.clamp_(-1.6, 1.6)
            err = abs(theta.item())
            runs.append(dict(bench="B1", method=method, init=start, final=theta.item(), error=err, success=err < 0.05,
                             seconds=time.perf_counter() - t0, loss_seconds=t_loss))
            print(json.dumps(runs[-1]), file=args.jsonl, flush=True)
    return runs


# ------------------------------------------------------------------------------- disks


def disks(pos: torch.Tensor, colors: torch.Tensor, radius: float, size: int, mode: str) -> torch.Tensor:
    """Anti-aliased disks. pos (B, n, 2) as (x, y) px, colors (n, C) -> (B, C, size, size).

    ``mode="add"``: sum of colour x coverage; ``"over"``: composited over black in order."""
    c = torch.arange(size, dtype=pos.dtype) + 0.5
    dx = c.view(1, 1, 1, -1) - pos[..., 0, None, None]
    dy = c.view(1, 1, -1, 1) - pos[..., 1, None, None]
    cov = torch.sigmoid((radius - (dx * dx + dy * dy + 1e-12).sqrt()) * 4.0)  # (B, n, H, W)
    b, n = pos.shape[:2]
    img = pos.new_zeros(b, colors.shape[1], size, size)
    for i in range(n):
        col, k = colors[i].view(1, -1, 1, 1), cov[:, i : i + 1]
        img = img + col * k if mode == "add" else img * (1 - k) + col * k
    return img


def optimise_disks(loss: LossFn, init: torch.Tensor, target: torch.Tensor, colors, radius, size, mode, steps, lr) -> torch.Tensor:
    """Adam on disk positions; the batch holds independent problems (losses reduce by sum)."""
    pos = init.clone().requires_grad_(True)
    opt = torch.optim.Adam([pos], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        loss(disks(pos, colors, radius, size, mode), target).backward()
        opt.step()
        with torch.no_grad():
            pos.clamp_(0, size)
    return pos.detach()


def bench_b2(args, methods: Sequence[str]) -> list[dict[str, Any]]:
    size, steps = 64, args.b2_steps
    losses = make_losses((0.5, 2.5, 7.5), (0.5, 2.5, 7.5, 22.5), None, reduction="sum")
    gen = torch.Generator(device=torch.get_default_device()).manual_seed(0)
    runs = []
    grey = torch.tensor([[0.8]])
    # single disk: target at (20, 32), starts 12..35 px to the right, alternately up/down a bit
    offsets = torch.tensor([12.0, 16.0, 21.0, 26.0, 30.0, 35.0])
    single_init = torch.stack([20 + offsets, 32 + torch.tensor([2.0, -2, 3, -3, 1, -1])], -1)[:, None]  # (6, 1, 2)
    single_truth = torch.tensor([[[20.0, 32.0]]]).expand(6, 1, 2)
    clean = disks(single_truth, grey, 4.0, size, "add")
    noisy = clean + 0.1 * torch.randn(clean.shape, generator=gen)
    # two disks 0.9 and 0.35: targets at x = 20 (bright) and x = 44 (dim); bright starts beyond the dim target
    two_colors = torch.tensor([[0.9], [0.35]])
    two_truth = torch.tensor([[20.0, 32.0], [44.0, 32.0]]).expand(8, 2, 2)
    bx = torch.tensor([50.0, 52, 54, 56, 50, 52, 54, 56])
    dx = torch.tensor([10.0, 12, 14, 8, 30, 28, 26, 24])
    by = torch.tensor([28.0, 36, 30, 34, 26, 38, 32, 33])
    two_init = torch.stack([torch.stack([bx, by], -1), torch.stack([dx, 64 - by], -1)], 1)
    two_target = disks(two_truth, two_colors, 4.0, size, "add")
    toys = [
        ("single", single_init, single_truth, clean, grey),
        ("noisy_ref", single_init, single_truth, noisy, grey),
        ("two_tonal", two_init, two_truth, two_target, two_colors),
    ]
    for toy, init, truth, target, colors in toys:
        for method in methods:
            t0 = time.perf_counter()
            final = optimise_disks(losses[method], init, target, colors, 4.0, size, "add", steps, 0.5)
            dist = (final - truth).norm(dim=-1)  # (B, n)
            for i in range(init.shape[0]):
                runs.append(dict(bench="B2", toy=toy, method=method, init=init[i].tolist(), final=final[i].tolist(),
                                 error=float(dist[i].max()), success=bool((dist[i] < 1.0).all()),
                                 first_on_target=bool(dist[i, 0] < 1.0), seconds=(time.perf_counter() - t0) / init.shape[0]))
                print(json.dumps(runs[-1]), file=args.jsonl, flush=True)
    return runs


PALETTE = torch.tensor([[1, 0.1, 0.1], [0.1, 1, 0.1], [0.1, 0.2, 1], [1, 1, 0.1], [1, 0.1, 1], [0.1, 1, 1], [1, 0.5, 0.1], [0.5, 0.1, 1]])


def psnr(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    mse = (x - y).square().flatten(1).mean(1).clamp_min(1e-10)
    return 10 * torch.log10(1.0 / mse)


def bench_b3(args, methods: Sequence[str]) -> list[dict[str, Any]]:
    size, runs = 64, []
    losses = make_losses((0.5, 2.5, 7.5), (0.5, 2.5, 7.5, 22.5), None, reduction="sum")
    for n in args.b3_n:
        k = int(math.isqrt(n))
        radius = 6.0 if n <= 4 else 4.0
        grid = (torch.arange(k, dtype=torch.float32) + 0.5) * size / k
        truth = torch.stack(torch.meshgrid(grid, grid, indexing="xy"), -1).reshape(1, n, 2).expand(args.b3_seeds, n, 2)
        colors = PALETTE[torch.arange(n) % len(PALETTE)] * (1 - 0.5 * (torch.arange(n) // len(PALETTE) % 2)).view(-1, 1)
        target = disks(truth, colors, radius, size, "over")
        gen = torch.Generator(device=torch.get_default_device()).manual_seed(n)
        init = 4 + (size - 8) * torch.rand(args.b3_seeds, n, 2, generator=gen)
        for method in methods:
            t0 = time.perf_counter()
            final = optimise_disks(losses[method], init, target, colors, radius, size, "over", args.b3_steps, 0.5)
            p = psnr(disks(final, colors, radius, size, "over"), target)
            rec = ((final - truth).norm(dim=-1) < 2.0).float().mean(1)
            for s in range(args.b3_seeds):
                runs.append(dict(bench="B3", n=n, seed=s, method=method, psnr=float(p[s]), recovered=float(rec[s]),
                                 success=bool(rec[s] == 1.0), seconds=(time.perf_counter() - t0) / args.b3_seeds))
                print(json.dumps(runs[-1]), file=args.jsonl, flush=True)
    return runs


# ---------------------------------------------------------------------------------- cost


def bench_cost(args) -> dict[str, Any]:
    """Median seconds of loss forward+backward at 256^2x3 vs one render step at 256^2, 4 spp,
    and the loss / gradient error of the ``cell_fraction`` settings against the exact LOI.

    ``ndtr_floor`` times only the point CDFs of the rendered image (one ``erfc`` over the
    ``(1, 3, K, H + 2 r_sigma, W + 2 r_sigma)`` support per inner scale, no blur, no backward):
    no implementation of this formulation can be faster than that on the same machine. Errors
    are the largest over renders at azimuths ``ERROR_AZIMUTHS``."""
    res = args.cost_resolution
    scene = torchir.Scene.builtin("glossy_highlight", resolution=res)
    render = torchir.functions.render
    target = render(scene, {}, spp=16, seed=5).detach()[None]
    images = {theta: render(scene, {"light.azimuth": torch.tensor([theta])}, spp=4, seed=6).detach()[None] for theta in ERROR_AZIMUTHS}
    img0 = images[0.4]  # the image the loss steps are timed on
    losses = make_losses((1, 5, 15, 45), (1, 5), "reinhard")
    losses.pop("loi_cells")
    losses["loi_renormalize"] = LOILoss(transform="reinhard", border="renormalize")
    losses["loi_low_memory"] = LOILoss(transform="reinhard", low_memory=True)
    for f in CELL_FRACTIONS:
        losses[f"loi_cells_{f:g}"] = LOILoss(transform="reinhard", cell_fraction=f)
    ref = losses["loi_exact"]
    bins = ref.cdfs(img0, 0.0, 0.0).shape[2]  # K bin edges
    margin = math.ceil(ref.pad_frac * res)
    # D is computed on the image and r_sigma around it (beyond, both images are the pad value)
    sides = [res + 2 * min(margin, math.ceil(ref.truncate * s)) for s in ref.sigmas]
    supports = [torch.rand(1, 3, bins, side, side) for side in sides]

    def render_step(i):
        theta = torch.tensor([0.4], requires_grad=True)
        render(scene, {"light.azimuth": theta}, spp=4, seed=100 + i).sum().backward()

    def loss_step(fn):
        def run(i):
            x = img0.clone().requires_grad_(True)
            fn(x, target).backward()
        return run

    def ndtr_floor(i):
        for support in supports:
            torch.erfc(support)

    def dense_products(job):
        def run(i):
            with native_products(False):
                job(i)
        return run

    jobs = {"render": render_step, **{k: loss_step(v) for k, v in losses.items()}, "ndtr_floor": ndtr_floor}
    if native_available():  # the same losses with every blur a dense matrix product (no compiler)
        jobs["loi_dense_products"] = dense_products(loss_step(losses["loi"]))
        jobs["loi_exact_dense_products"] = dense_products(loss_step(losses["loi_exact"]))
    for job in jobs.values():  # warm-up (kernel compilation, target caches)
        job(0)
    times: dict[str, list[float]] = {k: [] for k in jobs}
    for rep in range(args.cost_reps):
        order = list(jobs) if rep % 2 == 0 else list(reversed(jobs))  # interleaved, alternating order
        for k in order:
            t0 = time.perf_counter()
            jobs[k](rep + 1)
            times[k].append(time.perf_counter() - t0)
    med = {k: sorted(v)[len(v) // 2] for k, v in times.items()}

    def loss_and_grad(fn, img):
        x = img.clone().requires_grad_(True)
        v = fn(x, target)
        v.backward()
        return v.item(), x.grad

    error = {}  # the largest over the rendered images
    for theta, img in images.items():
        v_ref, g_ref = loss_and_grad(ref, img)
        for k, fn in losses.items():
            if k.startswith("loi"):
                v, g = loss_and_grad(fn, img)
                e = error.setdefault(k, dict(loss_relative_error=0.0, gradient_relative_error=0.0))
                e["loss_relative_error"] = max(e["loss_relative_error"], abs(v / v_ref - 1))
                e["gradient_relative_error"] = max(e["gradient_relative_error"], float((g - g_ref).norm() / g_ref.norm()))
    return {"resolution": res, "median_seconds": med, "ratio_to_render": {k: med[k] / med["render"] for k in med}, "error_vs_exact_loi": error}


# ------------------------------------------------------------------------------ reporting


def summarise(runs: list[dict[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    b1 = [r for r in runs if r["bench"] == "B1"]
    if b1:
        out["B1"] = {m: dict(successes=sum(r["success"] for r in b1 if r["method"] == m), runs=sum(r["method"] == m for r in b1),
                             median_error=median([r["error"] for r in b1 if r["method"] == m]),
                             loss_seconds_per_run=median([r["loss_seconds"] for r in b1 if r["method"] == m]))
                     for m in methods}
    b2 = [r for r in runs if r["bench"] == "B2"]
    if b2:
        out["B2"] = {toy: {m: dict(successes=sum(r["success"] for r in b2 if r["toy"] == toy and r["method"] == m),
                                   first_on_target=sum(r["first_on_target"] for r in b2 if r["toy"] == toy and r["method"] == m),
                                   runs=sum(r["toy"] == toy and r["method"] == m for r in b2)) for m in methods}
                     for toy in dict.fromkeys(r["toy"] for r in b2)}
    b3 = [r for r in runs if r["bench"] == "B3"]
    if b3:
        out["B3"] = {str(n): {m: dict(mean_psnr=_mean([r["psnr"] for r in b3 if r["n"] == n and r["method"] == m]),
                                      median_psnr=median([r["psnr"] for r in b3 if r["n"] == n and r["method"] == m]),
                                      recovered=_mean([r["recovered"] for r in b3 if r["n"] == n and r["method"] == m]),
                                      all_recovered=sum(r["success"] for r in b3 if r["n"] == n and r["method"] == m),
                                      runs=sum(r["n"] == n and r["method"] == m for r in b3)) for m in methods}
                     for n in dict.fromkeys(r["n"] for r in b3)}
    return out


def _mean(v):
    return sum(v) / len(v) if v else float("nan")


def print_tables(summary: dict[str, Any], cost: dict[str, Any] | None, methods: Sequence[str]) -> None:
    head = "| " + " | ".join(["setting", *methods]) + " |"
    rule = "|" + "---|" * (len(methods) + 1)
    if "B1" in summary:
        s = summary["B1"]
        print("\n### B1 glossy highlight: successes (|theta| < 0.05 rad) / median |error| rad\n")
        print(head), print(rule)
        print("| starts +-0.5, +-0.9, +-1.3 | " + " | ".join(f"{s[m]['successes']}/{s[m]['runs']} / {s[m]['median_error']:.3g}" for m in methods) + " |")
        print("| loss seconds per run (median) | " + " | ".join(f"{s[m]['loss_seconds_per_run']:.2f}" for m in methods) + " |")
    if "B2" in summary:
        print("\n### B2 toys: runs with every disk within 1 px (two_tonal: bright disk on target / both)\n")
        print(head), print(rule)
        for toy, s in summary["B2"].items():
            cell = (lambda m: f"{s[m]['first_on_target']} / {s[m]['successes']} of {s[m]['runs']}") if toy == "two_tonal" else (lambda m: f"{s[m]['successes']}/{s[m]['runs']}")
            print(f"| {toy} | " + " | ".join(cell(m) for m in methods) + " |")
    if "B3" in summary:
        print("\n### B3 known-colour disks: mean PSNR dB / median PSNR dB / fraction of disks within 2 px / runs all recovered\n")
        print(head), print(rule)
        for n, s in summary["B3"].items():
            print(f"| n = {n} | " + " | ".join(f"{s[m]['mean_psnr']:.2f} / {s[m]['median_psnr']:.2f} / {s[m]['recovered']:.2f} / {s[m]['all_recovered']}/{s[m]['runs']}" for m in methods) + " |")
    if cost:
        print(f"\n### Cost at {cost['resolution']}x{cost['resolution']}x3: median seconds (forward + backward), ratio to one render step (4 spp)\n")
        print("| job | seconds | ratio to render | loss error vs exact LOI | gradient error vs exact LOI |"), print("|---|---|---|---|---|")
        err = cost.get("error_vs_exact_loi", {})
        for k, v in cost["median_seconds"].items():
            e = err.get(k)
            cols = f"{e['loss_relative_error']:.1e} | {e['gradient_relative_error']:.1e}" if e else "- | -"
            print(f"| {k} | {v:.4f} | {cost['ratio_to_render'][k]:.2f} | {cols} |")


def plot(summary: dict[str, Any], runs: list[dict[str, Any]], methods: Sequence[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    if "B1" in summary:
        b1 = [r for r in runs if r["bench"] == "B1"]
        for i, m in enumerate(methods):
            xs = [r["init"] for r in b1 if r["method"] == m]
            ys = [max(r["error"], 1e-4) for r in b1 if r["method"] == m]
            axes[0].scatter([x + 0.03 * (i - 2.5) for x in xs], ys, label=m, s=18)
        axes[0].axhline(0.05, color="k", lw=0.5, ls="--")
        axes[0].set(yscale="log", xlabel="start azimuth (rad)", ylabel="final |error| (rad)", title="B1 glossy highlight")
        axes[0].legend(fontsize=7)
    if "B2" in summary:
        toys = list(summary["B2"])
        for i, m in enumerate(methods):
            axes[1].bar([t + 0.13 * (i - 2.5) for t in range(len(toys))], [summary["B2"][toy][m]["successes"] / summary["B2"][toy][m]["runs"] for toy in toys], 0.13, label=m)
        axes[1].set(xticks=range(len(toys)), xticklabels=toys, ylabel="success rate", title="B2 toys")
    if "B3" in summary:
        ns = list(summary["B3"])
        for i, m in enumerate(methods):
            axes[2].bar([t + 0.13 * (i - 2.5) for t in range(len(ns))], [summary["B3"][n][m]["mean_psnr"] for n in ns], 0.13, label=m)
        axes[2].set(xticks=range(len(ns)), xticklabels=[f"n={n}" for n in ns], ylabel="mean PSNR (dB)", title="B3 known-colour disks")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", nargs="+", choices=["B1", "B2", "B3", "cost"], default=["B1", "B2", "B3", "cost"])
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument("--b1-steps", type=int, default=150)
    p.add_argument("--b1-resolution", type=int, default=96)
    p.add_argument("--b2-steps", type=int, default=200)
    p.add_argument("--b3-steps", type=int, default=300)
    p.add_argument("--b3-seeds", type=int, default=10)
    p.add_argument("--b3-n", type=int, nargs="+", default=[4, 16], help="disk counts (perfect squares)")
    p.add_argument("--cost-resolution", type=int, default=256)
    p.add_argument("--cost-reps", type=int, default=7)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--out", default="results/bench_loi")
    p.add_argument("--quick", action="store_true", help="B1 80 steps, B2 120, B3 n=4 x 5 seeds x 150 steps, 3 cost reps")
    args = p.parse_args(argv)
    if args.quick:
        args.b1_steps, args.b2_steps, args.b3_steps, args.b3_seeds, args.b3_n, args.cost_reps = 80, 120, 150, 5, [4], 3
    if args.threads:
        torch.set_num_threads(args.threads)
    torchir.backend.set_variant("auto")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs: list[dict[str, Any]] = []
    cost = None
    t0 = time.perf_counter()
    with open(out / "runs.jsonl", "w") as args.jsonl:
        for name, fn in (("B1", bench_b1), ("B2", bench_b2), ("B3", bench_b3)):
            if name in args.only:
                t = time.perf_counter()
                runs += fn(args, args.methods)
                print(f"{name}: {time.perf_counter() - t:.0f} s", flush=True)
        if "cost" in args.only:
            cost = bench_cost(args)
    summary = summarise(runs, args.methods)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        print_tables(summary, cost, args.methods)
    print(printed.getvalue())
    settings = {k: v for k, v in vars(args).items() if k != "jsonl"}
    result = dict(settings=settings, machine=dict(platform=platform.platform(), cpus=os.cpu_count(), torch_threads=torch.get_num_threads()),
                  summary=summary, cost=cost, runs=runs, seconds=time.perf_counter() - t0)
    save_results(out, result, printed.getvalue())
    plot(summary, runs, args.methods, out / "loi_bench.png")
    print(f"\nwrote {out / 'results.json'}, {out / 'runs.jsonl'} and {out / 'loi_bench.png'} ({result['seconds']:.0f} s)")
    return result


if __name__ == "__main__":
    main()
