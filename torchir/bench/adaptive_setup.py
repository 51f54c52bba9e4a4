"""``torchir bench adaptive``'s settings (command line), its two problems (the Cornell box's
painted canvas; a glossy sphere behind diffuse objects) with cached targets, and the gradient
estimators and variance statistics its parts share."""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

import torchir
from torchir.functions import render
from torchir.modules.losses import L2Loss
from torchir.samplers import AdaptivePixelSampler, LossPixelSampler, UniformPixelSampler, sampled_loss

SAMPLER_CLASSES = {"uniform": UniformPixelSampler, "eq5": LossPixelSampler, "adaptive": AdaptivePixelSampler}
METHODS = ("uniform", "eq5", "adaptive")
TEX = "canvas.bsdf.reflectance.data"
RED = "red.reflectance.value"
ALPHA = "mirror.bsdf.alpha.value"
SMOOTH = 10  # trailing window (iterations) of the smoothed error curves


# ------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class Config:
    """Benchmark settings (see :func:`parse_args`)."""

    resolution: int = 128
    budgets: tuple[float, ...] = (0.03, 0.01)
    draws: int = 200
    seeds: int = 5
    iters: int = 300
    low_budget: float = 0.01
    plateau_iters: int = 500
    plateau_seeds: int = 3
    plateau_variants: tuple[str, ...] = ("adaptive", "alpha0.3", "refresh5", "paper", "scale2")
    late_draws: int = 100
    glossy_resolution: int = 64
    glossy_draws: int = 200
    glossy_init: float = 0.2
    glossy_truth: float = 0.05
    target_spp: int = 1024
    lr: float = 0.02
    parts: str = "abcd"
    quick: bool = False
    out: str = "results/bench_adaptive"


# Mitigation knobs of part (d): name -> AdaptivePixelSampler options (all exist in the sampler).
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "uniform": ("uniform", {}),
    "eq5": ("eq5", {}),
    "adaptive": ("adaptive", {}),
    "alpha0.3": ("adaptive", {"alpha": 0.3}),
    "refresh5": ("adaptive", {"refresh_every": 5}),
    "paper": ("adaptive", {"multires": "paper"}),
    "scale2": ("adaptive", {"scale": 2, "min_side": 16}),
    "levels0": ("adaptive", {"levels": 0}),
}


