#!/usr/bin/env python
"""Overhead of torchir over a native Mitsuba/Dr.Jit optimisation loop.

The same inverse-rendering loop (recover one scene parameter with Adam, L2 image loss, clamp
to [0, 1]) is written twice:

* **native**: ``mi.render(scene, params)`` + ``dr.backward`` + ``mi.ad.Adam``, as in Mitsuba's
  tutorials;
* **torchir**: ``torchir.functions.render`` + ``loss.backward()`` + ``torch.optim.Adam``.

Each method gets its own scene object, starts from the same value (the parameter filled with
0.5, e.g. a grey red wall) and fits the same target image, rendered once at high spp from the
true value. After untimed warm-up steps, R repetitions of S-step blocks are timed, the two
methods alternating (ABAB, first method swapped every repetition) so that machine noise hits
both alike. ``dr.sync_thread()`` is called before every clock read, so queued kernels count
towards the step that launched them.

Reported per method: median and IQR of seconds/step over the repetitions, JIT kernels launched
per step, kernels compiled and in-memory cache misses during the timed blocks (goal: 0), and
the share of wall time spent executing kernels (the rest is Python tracing, torch, interop and
idle time). The ratio torchir/native is the median of the per-repetition ratios (goal: <= 1).

Usage:
    torchir bench overhead [--quick]
    (default: Cornell box 128x128, 4 spp, 5 x 20 steps; --quick: 64x64, 3 x 10 steps)

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/seconds_per_step.png``.
"""
from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

import torchir
from torchir.bench import environment, save_results
from torchir.backend import KernelStats, count_kernels
from torchir.functions import render

METHODS = ("native", "torchir")
INIT_VALUE = 0.5  # initial value of every entry of the optimised parameter (0.5 grey)


# ------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class Config:
    """Benchmark settings (see :func:`parse_args`)."""

    scene: str = "cbox"
    param: str | None = None  # None: the scene's first typical parameter
    resolution: int = 128
    spp: int = 4
    target_spp: int = 256
    steps: int = 20
    reps: int = 5
    warmup: int = 5
    lr: float = 0.02
    out: str = "results/bench_overhead"


def parse_args(argv: Sequence[str] | None = None) -> Config:
    """Command-line options -> :class:`Config` (``--quick`` overrides resolution, steps, reps)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="cbox", choices=sorted(torchir.scenes.available()), help="built-in scene")
    p.add_argument("--param", default=None, help="parameter to optimise (default: the scene's first typical one)")
    p.add_argument("--resolution", type=int, default=128, help="image height = width")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of each optimisation step")
    p.add_argument("--target-spp", type=int, default=256, help="samples per pixel of the target image")
    p.add_argument("--steps", type=int, default=20, help="steps per timed block (S)")
    p.add_argument("--reps", type=int, default=5, help="repetitions: timed blocks per method (R)")
    p.add_argument("--warmup", type=int, default=5, help="untimed warm-up steps per method")
    p.add_argument("--lr", type=float, default=0.02, help="Adam learning rate")
    p.add_argument("--out", default="results/bench_overhead", help="output directory")
    p.add_argument("--quick", action="store_true", help="smoke test: resolution 64, steps 10, reps 3")
    a = p.parse_args(argv)
    if a.quick:
        a.resolution, a.steps, a.reps = 64, 10, 3
    for name in ("resolution", "spp", "target_spp", "steps", "reps"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    if a.warmup < 1:
        p.error("--warmup must be >= 1 (the first step compiles the kernels)")
    return Config(
        scene=a.scene, param=a.param, resolution=a.resolution, spp=a.spp, target_spp=a.target_spp,
        steps=a.steps, reps=a.reps, warmup=a.warmup, lr=a.lr, out=a.out,
    )


# ------------------------------------------------------------------------------ the two loops
class Loop(Protocol):
    """One optimisation loop: ``step(seed)`` does render, loss, backward, Adam step, clamp."""

    name: str

    def step(self, seed: int) -> None: ...

    def value(self) -> np.ndarray: ...


def filled_like(value: Any, fill: float) -> Any:
    """A Mitsuba/Dr.Jit value of ``value``'s type and shape with every entry ``fill``."""
    shape = tuple(value.shape) if dr.is_tensor_v(value) else dr.width(value)
    return dr.full(type(value), fill, shape)


