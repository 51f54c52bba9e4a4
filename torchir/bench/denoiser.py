#!/usr/bin/env python
"""Denoisers in the optimisation loop (Gu et al. 2024): none vs cross-bilateral vs target-aware.

The target-aware denoiser is that of Gu et al. 2024, "Target-Aware Image Denoising for Inverse Monte Carlo
Rendering" (SIGGRAPH 2024), "the paper" below.

Two parts, one command:

1. **Optimisation** on the ``textured_wall`` scene (a Cornell-box back wall lit only by
   bounced light: heavy-tailed few-spp noise). The wall's texture is recovered from a constant
   0.5 with Adam (lr 0.02, clamp to [0, 1]) and an L1 loss on the (denoised) render, for the
   ``albedo`` task (diffuse albedo texture) and the ``roughness`` task (roughness texture of a
   principled wall: invisible to G-buffers, where the paper expects the cross-bilateral filter
   to lose). The three methods are interleaved step by step with common seeds (rotating which
   goes first), each with its own parameter and optimiser. Reported per method: texel L1 vs the
   ground truth (every step: final and best iterate), image L1 of a high-spp render of the final,
   best-texel and equal-time iterates vs the target, wall time per step. Image L1 renders use the
   target's seed and spp (common random numbers: the ground truth scores exactly 0), which
   removes most of the Monte Carlo noise floor of the comparison. The loop calls ``torchir.functions.render`` and ``torch.optim.Adam`` directly.
2. **Timing**: forward+backward of the target-aware denoiser (tap table when it fits the
   memory budget, else taps on the fly) and of the cross-bilateral filter at 64^2, 256^2 (and
   512^2) for r = 7 and 15, against one 16-spp render step (forward+backward) of the scene at
   the same size.

Usage:
    torchir bench denoiser --quick   # 64^2, 4 spp, 1 seed, 60 steps, 2048-spp target; timing 64^2/256^2
    torchir bench denoiser           # 4 and 16 spp, 3 seeds, 200 steps; timing to 512^2

Writes ``<out>/results.json``, ``<out>/texel_error.png`` and ``<out>/timing.png``.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

import torchir
from torchir.functions import render, render_gbuffers
from torchir.modules import CrossBilateralDenoiser, TargetAwareDenoiser, l1_loss
from torchir.bench import save_results

METHODS = ("none", "cross_bilateral", "target_aware")
KEYS = {"albedo": "back.bsdf.reflectance.data", "roughness": "back.bsdf.roughness.data"}


@dataclass(frozen=True)
class Config:
    resolution: int = 64
    tasks: tuple[str, ...] = ("albedo", "roughness")
    spps: tuple[int, ...] = (4, 16)
    seeds: tuple[int, ...] = (0, 1, 2)
    steps: int = 200
    radius: int = 7
    lr: float = 0.02
    target_spp: int = 8192
    gbuffer_spp: int = 4
    timing_sizes: tuple[int, ...] = (64, 256, 512)
    timing_radii: tuple[int, ...] = (7, 15)
    timing_reps: int = 3
    torch_threads: int = 1
    out: str = "results/bench_denoiser"


def parse_args(argv: Sequence[str] | None = None) -> Config:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="4 spp, 1 seed, 60 steps, timing up to 256^2")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--seeds", type=int, default=None, help="number of seeds")
    p.add_argument("--spp", type=int, nargs="+", default=None)
    p.add_argument("--tasks", nargs="+", choices=sorted(KEYS), default=None)
    p.add_argument("--target-spp", type=int, default=None, help="spp of the target and of the image-L1 renders")
    p.add_argument("--radius", type=int, default=7, help="window radius of both denoisers in the optimisation")
    p.add_argument("--no-timing", action="store_true")
    p.add_argument("--no-optim", action="store_true")
    p.add_argument("--torch-threads", type=int, default=1,
                   help="torch intra-op threads (1: the taps are many small ops; on a shared, oversubscribed "
                        "CPU, OpenMP barriers made 2 threads up to 50x slower)")
    p.add_argument("--out", default="results/bench_denoiser")
    a = p.parse_args(argv)
    c = Config(radius=a.radius, out=a.out, torch_threads=a.torch_threads)
    if a.quick:
        c = Config(radius=a.radius, out=a.out, torch_threads=a.torch_threads, spps=(4,), seeds=(0,), steps=60, target_spp=2048,
                   timing_sizes=(64, 256), timing_reps=2)
    c = Config(**{**asdict(c), **{k: v for k, v in dict(
        steps=a.steps, target_spp=a.target_spp, seeds=None if a.seeds is None else tuple(range(a.seeds)),
        spps=None if a.spp is None else tuple(a.spp), tasks=None if a.tasks is None else tuple(a.tasks)).items()
        if v is not None}})
    if a.no_timing:
        c = Config(**{**asdict(c), "timing_sizes": ()})
    if a.no_optim:
        c = Config(**{**asdict(c), "tasks": ()})
    return c


# ---------------------------------------------------------------------------- optimisation
def run_task(cfg: Config, scene: torchir.Scene, task: str, spp: int, seed: int, target: torch.Tensor) -> dict[str, Any]:
    key = KEYS[task]
    truth = scene.get(key)
    dens = {"cross_bilateral": CrossBilateralDenoiser(radius=cfg.radius), "target_aware": TargetAwareDenoiser(radius=cfg.radius)}
    dens["target_aware"].set_target(target[None])
    state = {}
    for m in METHODS:
        x = torch.full_like(truth, 0.5).requires_grad_()
        state[m] = dict(x=x, opt=torch.optim.Adam([x], lr=cfg.lr), time=[], texel=[], iterates=[])
    for it in range(cfg.steps):
        render_seed = 1000 * seed + 2 * it + 1
        order = METHODS[it % 3:] + METHODS[: it % 3]
        for m in order:
            s = state[m]
            t0 = time.perf_counter()
            img = render(scene, {key: s["x"]}, spp=spp, seed=render_seed)[None]
            if m == "cross_bilateral":
                guide = render_gbuffers(scene, {key: s["x"].detach()}, spp=cfg.gbuffer_spp, seed=render_seed)[None]
                img = dens[m](img, target[None], guide)
            elif m == "target_aware":
                img = dens[m](img, target[None])
            loss = l1_loss(img, target[None])
            s["opt"].zero_grad()
            loss.backward()
            s["opt"].step()
            with torch.no_grad():
                s["x"].clamp_(0.0, 1.0)
            s["time"].append(time.perf_counter() - t0)
            s["texel"].append(float((s["x"].detach() - truth).abs().mean()))
            s["iterates"].append(s["x"].detach().clone())

    def image_l1(x: torch.Tensor) -> float:  # same seed as the target: common random numbers
        with torch.no_grad():
            return float(l1_loss(render(scene, {key: x}, spp=cfg.target_spp, seed=_TARGET_SEED), target))

    budget = min(sum(state[m]["time"]) for m in METHODS)
    out: dict[str, Any] = {"initial_image_l1": image_l1(torch.full_like(truth, 0.5)),
                           "initial_texel_l1": float((0.5 - truth).abs().mean())}
    for m in METHODS:
        s = state[m]
        best = min(range(cfg.steps), key=lambda i: s["texel"][i])
        cum = torch.tensor(s["time"]).cumsum(0)
        eq = max(int((cum <= budget + 1e-9).sum()) - 1, 0)
        images = {i: image_l1(s["iterates"][i]) for i in {cfg.steps - 1, best, eq}}
        out[m] = dict(
            texel_final=s["texel"][-1], texel_best=s["texel"][best], best_step=best,
            image_final=images[cfg.steps - 1], image_best=images[best],
            equal_time_step=eq, texel_equal_time=s["texel"][eq], image_equal_time=images[eq],
            seconds_per_step=statistics.median(s["time"]), texel_curve=s["texel"],
        )
    return out


_TARGET_SEED = 987654


def optimisation(cfg: Config) -> dict[str, Any]:
    results: dict[str, Any] = {}
    for task in cfg.tasks:
        # Frozen render passes return wrong images for 1-channel bitmap textures (the roughness
        # map; found here, reported): render that task's scene unfrozen.
        torchir.backend.set_frozen_renders(task != "roughness")
        scene = torchir.Scene.builtin("textured_wall", resolution=cfg.resolution, material=task)
        t0 = time.perf_counter()
        target = render(scene, spp=cfg.target_spp, seed=_TARGET_SEED)
        print(f"[{task}] target: {cfg.target_spp} spp in {time.perf_counter() - t0:.1f} s", flush=True)
        for spp in cfg.spps:
            for seed in cfg.seeds:
                t0 = time.perf_counter()
                r = run_task(cfg, scene, task, spp, seed, target)
                results[f"{task}/spp{spp}/seed{seed}"] = r
                print(f"[{task}] spp {spp} seed {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
    return results


def optimisation_tables(cfg: Config, res: dict[str, Any]) -> str:
    lines = []
    for task in cfg.tasks:
        for spp in cfg.spps:
            runs = [res[f"{task}/spp{spp}/seed{s}"] for s in cfg.seeds]
            med = lambda f, runs=runs: statistics.median(f(r) for r in runs)
            lines += [f"\n### {task}, {spp} spp, {cfg.resolution}^2, r = {cfg.radius}, {cfg.steps} steps, "
                      f"{len(runs)} seed(s) (medians; ratio = method / none)\n",
                      "| method | image L1 final | ratio | image L1 best | image L1 equal time | texel L1 final | "
                      "texel L1 best (step) | s/step |", "|---|---|---|---|---|---|---|---|",
                      f"| initial | {med(lambda r: r['initial_image_l1']):.5f} | | | | {med(lambda r: r['initial_texel_l1']):.4f} | | |"]
            base = med(lambda r: r["none"]["image_final"])
            for m in METHODS:
                g = lambda k, m=m: med(lambda r: r[m][k])
                lines.append(f"| {m} | {g('image_final'):.5f} | {g('image_final') / base:.2f} | {g('image_best'):.5f} | "
                             f"{g('image_equal_time'):.5f} | {g('texel_final'):.4f} | {g('texel_best'):.4f} "
                             f"({int(g('best_step'))}) | {g('seconds_per_step'):.3f} |")
            ratios = [r["target_aware"]["image_final"] / r["none"]["image_final"] for r in runs]
            lines.append(f"\nper-seed target_aware / none image L1: {', '.join(f'{x:.2f}' for x in ratios)}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------- timing
def _median_time(fn, reps: int) -> float:
    fn()  # warm-up (kernel compilation, tap table)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def timing(cfg: Config) -> list[dict[str, Any]]:
    rows = []
    g = torch.Generator(device="cpu").manual_seed(0)
    for size in cfg.timing_sizes:
        scene = torchir.Scene.builtin("textured_wall", resolution=size)
        key = KEYS["albedo"]
        x = scene.get(key).requires_grad_()

        def render_step(scene=scene, key=key, x=x) -> None:
            render(scene, {key: x}, spp=16, seed=1).abs().mean().backward()

        t_render = _median_time(render_step, cfg.timing_reps)
        device = torchir.backend.device()  # beside the renders it is timed against
        target = torch.rand(1, 3, size, size, generator=g, device="cpu").to(device)
        noisy = (target + 0.3 * torch.randn(1, 3, size, size, generator=g, device="cpu").to(device)).requires_grad_()
        guide = render_gbuffers(scene)[None]
        for r in cfg.timing_radii:
            row = dict(size=size, radius=r, render_step=t_render)
            for name, den in (("target_aware", TargetAwareDenoiser(radius=r)),
                              ("target_aware_taps", TargetAwareDenoiser(radius=r, impl="taps")),
                              ("cross_bilateral", CrossBilateralDenoiser(radius=r))):
                t0 = time.perf_counter()
                if name.startswith("target_aware"):
                    den.set_target(target)
                row[f"{name}_build"] = time.perf_counter() - t0

                def step(den=den, noisy=noisy, target=target, guide=guide) -> None:
                    den(noisy, target, guide).abs().mean().backward()

                row[name] = _median_time(step, cfg.timing_reps)
                row[f"{name}_ratio"] = row[name] / t_render
            rows.append(row)
            print(f"timing {size}^2 r={r}: " + ", ".join(f"{k}={v:.3f}" for k, v in row.items() if isinstance(v, float)), flush=True)
    return rows


def timing_table(rows: list[dict[str, Any]]) -> str:
    lines = ["\n### forward+backward seconds (ratio to one 16-spp render step of the scene)\n",
             "| size | r | render step | target-aware (auto: tap table if <= 1 GiB) | build | target-aware (taps on the fly) | cross-bilateral |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['size']}^2 | {r['radius']} | {r['render_step']:.3f} | {r['target_aware']:.3f} "
                     f"({r['target_aware_ratio']:.3f}x) | {r['target_aware_build']:.2f} | {r['target_aware_taps']:.3f} "
                     f"({r['target_aware_taps_ratio']:.3f}x) | {r['cross_bilateral']:.3f} ({r['cross_bilateral_ratio']:.3f}x) |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ main
def plots(cfg: Config, res: dict[str, Any], rows: list[dict[str, Any]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if res:
        panels = [(t, s) for t in cfg.tasks for s in cfg.spps]
        fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.5), squeeze=False)
        for ax, (task, spp) in zip(axes[0], panels):
            for m in METHODS:
                for i, seed in enumerate(cfg.seeds):
                    curve = res[f"{task}/spp{spp}/seed{seed}"][m]["texel_curve"]
                    ax.plot(curve, color={"none": "C0", "cross_bilateral": "C1", "target_aware": "C2"}[m],
                            alpha=0.8, label=m if i == 0 else None)
            ax.set(title=f"{task}, {spp} spp", xlabel="step", ylabel="texel L1")
            ax.legend()
        fig.tight_layout()
        fig.savefig(out / "texel_error.png", dpi=120)
    if rows:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        labels = [f"{r['size']}²\nr={r['radius']}" for r in rows]
        for j, name in enumerate(("target_aware", "target_aware_taps", "cross_bilateral")):
            ax.bar([i + 0.27 * (j - 1) for i in range(len(rows))], [r[f"{name}_ratio"] for r in rows], 0.27, label=name)
        ax.axhline(0.25, color="k", ls="--", lw=0.8, label="goal 0.25")
        ax.set(xticks=range(len(rows)), xticklabels=labels, ylabel="fwd+bwd / render step", yscale="log")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "timing.png", dpi=120)


def main(argv: Sequence[str] | None = None) -> None:
    cfg = parse_args(argv)
    torchir.backend.set_variant("auto")
    torch.set_num_threads(cfg.torch_threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = timing(cfg) if cfg.timing_sizes else []
    res = optimisation(cfg) if cfg.tasks else {}
    text = (timing_table(rows) if rows else "") + (optimisation_tables(cfg, res) if res else "")
    print(text)
    meta = dict(config=asdict(cfg), machine=platform.platform(), torch_threads=torch.get_num_threads(),
                variant=torchir.backend.variant(), seconds=time.perf_counter() - t0)
    save_results(out, dict(meta=meta, timing=rows, optimisation=res), text)
    plots(cfg, res, rows, out)
    print(f"\nwrote {out}/results.json and plots ({meta['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
