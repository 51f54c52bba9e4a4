#!/usr/bin/env python
"""ReSTIR for a pose seen only through its shadow (paper 004, Fig. 10 "Tree"), at equal time.

``occluded_lights``: the ``blocker`` hangs outside the camera's view and casts a sharp shadow on
the floor. Its rotation about the vertical axis (:func:`torchir.derived.rigid_transform`) is
recovered from the image alone, from several starts, with Adam on the L2 loss. Methods:

* **ReSTIR**: spatiotemporal reuse (``ReSTIRSampler`` defaults) + boundary terms;
* **forward-only**: reuse for the image, plain RIS for the interior gradient;
* **B.2**: RIS with the same candidates, no reuse;
* **direct_projective**: Mitsuba's own integrator (no guiding), no ``ReSTIRSampler``.

The blocker's gradient is entirely a shadow-boundary term (``direct_projective``'s, which
torchir adds without reuse), weighted by the loss's adjoint ``2 (image - target)``. Reuse
therefore helps through the image: a less noisy adjoint. **Equal time**: ReSTIR runs ``--steps``
steps from each start (burn-in included in its time); every other method then steps until it
has used the same wall time (at most ``4 x --steps``). A start converges when the final angle is
within ``--tolerance`` degrees of the truth.

Usage:
    python -m torchir.bench.restir_shadow --quick    # 32², 2 starts, 20 steps (< 1 min)
    python -m torchir.bench.restir_shadow            # 64², starts +-20, +-40 degrees, 80 steps

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/shadow.png`` (angle against
wall time).
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torchir  # noqa: I001  (before torch)

import torch

from torchir.bench import write_outputs
from torchir.derived import rigid_transform
from torchir.functions import render
from torchir.samplers import ReSTIRSampler
from torchir.scenes.occluded_lights import BLOCKER_CENTER

METHODS = ("ReSTIR", "forward-only", "B.2", "direct_projective")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 64, quick 32)")
    p.add_argument("--starts", default=None, help="start angles in degrees, comma-separated (default 20,-20,40,-40; quick 20,-20)")
    p.add_argument("--steps", type=int, default=None, help="ReSTIR steps per start (default 80, quick 20)")
    p.add_argument("--burn-in", type=int, default=32)
    p.add_argument("--lr", type=float, default=1.0, help="Adam learning rate (degrees)")
    p.add_argument("--target-spp", type=int, default=256)
    p.add_argument("--tolerance", type=float, default=5.0, help="converged: final |angle| below this (degrees)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default="results/bench_restir_shadow")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (32 if a.quick else 64)
    a.starts = [float(s) for s in (a.starts or ("20,-20" if a.quick else "20,-20,40,-40")).split(",")]
    a.steps = a.steps or (20 if a.quick else 80)
    return a


def shadow_problem(resolution: int, integrator: dict[str, Any] | None = None) -> tuple[torchir.Scene, str]:
    """``occluded_lights`` with the blocker's rotation about z as a derived parameter."""
    scene = torchir.Scene.builtin("occluded_lights", resolution=resolution, override_integrator=integrator)
    return scene, rigid_transform(scene, "blocker", rotation_axis=[0, 0, 1], pivot=list(BLOCKER_CENTER))[1]


def sampler_for(method: str, scene: torchir.Scene, burn_in: int) -> ReSTIRSampler | None:
    if method == "direct_projective":
        return None
    preset = {"ReSTIR": "restir", "forward-only": "forward_only", "B.2": "b2"}[method]
    return ReSTIRSampler(scene, preset=preset, burn_in=burn_in)


def fit(scene, key, target, start, sampler, a, max_steps: int, budget: float | None) -> dict[str, Any]:
    """Adam from ``start`` until ``max_steps`` or, with ``budget``, that many seconds."""
    theta = torch.tensor([start], requires_grad=True)
    opt = torch.optim.Adam([theta], lr=a.lr)
    angles, clock, elapsed = [], [], 0.0
    for step in range(max_steps):
        t0 = time.perf_counter()
        opt.zero_grad()
        loss = ((render(scene, {key: theta}, spp=1, seed=1000 + step, sampler=sampler) - target) ** 2).mean()
        loss.backward()
        opt.step()
        elapsed += time.perf_counter() - t0
        angles.append(float(theta.detach()))
        clock.append(elapsed)
        if budget is not None and elapsed >= budget:
            break
    final = angles[-1]
    return {"start": start, "angles": angles, "clock": clock, "seconds": elapsed, "steps": len(angles),
            "final": final, "converged": abs(final) < a.tolerance}


def summarize(results: dict[str, list[dict[str, Any]]], tolerance: float) -> str:
    lines = [f"| method | converged (final within {tolerance:g} degrees) | final angles | steps | seconds |", "|---|---|---|---|---|"]
    for name, runs in results.items():
        done = sum(r["converged"] for r in runs)
        finals = ", ".join(f"{r['final']:.1f}" for r in runs)
        steps = ", ".join(str(r["steps"]) for r in runs)
        lines.append(f"| {name} | {done} of {len(runs)} | {finals} | {steps} | {sum(r['seconds'] for r in runs):.1f} |")
    return "\n".join(lines) + "\n"


def draw(results: dict[str, list[dict[str, Any]]]):
    """The angle of every run against its wall time, one colour per method."""
    def on(ax) -> None:
        for i, (name, runs) in enumerate(results.items()):
            for j, r in enumerate(runs):
                ax.plot(r["clock"], r["angles"], color=f"C{i}", lw=0.9, label=name if j == 0 else None)
        ax.axhline(0.0, color="k", lw=0.5)
    return on


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    scene, key = shadow_problem(a.resolution)
    plain, plain_key = shadow_problem(a.resolution, {"type": "direct_projective", "guiding": "none"})
    target = render(plain, {plain_key: torch.tensor([0.0])}, spp=a.target_spp, seed=7).detach()
    for method in METHODS:  # compile every method's kernels before timing (a short burn-in)
        s, k = (plain, plain_key) if method == "direct_projective" else (scene, key)
        fit(s, k, target, a.starts[0], sampler_for(method, s, 1), a, 2, None)
    results: dict[str, list[dict[str, Any]]] = {m: [] for m in METHODS}
    for start in a.starts:
        budget = None
        for method in METHODS:
            s, k = (plain, plain_key) if method == "direct_projective" else (scene, key)
            t0 = time.perf_counter()
            sampler = sampler_for(method, s, a.burn_in)
            run = fit(s, k, target, start, sampler, a, a.steps if budget is None else 4 * a.steps, budget)
            if budget is None:  # ReSTIR sets the budget, its burn-in (in the first render) included
                budget = time.perf_counter() - t0
            results[method].append(run)
            print(f"{method} from {start:+.0f}: final {run['final']:.2f} in {run['steps']} steps, {run['seconds']:.1f} s", flush=True)
    summary = (f"# Pose from a shadow (occluded_lights), {a.resolution}², Adam lr {a.lr}, equal time per start\n\n"
               + summarize(results, a.tolerance))
    write_outputs(out, summary, {"args": vars(a), "results": results}, draw(results), "shadow.png",
                  "wall time (s; ReSTIR's burn-in included)", "blocker rotation (degrees; truth 0)")
    return results


if __name__ == "__main__":
    main()