class NativeLoop:
    """The loop of Mitsuba's tutorials: ``mi.render`` + ``dr.backward`` + ``mi.ad.Adam``."""

    name = "native"

    def __init__(self, scene: mi.Scene, key: str, target: mi.TensorXf, spp: int, lr: float) -> None:
        self.scene, self.key, self.target, self.spp = scene, key, target, spp
        self.params = mi.traverse(scene)
        self.opt = mi.ad.Adam(lr=lr)
        self.opt[key] = filled_like(self.params[key], INIT_VALUE)
        self.params.update(self.opt)

    def step(self, seed: int) -> None:
        img = mi.render(self.scene, self.params, spp=self.spp, seed=seed)
        loss = dr.mean(dr.square(img - self.target))
        dr.backward(loss)
        self.opt.step()
        self.opt[self.key] = dr.clip(self.opt[self.key], 0.0, 1.0)
        self.params.update(self.opt)

    def value(self) -> np.ndarray:
        return np.array(self.opt[self.key]).ravel()


class TorchirLoop:
    """The same loop in torch: ``torchir.functions.render`` + ``torch.optim.Adam``."""

    name = "torchir"

    def __init__(self, scene: torchir.Scene, key: str, target: torch.Tensor, spp: int, lr: float) -> None:
        self.scene, self.key, self.target, self.spp = scene, key, target, spp
        self.param = torch.nn.Parameter(torch.full_like(scene.get(key), INIT_VALUE))
        self.opt = torch.optim.Adam([self.param], lr=lr)

    def step(self, seed: int) -> None:
        self.opt.zero_grad(set_to_none=True)
        img = render(self.scene, {self.key: self.param}, spp=self.spp, seed=seed)
        loss = ((img - self.target) ** 2).mean()
        loss.backward()
        self.opt.step()
        with torch.no_grad():
            self.param.clamp_(0.0, 1.0)

    def value(self) -> np.ndarray:
        return self.param.detach().cpu().numpy().ravel().copy()


@dataclass
class Setup:
    """Both loops, the parameter key and its true value."""

    key: str
    true_value: np.ndarray
    loops: dict[str, Loop]
    target_seconds: float


def build(cfg: Config) -> Setup:
    """Two separate scenes, the target (rendered once, natively, from the true value), two loops."""
    scene_native = torchir.Scene.builtin(cfg.scene, resolution=cfg.resolution)
    scene_torchir = torchir.Scene.builtin(cfg.scene, resolution=cfg.resolution)
    key = cfg.param or torchir.scenes.get(cfg.scene).parameters[0]
    info = scene_native.info(key)  # KeyError with suggestions for a wrong --param
    if not (info.bindable and info.differentiable):
        raise SystemExit(f"parameter {key!r} ({info.type_name}) is not a differentiable float parameter")
    true_value = scene_torchir.get(key).cpu().numpy().ravel().copy()

    t0 = time.perf_counter()
    target = mi.render(scene_native.mi_scene, spp=cfg.target_spp, seed=2**31 - 1)  # (H, W, C)
    dr.eval(target)
    dr.sync_thread()
    target_seconds = time.perf_counter() - t0
    target_native = mi.TensorXf(target)
    target_torch = target.torch().permute(2, 0, 1).contiguous().clone()  # (C, H, W), as render()

    loops: dict[str, Loop] = {
        "native": NativeLoop(scene_native.mi_scene, key, target_native, cfg.spp, cfg.lr),
        "torchir": TorchirLoop(scene_torchir, key, target_torch, cfg.spp, cfg.lr),
    }
    return Setup(key=key, true_value=true_value, loops=loops, target_seconds=target_seconds)


# ------------------------------------------------------------------------------ timing
@dataclass
class Block:
    """One timed block of one method."""

    method: str
    rep: int
    step_seconds: list[float]
    kernels: KernelStats

    @property
    def seconds(self) -> float:
        return float(sum(self.step_seconds))

    @property
    def seconds_per_step(self) -> float:
        return self.seconds / len(self.step_seconds)


def run_steps(loop: Loop, first_seed: int, steps: int) -> list[float]:
    """Run ``steps`` steps with seeds ``first_seed, first_seed + 1, ...``; seconds of each step
    (``dr.sync_thread()`` before every clock read, so each step pays for its own kernels)."""
    times = []
    dr.sync_thread()
    t_prev = time.perf_counter()
    for i in range(steps):
        loop.step(first_seed + i)
        dr.sync_thread()
        t = time.perf_counter()
        times.append(t - t_prev)
        t_prev = t
    return times


def run_block(loop: Loop, rep: int, first_seed: int, steps: int) -> Block:
    """A timed block, its kernels counted by :func:`torchir.backend.count_kernels`."""
    with count_kernels() as stats:
        times = run_steps(loop, first_seed, steps)
    return Block(method=loop.name, rep=rep, step_seconds=times, kernels=stats)


