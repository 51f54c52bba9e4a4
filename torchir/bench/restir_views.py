#!/usr/bin/env python
"""ReSTIR across views (Wang et al. 2023, Alg. 8): one carried-over reservoir store against one chain per sensor.

A multi-view texture problem: ``oxalis_lite`` (a textured canvas, two bright spots, dim and
hidden lights) seen by ``--views`` cameras on an arc in front of the canvas. Each step renders
one view (views in turn: a mini-batch of one), with the texture held fixed, and takes the
gradient of a fixed random linear loss; its error is ``||g - g_ref|| / ||g_ref||`` against that
view's ``prb`` gradient at ``--ref-spp``. Methods (``ReSTIRSampler`` options):

* **B.2**: RIS over the candidates, no reuse (the floor of what reuse must beat);
* **per-sensor (burn-in B)**: one reservoir chain per sensor (``multiview="per_sensor"``): each
  view burns in on its first visit and reuses only its own reservoirs of its last visit;
* **carry-over (burn-in B)**: one store (``multiview="carry_over"``): the first view burns in,
  every view reuses the store's reservoirs near its shading points (other views' too), and a
  render replaces only the reservoirs its camera sees.

Reported per method: RMS relative gradient error over all steps, wall time (burn-ins
included: they are spent to produce these gradients), and the efficiency ``1 / (error² x
time)`` relative to per-sensor chains with the same burn-in (> 1: carry-over is better at equal
time; squared errors fall as 1 / time at a fixed method).

Usage:
    python -m torchir.bench.restir_views --quick    # 32², 4 views, 16 steps (< 1 min)
    python -m torchir.bench.restir_views            # 128², 8 views, 64 steps (a few minutes)

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/views.png`` (gradient error
of each step against the cumulative wall time).
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torchir  # noqa: I001  (before torch)
from torchir.bench import write_outputs

import numpy as np
import torch

KEY = "canvas.bsdf.reflectance.data"


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 128, quick 32)")
    p.add_argument("--views", type=int, default=None, help="cameras (default 8, quick 4)")
    p.add_argument("--steps", type=int, default=None, help="gradient steps per method, one view each (default 64, quick 16)")
    p.add_argument("--burn-in", default=None, help="burn-in passes, comma-separated (default 32,4; quick 8,2)")
    p.add_argument("--candidates", type=int, default=16)
    p.add_argument("--spp", type=int, default=1)
    p.add_argument("--ref-spp", type=int, default=None, help="spp of each view's reference gradient (default 4096, quick 256)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default="results/bench_restir_views")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (32 if a.quick else 128)
    a.views = a.views or (4 if a.quick else 8)
    a.steps = a.steps or (16 if a.quick else 64)
    a.burn_in = [int(b) for b in (a.burn_in or ("8,2" if a.quick else "32,4")).split(",")]
    a.ref_spp = a.ref_spp or (256 if a.quick else 4096)
    return a


def views_scene(resolution: int, views: int) -> torchir.Scene:
    """``oxalis_lite`` seen by ``views`` cameras on a 70-degree arc, 3 units from the canvas."""
    return torchir.Scene.builtin("oxalis_lite", resolution=resolution, views=views)


def methods(a: argparse.Namespace) -> dict[str, dict[str, Any] | None]:
    out: dict[str, dict[str, Any] | None] = {"B.2": {"preset": "b2", "candidates": a.candidates}}
    for b in a.burn_in:
        for mode, label in (("per_sensor", "per-sensor"), ("carry_over", "carry-over")):
            out[f"{label} (burn-in {b})"] = {"candidates": a.candidates, "burn_in": b, "multiview": mode}
    return out


def _loss_weights(scene: torchir.Scene, views: int) -> list[torch.Tensor]:
    g = torch.Generator(device="cpu").manual_seed(0)
    h, w = scene.resolution
    return [torch.rand(3, h, w, generator=g, device="cpu").to(torchir.backend.device()) for _ in range(views)]


def _gradient(scene, texture, weights, view, spp, seed, sampler=None) -> torch.Tensor:
    from torchir.functions import render

    t = texture.clone().requires_grad_()
    (render(scene, {KEY: t}, spp=spp, seed=seed, sensor=view, sampler=sampler) * weights).sum().backward()
    return t.grad


def references(scene, texture, weights, a) -> list[torch.Tensor]:
    """Each view's prb gradient at ``ref_spp`` (in batches of 256 spp)."""
    batches = max(1, a.ref_spp // 256)
    return [torch.stack([_gradient(scene, texture, weights[v], v, min(256, a.ref_spp), 90_000 + 97 * v + b)
                         for b in range(batches)]).mean(0) for v in range(a.views)]


def run_method(scene, texture, weights, refs, options, a) -> dict[str, Any]:
    from torchir.samplers import ReSTIRSampler

    sampler = ReSTIRSampler(scene, **options)
    errors, clock, t = [], [], 0.0
    for step in range(a.steps):
        view = step % a.views
        t0 = time.perf_counter()
        g = _gradient(scene, texture, weights[view], view, a.spp, step, sampler)
        t += time.perf_counter() - t0
        errors.append(float((g - refs[view]).norm() / refs[view].norm()))
        clock.append(t)
    return {"errors": errors, "clock": clock, "seconds": t, "rms_error": float(np.sqrt(np.mean(np.square(errors))))}


def summarize(results: dict[str, dict[str, Any]], burn_ins: list[int]) -> str:
    lines = ["| method | RMS gradient error | seconds | efficiency vs per-sensor (same burn-in) |", "|---|---|---|---|"]
    for name, r in results.items():
        rel = "-"
        for b in burn_ins:
            base = results.get(f"per-sensor (burn-in {b})")
            if name == f"carry-over (burn-in {b})" and base:
                rel = f"{(base['rms_error'] ** 2 * base['seconds']) / (r['rms_error'] ** 2 * r['seconds']):.2f}x"
        lines.append(f"| {name} | {r['rms_error']:.4f} | {r['seconds']:.2f} | {rel} |")
    return "\n".join(lines) + "\n"


def draw(results: dict[str, dict[str, Any]]):
    """Each step's gradient error against the cumulative wall time, per method."""
    def on(ax) -> None:
        for name, r in results.items():
            ax.plot(r["clock"], r["errors"], ".-", ms=3, lw=0.8, label=name)
    return on


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = views_scene(a.resolution, a.views)
    texture = torch.full_like(scene.get(KEY), 0.5)
    weights = _loss_weights(scene, a.views)
    print(f"references: {a.views} views at {a.ref_spp} spp ...", flush=True)
    refs = references(scene, texture, weights, a)
    _gradient(scene, texture, weights[0], 0, a.spp, 0, __import__("torchir.samplers", fromlist=["x"]).ReSTIRSampler(
        scene, candidates=a.candidates, burn_in=1))  # compile the kernels before timing
    results = {}
    for name, options in methods(a).items():
        print(f"{name} ...", flush=True)
        results[name] = run_method(scene, texture, weights, refs, options, a)
    summary = (f"# ReSTIR across views: {a.views} views, {a.resolution}², {a.steps} steps, {a.spp} spp, "
               f"{a.candidates} candidates\n\n" + summarize(results, a.burn_in))
    write_outputs(out, summary, {"args": vars(a), "results": results}, draw(results), "views.png",
                  "wall time (s, burn-ins included)", "relative gradient error of the step", log_y=True)
    return results


if __name__ == "__main__":
    main()