def parse_args(argv: Sequence[str] | None = None) -> Config:
    """Command-line options -> :class:`Config` (``--quick`` shrinks resolution, seeds, iterations)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="cbox image side (default 128, quick 64)")
    p.add_argument("--budgets", default=None, help="comma-separated pixel fractions for part a (default 0.03,0.01)")
    p.add_argument("--draws", type=int, default=None, help="gradient draws per method in part a (>= 100)")
    p.add_argument("--seeds", type=int, default=None, help="optimisation seeds in part b (default 5, quick 3)")
    p.add_argument("--iters", type=int, default=None, help="iterations in part b (default 300, quick 150)")
    p.add_argument("--plateau-iters", type=int, default=None, help="iterations in part d (default 500, quick 250)")
    p.add_argument("--plateau-seeds", type=int, default=None, help="seeds in part d (default 3, quick 2)")
    p.add_argument("--variants", default=None, help=f"part-d adaptive variants, from {sorted(VARIANTS)}")
    p.add_argument("--target-spp", type=int, default=1024, help="samples per pixel of the target images")
    p.add_argument("--lr", type=float, default=0.02, help="Adam learning rate")
    p.add_argument("--parts", default="abcd", help="which parts to run (subset of 'abcd')")
    p.add_argument("--out", default="results/bench_adaptive", help="output directory")
    p.add_argument("--quick", action="store_true", help="64x64, 3 seeds, fewer iterations and draws")
    a = p.parse_args(argv)
    q = a.quick
    pick = lambda given, full, quick: given if given is not None else (quick if q else full)
    budgets = tuple(float(b) for b in a.budgets.split(",")) if a.budgets else (0.03, 0.01)
    variants = tuple(v for v in a.variants.split(",") if v) if a.variants else (
        ("adaptive", "alpha0.3") if q else ("adaptive", "alpha0.3", "refresh5", "paper", "scale2")
    )
    cfg = Config(
        resolution=pick(a.resolution, 128, 64),
        budgets=budgets,
        draws=pick(a.draws, 200, 100),
        seeds=pick(a.seeds, 5, 3),
        iters=pick(a.iters, 300, 150),
        plateau_iters=pick(a.plateau_iters, 500, 250),
        plateau_seeds=pick(a.plateau_seeds, 3, 2),
        plateau_variants=variants,
        late_draws=pick(a.draws, 200, 50),
        glossy_resolution=64,
        glossy_draws=pick(a.draws, 200, 100),
        target_spp=a.target_spp,
        lr=a.lr,
        parts=a.parts,
        quick=q,
        out=a.out,
    )
    if not set(cfg.parts) <= set("abcd") or not cfg.parts:
        p.error("--parts must be a non-empty subset of 'abcd'")
    if cfg.draws < 2 or cfg.seeds < 1 or cfg.iters < SMOOTH or cfg.plateau_iters < SMOOTH:
        p.error(f"need --draws >= 2, --seeds >= 1, --iters and --plateau-iters >= {SMOOTH}")
    if not all(0.0 < b <= 1.0 for b in budgets):
        p.error("--budgets must be fractions in (0, 1]")
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; choose from {sorted(VARIANTS)}")
    return cfg


# ------------------------------------------------------------------------------ problems
@dataclass
class Problem:
    """A scene, the optimised parameters (init and truth), the target and the loss."""

    name: str
    scene: torchir.Scene
    init: dict[str, torch.Tensor]
    truth: dict[str, torch.Tensor]
    target: torch.Tensor  # (C, H, W)
    target_seconds: float
    loss_fn: L2Loss = field(default_factory=L2Loss)

    @property
    def m(self) -> int:
        h, w = self.scene.resolution
        return h * w

    def leaves(self, values: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """Fresh leaf tensors (requires_grad) of ``values`` (default: the initial values)."""
        values = self.init if values is None else values
        return {k: v.detach().clone().requires_grad_() for k, v in values.items()}


def cached_target(scene: torchir.Scene, path: Path, spp: int, chunk: int = 128) -> tuple[torch.Tensor, float]:
    """High-spp target of the scene's loaded values, ``(C, H, W)``, cached at ``path``."""
    if path.exists():
        return torch.load(path), 0.0
    t0 = time.perf_counter()
    images = []
    with torch.no_grad():
        for i in range((spp + chunk - 1) // chunk):
            n = min(chunk, spp - i * chunk)
            images.append(render(scene, {}, spp=n, seed=2**31 - 1 - i) * n)
    target = (torch.stack(images).sum(0) / spp).contiguous()
    seconds = time.perf_counter() - t0
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(target, path)
    return target, seconds


def cbox_problem(cfg: Config, out: Path) -> Problem:
    scene = torchir.Scene.builtin("cbox", resolution=cfg.resolution, canvas=8)
    truth = {TEX: scene.get(TEX), RED: scene.get(RED)}
    init = {TEX: torch.full_like(truth[TEX], 0.5), RED: torch.full_like(truth[RED], 0.3)}
    target, seconds = cached_target(scene, out / f"target_cbox_canvas8_{cfg.resolution}_{cfg.target_spp}spp.pt", cfg.target_spp)
    return Problem("cbox", scene, init, truth, target, seconds)


def glossy_dict(resolution: int, alpha: float) -> dict[str, Any]:
    """Fig. 3 analogue: a rough-conductor (GGX, aluminium) sphere behind three diffuse objects,
    floor, area light, dim environment; prb max_depth 3 (the objects are seen in the sphere
    with direct light), box filter."""
    T = mi.ScalarTransform4f

    def diffuse(c: list[float]) -> dict[str, Any]:
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": c}}

    film = {
        "type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"},
        "pixel_format": "rgb", "component_format": "float32", "sample_border": False,
    }
    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 3},
        "sensor": {
            "type": "perspective", "fov": 40, "fov_axis": "smaller",
            "to_world": T().look_at(origin=[0, 1.0, 4.5], target=[0, 0.6, 0], up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": 4}, "film": film,
        },
        "mirror": {
            "type": "sphere", "center": [0, 0.8, -0.6], "radius": 0.8,
            "bsdf": {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": alpha},
        },
        "obj_a": {"type": "sphere", "center": [-0.9, 0.25, 0.8], "radius": 0.25, "bsdf": diffuse([0.8, 0.2, 0.2])},
        "obj_b": {"type": "cube", "to_world": T().translate([0.0, 0.2, 1.1]).scale(0.2), "bsdf": diffuse([0.2, 0.7, 0.2])},
        "obj_c": {"type": "sphere", "center": [0.9, 0.3, 0.7], "radius": 0.3, "bsdf": diffuse([0.2, 0.3, 0.8])},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4.0), "bsdf": diffuse([0.4, 0.4, 0.4])},
        "light": {
            "type": "rectangle", "to_world": T().translate([0, 3.0, 1.5]).rotate([1, 0, 0], 90).scale(0.8),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 12.0}},
        },
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.1}},
    }