def warm_up(setup: Setup, steps: int) -> dict[str, KernelStats]:
    """Untimed steps (seeds 0..steps-1) of each method, interleaved; their kernel statistics."""
    stats = {m: KernelStats() for m in METHODS}
    for i in range(steps):
        for m in METHODS:
            with count_kernels() as s:
                setup.loops[m].step(i)
            for f in ("launched", "compiled", "cache_misses", "execution_time"):
                setattr(stats[m], f, getattr(stats[m], f) + getattr(s, f))
    return stats


def benchmark(setup: Setup, cfg: Config) -> list[Block]:
    """R repetitions of one S-step block per method, ABAB with the first method swapped every
    repetition; both methods use the same seeds for the same step index."""
    blocks: list[Block] = []
    for rep in range(cfg.reps):
        order = METHODS if rep % 2 == 0 else METHODS[::-1]
        first_seed = cfg.warmup + rep * cfg.steps
        for m in order:
            block = run_block(setup.loops[m], rep, first_seed, cfg.steps)
            blocks.append(block)
            print(
                f"  rep {rep + 1}/{cfg.reps}  {m:<8} {block.seconds_per_step * 1e3:8.2f} ms/step  "
                f"compiled {block.kernels.compiled}",
                flush=True,
            )
    return blocks


# ------------------------------------------------------------------------------ summary
@dataclass
class MethodSummary:
    """Statistics of one method over the timed blocks."""

    method: str
    seconds_per_step: list[float]  # per repetition
    median: float
    q25: float
    q75: float
    kernels_per_step: float
    compiled: int
    cache_misses: int
    kernel_seconds: float
    wall_seconds: float
    kernel_time_share: float
    final_value: list[float] = field(default_factory=list)

    @property
    def iqr(self) -> float:
        return self.q75 - self.q25


def summarise(blocks: list[Block], method: str, final_value: np.ndarray) -> MethodSummary:
    """Median/IQR over repetitions and summed kernel statistics of ``method``'s blocks."""
    mine = sorted((b for b in blocks if b.method == method), key=lambda b: b.rep)
    per_rep = [b.seconds_per_step for b in mine]
    q25, med, q75 = (float(v) for v in np.percentile(per_rep, [25, 50, 75]))
    steps = sum(len(b.step_seconds) for b in mine)
    wall = sum(b.seconds for b in mine)
    kernel_s = sum(b.kernels.execution_time for b in mine)
    return MethodSummary(
        method=method,
        seconds_per_step=per_rep,
        median=med,
        q25=q25,
        q75=q75,
        kernels_per_step=sum(b.kernels.launched for b in mine) / steps,
        compiled=sum(b.kernels.compiled for b in mine),
        cache_misses=sum(b.kernels.cache_misses for b in mine),
        kernel_seconds=kernel_s,
        wall_seconds=wall,
        kernel_time_share=kernel_s / wall if wall > 0 else float("nan"),
        final_value=[float(v) for v in final_value],
    )


def ratio_per_rep(summaries: dict[str, MethodSummary]) -> list[float]:
    """torchir/native seconds per step, per repetition."""
    return [t / n for t, n in zip(summaries["torchir"].seconds_per_step, summaries["native"].seconds_per_step)]


def format_table(summaries: dict[str, MethodSummary], ratio: float) -> str:
    """The final table (one row per method, then the ratio)."""
    header = (
        f"{'method':<9} {'s/step (median)':>15}  {'IQR':>9}  {'kernels/step':>12}  "
        f"{'compiled after warm-up':>22}  {'cache misses':>12}  {'kernel time share':>17}"
    )
    lines = [header]
    for m in METHODS:
        s = summaries[m]
        lines.append(
            f"{m:<9} {s.median:>15.4f}  {s.iqr:>9.4f}  {s.kernels_per_step:>12.1f}  "
            f"{s.compiled:>22d}  {s.cache_misses:>12d}  {s.kernel_time_share:>17.2f}"
        )
    lines.append(f"ratio torchir/native: {ratio:.2f}")
    return "\n".join(lines)


def save(out: Path, cfg: Config, setup: Setup, warm: dict[str, KernelStats], blocks: list[Block],
         summaries: dict[str, MethodSummary], ratios: list[float], ratio: float) -> None:
    """Write ``results.json`` and the seconds/step plot to ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "config": asdict(cfg),
        "param": setup.key,
        "true_value": [float(v) for v in setup.true_value],
        "initial_value": INIT_VALUE,
        "target_seconds": setup.target_seconds,
        "environment": environment(),
        "warmup_kernels": {m: {k: v for k, v in asdict(s).items() if k != "hashes"} for m, s in warm.items()},
        "summary": {m: {**asdict(s), "iqr": s.iqr} for m, s in summaries.items()},
        "ratio_per_rep": ratios,
        "ratio": ratio,
        "blocks": [
            {
                "method": b.method,
                "rep": b.rep,
                "seconds_per_step": b.seconds_per_step,
                "step_seconds": b.step_seconds,
                "kernels": asdict(b.kernels),
            }
            for b in blocks
        ],
    }
    save_results(out, result, summary=(
        f"Scene {cfg.scene} {cfg.resolution}², {cfg.spp} spp, {cfg.reps} x {cfg.steps} timed steps per method "
        f"(interleaved). Goal: torchir/native <= 1 and zero compilations after warm-up.\n\n"
        f"```\n{format_table(summaries, ratio)}\n```\n"
    ))
    plot(out / "seconds_per_step.png", cfg, summaries, ratio)


def plot(path: Path, cfg: Config, summaries: dict[str, MethodSummary], ratio: float) -> None:
    """Seconds/step per repetition of both methods (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    reps = np.arange(1, cfg.reps + 1)
    for m, marker in zip(METHODS, ("o", "s")):
        s = summaries[m]
        ax.plot(reps, np.array(s.seconds_per_step) * 1e3, marker=marker, label=f"{m} (median {s.median * 1e3:.1f} ms)")
    ax.set_xlabel("repetition")
    ax.set_ylabel("ms / step")
    ax.set_xticks(reps)
    ax.set_ylim(bottom=0)
    ax.set_title(
        f"{cfg.scene} {cfg.resolution}², {cfg.spp} spp, {cfg.steps} steps/block: torchir/native = {ratio:.2f}",
        fontsize=9,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------ main
def main(argv: Sequence[str] | None = None) -> dict[str, MethodSummary]:
    """Run the benchmark, print the table, write the results; returns the per-method summaries."""
    cfg = parse_args(argv)
    torchir.backend.variant()
    print(f"[bench_overhead] {torchir.backend.describe()}, {os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}")
    setup = build(cfg)
    print(
        f"[bench_overhead] scene {cfg.scene} {cfg.resolution}x{cfg.resolution}, param {setup.key!r}, "
        f"spp {cfg.spp}; target {cfg.target_spp} spp in {setup.target_seconds:.2f} s"
    )

    t0 = time.perf_counter()
    warm = warm_up(setup, cfg.warmup)
    print(
        f"[bench_overhead] warm-up: {cfg.warmup} steps/method in {time.perf_counter() - t0:.1f} s, kernels compiled "
        + ", ".join(f"{m} {warm[m].compiled}" for m in METHODS)
    )
    print(f"[bench_overhead] timing {cfg.reps} x {cfg.steps} steps per method (ABAB, swapped every repetition)")
    blocks = benchmark(setup, cfg)

    summaries = {m: summarise(blocks, m, setup.loops[m].value()) for m in METHODS}
    ratios = ratio_per_rep(summaries)
    ratio = float(np.median(ratios))
    out = Path(cfg.out)
    save(out, cfg, setup, warm, blocks, summaries, ratios, ratio)

    print()
    print(format_table(summaries, ratio))
    print(f"per-repetition ratios: {', '.join(f'{r:.2f}' for r in ratios)}")
    fmt = lambda v: "[" + ", ".join(f"{x:.3f}" for x in v) + "]"  # noqa: E731
    print(
        f"{setup.key}: true {fmt(setup.true_value)}, after {cfg.warmup + cfg.reps * cfg.steps} steps: "
        + ", ".join(f"{m} {fmt(summaries[m].final_value)}" for m in METHODS)
    )
    print(f"goal: ratio <= 1.0 -> {'met' if ratio <= 1.0 else 'NOT met'}; zero compilations after warm-up -> "
          f"{'met' if all(summaries[m].compiled == 0 for m in METHODS) else 'NOT met'}")
    load = os.getloadavg()[0]
    if load > 0.75 * (os.cpu_count() or 1) + 1.0:
        print(f"note: 1-min load average {load:.1f} on {os.cpu_count()} CPUs: other processes competed for the CPU")
    print(f"wrote {out / 'results.json'} and {out / 'seconds_per_step.png'}")
    return summaries


if __name__ == "__main__":
    main()