def glossy_problem(cfg: Config, out: Path) -> Problem:
    scene = torchir.Scene.from_dict(glossy_dict(cfg.glossy_resolution, cfg.glossy_truth))
    truth = {ALPHA: scene.get(ALPHA)}
    init = {ALPHA: torch.full_like(truth[ALPHA], cfg.glossy_init)}
    path = out / f"target_glossy_{cfg.glossy_resolution}_{cfg.glossy_truth}_{cfg.target_spp}spp.pt"
    target, seconds = cached_target(scene, path, cfg.target_spp)
    return Problem("glossy", scene, init, truth, target, seconds)


# ------------------------------------------------------------------------------ estimators
def make_sampler(problem: Problem, strategy: str, budget: float, seed: int, **options: Any):
    return SAMPLER_CLASSES[strategy](problem.scene, budget=budget, seed=seed, **options)


def refresh(problem: Problem, sampler, values: dict[str, torch.Tensor], step: int) -> None:
    """Stage 1 (as ``InverseRenderingModule.refresh_sampler``)."""
    sampler.update(values, [problem.target], problem.loss_fn, step=step)


def pixel_loss(problem: Problem, sampler, values: dict[str, torch.Tensor], seed: int) -> tuple[torch.Tensor, int]:
    """The importance-weighted loss of one pixel batch (:func:`torchir.samplers.sampled_loss`,
    one view, spp = spp_grad = 1) and the paths it traces (primal + replay)."""
    batch = sampler.sample()
    scored = sampled_loss(problem.scene, values, batch, [problem.target], [0], problem.loss_fn, seed=lambda view: seed, spp=1, spp_grad=1)
    return scored.loss, 2 * batch.index.numel()


def full_loss(problem: Problem, values: dict[str, torch.Tensor], seed: int) -> tuple[torch.Tensor, int]:
    """The full-image loss at 1 spp (primal + replay) and its paths."""
    image = render(problem.scene, values, spp=1, seed=seed, spp_grad=1)
    return problem.loss_fn(image[None], problem.target[None]), 2 * problem.m


def flat_grad(loss: torch.Tensor, values: dict[str, torch.Tensor]) -> torch.Tensor:
    grads = torch.autograd.grad(loss, list(values.values()))
    return torch.cat([g.reshape(-1) for g in grads]).double()


def draw_seed(*parts: int) -> int:
    """A render seed from integers (splitmix-style mixing), in [0, 2^32)."""
    h = 0x9E3779B97F4A7C15
    for p in parts:
        h = ((h ^ (p + 0x632BE59BD9B4E019)) * 0xBF58476D1CE4E5B9) % 2**64
        h ^= h >> 31
    return int(h % (2**32 - 1))


@dataclass
class VarianceResult:
    """Gradient statistics of one estimator over independent draws at fixed parameters."""

    method: str
    budget: float | None
    draws: int
    pixels: int
    paths_per_draw: float
    trace_all: float
    trace_tex: float  # the first parameter's components only (texture / roughness)
    seconds_per_draw: float
    stage1_seconds: float
    predicted_gain: float
    ess_fraction: float
    max_weight_ratio: float
    mean: list[float] = field(default_factory=list, repr=False)
    var: list[float] = field(default_factory=list, repr=False)


def gradient_statistics(problem: Problem, method: str, budget: float | None, draws: int, values: dict[str, torch.Tensor],
                        seed: int, sampler=None, stage1: bool = True, label: str | None = None) -> VarianceResult:
    """``draws`` independent gradient estimates at ``values`` (fresh render seeds and pixels each
    draw; one pmf, from one Stage 1 at ``values`` unless ``sampler`` is given with ``stage1=False``)."""
    leaves = problem.leaves(values)
    first = next(iter(leaves.values())).numel()
    stage1_seconds, gain = 0.0, 1.0
    if method != "full":
        if sampler is None:
            sampler = make_sampler(problem, method, budget, seed)
        if stage1 and sampler.uses_stage1:
            dr.sync_thread()
            t0 = time.perf_counter()
            refresh(problem, sampler, leaves, 0)
            stage1_seconds = time.perf_counter() - t0
        gain = float(sampler.diagnostics().get("predicted_gain", 1.0))
    samples, ess, maxw, seconds, paths = [], [], [], [], 0
    for i in range(draws):
        s = draw_seed(seed, 7, i)
        dr.sync_thread()
        t0 = time.perf_counter()
        loss, paths = full_loss(problem, leaves, s) if method == "full" else pixel_loss(problem, sampler, leaves, s)
        samples.append(flat_grad(loss, leaves))
        dr.sync_thread()
        seconds.append(time.perf_counter() - t0)
        if method != "full":
            d = sampler.diagnostics()
            ess.append(d.get("ess_fraction", 1.0))
            maxw.append(d.get("max_weight_ratio", 1.0))
    g = torch.stack(samples)
    var = g.var(0, unbiased=True)
    result = VarianceResult(
        method=label or method, budget=budget, draws=draws,
        pixels=problem.m if method == "full" else sampler.budget, paths_per_draw=float(paths),
        trace_all=float(var.sum()), trace_tex=float(var[:first].sum()),
        seconds_per_draw=float(np.median(seconds[1:] if draws > 2 else seconds)), stage1_seconds=stage1_seconds,
        predicted_gain=gain, ess_fraction=float(np.mean(ess)) if ess else 1.0,
        max_weight_ratio=float(np.max(maxw)) if maxw else 1.0,
        mean=g.mean(0).tolist(), var=var.tolist(),
    )
    result.samples = g  # (draws, parameters), for bootstrap intervals (not a dataclass field: not in results.json)
    return result


def bootstrap_traces(samples: torch.Tensor, reps: int = 1000, seed: int = 0) -> torch.Tensor:
    """Trace of the covariance of ``reps`` bootstrap resamples of the draws, ``(reps,)``."""
    g = torch.Generator(device="cpu").manual_seed(seed)  # the same resamples on every device
    k = samples.shape[0]
    out = []
    for chunk in range(0, reps, 100):
        idx = torch.randint(0, k, (min(100, reps - chunk), k), generator=g, device="cpu").to(samples.device)
        out.append(samples[idx].var(1, unbiased=True).sum(-1))
    return torch.cat(out)


def ratio_interval(base: VarianceResult, r: VarianceResult, level: float = 0.9) -> tuple[float, float]:
    """Percentile bootstrap interval of ``tr(base) / tr(r)`` (draws resampled independently): the
    trace estimates are heavy-tailed (rare pixels with huge adjoints), so 100 draws leave a wide
    interval."""
    if base is r:
        return 1.0, 1.0
    ratios = bootstrap_traces(base.samples, seed=1) / bootstrap_traces(r.samples, seed=2)
    lo, hi = torch.quantile(ratios, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=ratios.dtype))
    return float(lo), float(hi)


def z_scores(a: VarianceResult, ref: VarianceResult) -> np.ndarray:
    """Per-component z-scores of the difference of two estimators' means (unbiasedness check)."""
    ma, mb, va, vb = (np.array(x) for x in (a.mean, ref.mean, a.var, ref.var))
    se = np.sqrt(va / a.draws + vb / ref.draws)
    keep = se > 0
    return (ma[keep] - mb[keep]) / se[keep]
