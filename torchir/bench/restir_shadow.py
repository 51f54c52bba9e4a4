#!/usr/bin/env python
"""ReSTIR for a pose seen only through its shadow (paper 004, Fig. 10 "Tree"), at equal time.

``occluded_lights``: the ``blocker`` hangs outside the camera's view and casts a sharp shadow on
the floor. Its rotation about the vertical axis (:func:`torchir.derived.rigid_transform`) is
recovered from the image alone, from several starts, with Adam on the L2 loss. Methods:

* **ReSTIR**: spatiotemporal reuse (``ReSTIRSampler`` defaults) + boundary terms, the shadow-edge
  samples reused across steps (``edge_temporal``);
* **forward-only**: reuse for the image; plain RIS for the interior gradient, and shadow-edge
  samples without reuse, by edge length (the paper's edge guiding, Eq. 27, is a by-product of
  its edge reservoirs);
* **B.2**: RIS with the same candidates, no reuse, edges by length (as the paper's B.2);
* **B.2, guided edges**: B.2 with torchir's edge guide (a running estimate across steps, kept
  by every preset unless ``edge_guiding`` is off): a stronger baseline than the paper's;
* **ReSTIR, projective edges**: ReSTIR with the shadow edges from ``direct_projective`` (every
  edge of the scene) instead of edge samples on the blocker alone;
* **direct_projective**: Mitsuba's own integrator (no guiding), no ``ReSTIRSampler``.

The blocker's gradient is entirely a shadow-boundary term, weighted by the loss's adjoint
``2 (image - target)``: the samplers estimate it from points on the blocker's edges. Reuse helps
twice: through the image (a less noisy adjoint, which forward-only shares) and, for ReSTIR alone,
through edge samples kept across steps (paper 004 Alg. 6 with the whole edge sample in the
reservoir). The gradient spread is measured at one angle, so there the chains keep their samples
on unmoved geometry: an optimistic case for ReSTIR. **Equal time**: ReSTIR runs ``--steps``
steps from each start (burn-in included in its time); every other method then steps until it
has used the same wall time (at most ``4 x --steps``). A start converges when the final angle is
within ``--tolerance`` degrees of the truth.

Usage:
    python -m torchir.bench.restir_shadow --quick    # 32², 2 starts, 20 steps (< 1 min)
    python -m torchir.bench.restir_shadow            # 64², starts +-20, +-30 degrees, 80 steps
    python -m torchir.bench.restir_shadow --methods ReSTIR "B.2, guided edges"   # some methods only

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

METHODS = ("ReSTIR", "forward-only", "B.2", "B.2, guided edges", "ReSTIR, projective edges", "direct_projective")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 64, quick 32)")
    p.add_argument("--starts", default=None,
                   help="start angles in degrees, comma-separated (default 20,-20,30,-30: beyond about 40 the loss is flat; quick 20,-20)")
    p.add_argument("--steps", type=int, default=None, help="ReSTIR steps per start (default 80, quick 20)")
    p.add_argument("--burn-in", type=int, default=32)
    p.add_argument("--lr", type=float, default=1.0, help="Adam learning rate (degrees)")
    p.add_argument("--target-spp", type=int, default=256)
    p.add_argument("--tolerance", type=float, default=5.0, help="converged: final |angle| below this (degrees)")
    p.add_argument("--spread-steps", type=int, default=None, help="gradients per method for the spread table (default 24, quick 8)")
    p.add_argument("--spread-angle", type=float, default=10.0, help="angle (degrees) where the gradient spread is measured")
    p.add_argument("--blocker", choices=("box", "crown"), default="box",
                   help="occluded_lights' blocker: a box (12 edges) or a lumpy crown (3312 edges, most never on a shadow's outline)")
    p.add_argument("--edge-candidates", type=int, default=1,
                   help="whole shadow-edge samples per kept sample, RIS (the integrator's edge_candidates), for every torchir method")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), metavar="METHOD",
                   help="methods to run, in this order (quote names with spaces; default all: "
                        + "; ".join(METHODS) + "); the first sets the time budget")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default="results/bench_restir_shadow")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (32 if a.quick else 64)
    a.starts = [float(s) for s in (a.starts or ("20,-20" if a.quick else "20,-20,30,-30")).split(",")]
    a.steps = a.steps or (20 if a.quick else 80)
    a.spread_steps = a.spread_steps or (8 if a.quick else 24)
    return a


def shadow_problem(resolution: int, integrator: dict[str, Any] | None = None, blocker: str = "box") -> tuple[torchir.Scene, str]:
    """``occluded_lights`` with the blocker's rotation about z as a derived parameter."""
    scene = torchir.Scene.builtin("occluded_lights", resolution=resolution, override_integrator=integrator, blocker=blocker)
    return scene, rigid_transform(scene, "blocker", rotation_axis=[0, 0, 1], pivot=list(BLOCKER_CENTER))[1]


def sampler_for(method: str, scene: torchir.Scene, burn_in: int, edge_candidates: int = 1) -> ReSTIRSampler | None:
    if method == "direct_projective":
        return None
    preset = {"ReSTIR": "restir", "forward-only": "forward_only", "B.2": "b2", "B.2, guided edges": "b2",
              "ReSTIR, projective edges": "restir"}[method]
    sampler = ReSTIRSampler(scene, preset=preset, burn_in=burn_in)
    if method == "ReSTIR, projective edges":
        sampler.integrator.shadow_edge_sampling = False
    if method in ("forward-only", "B.2"):  # the paper's: edge guiding is a by-product of its edge reservoirs (Eq. 27)
        sampler.integrator.edge_guiding = False
    sampler.integrator.edge_candidates = edge_candidates
    return sampler


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


def gradient_spread(problems: dict[str, tuple], target, a) -> dict[str, dict[str, float]]:
    """Per method, ``a.spread_steps`` gradients of the L2 loss at ``a.spread_angle`` (new seeds,
    the sampler's state carried as in a run): mean, standard deviation and median seconds per
    step; ``var_x_time`` = variance x seconds, the figure equal time compares."""
    out = {}
    for method in a.methods:
        scene, key = problems[method]
        sampler = sampler_for(method, scene, a.burn_in, a.edge_candidates)
        extra = {} if sampler is None else {"sampler": sampler}
        grads, seconds = [], []
        for i in range(a.spread_steps + 2):  # two first steps (burn-in, kernels) not counted
            theta = torch.tensor([a.spread_angle], requires_grad=True)
            t0 = time.perf_counter()
            ((render(scene, {key: theta}, spp=1, seed=5000 + i, **extra) - target) ** 2).mean().backward()
            if i >= 2:
                seconds.append(time.perf_counter() - t0)
                grads.append(float(theta.grad))
        g = torch.tensor(grads, dtype=torch.float64)
        sd, step = float(g.std()), float(torch.tensor(seconds).median())
        out[method] = {"mean": float(g.mean()), "sd": sd, "seconds_per_step": step, "var_x_time": sd * sd * step}
    return out


def summarize_spread(spread: dict[str, dict[str, float]], angle: float) -> str:
    best = min((r["var_x_time"] for r in spread.values() if r["var_x_time"] > 0), default=0.0)  # 0: no sample found an edge
    lines = [f"Gradient d(loss)/d(angle) at {angle:g} degrees, one step each (spp 1):", "",
             "| method | mean | sd | sd / mean | s/step | variance x time | x best |", "|---|---|---|---|---|---|---|"]
    for name, r in spread.items():
        rel = r["sd"] / abs(r["mean"]) if r["mean"] else float("inf")
        lines.append(f"| {name} | {r['mean']:.3g} | {r['sd']:.3g} | {rel:.2f} | {r['seconds_per_step']:.3f} | "
                     f"{r['var_x_time']:.3g} | {r['var_x_time'] / best if best > 0 and r['var_x_time'] > 0 else float('nan'):.3g} |")
    return "\n".join(lines) + "\n"


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
    scene, key = shadow_problem(a.resolution, blocker=a.blocker)
    plain, plain_key = shadow_problem(a.resolution, {"type": "direct_projective", "guiding": "none"}, blocker=a.blocker)
    target = render(plain, {plain_key: torch.tensor([0.0])}, spp=a.target_spp, seed=7).detach()
    problems = {m: (plain, plain_key) if m == "direct_projective" else (scene, key) for m in a.methods}
    for method in a.methods:  # compile every method's kernels before timing (a short burn-in)
        s, k = problems[method]
        fit(s, k, target, a.starts[0], sampler_for(method, s, 1, a.edge_candidates), a, 2, None)
    spread = gradient_spread(problems, target, a)
    results: dict[str, list[dict[str, Any]]] = {m: [] for m in a.methods}
    for start in a.starts:
        budget = None
        for method in a.methods:
            s, k = problems[method]
            t0 = time.perf_counter()
            sampler = sampler_for(method, s, a.burn_in, a.edge_candidates)
            run = fit(s, k, target, start, sampler, a, a.steps if budget is None else 4 * a.steps, budget)
            if budget is None:  # the first method (ReSTIR by default) sets the budget, its burn-in (in the first render) included
                budget = time.perf_counter() - t0
            results[method].append(run)
            print(f"{method} from {start:+.0f}: final {run['final']:.2f} in {run['steps']} steps, {run['seconds']:.1f} s", flush=True)
    summary = (f"# Pose from a shadow (occluded_lights, {a.blocker} blocker, edge candidates {a.edge_candidates}), {a.resolution}², Adam lr {a.lr}, equal time per start\n\n"
               + summarize(results, a.tolerance) + "\n" + summarize_spread(spread, a.spread_angle))
    write_outputs(out, summary, {"args": vars(a), "results": results, "spread": spread}, draw(results), "shadow.png",
                  "wall time (s; ReSTIR's burn-in included)", "blocker rotation (degrees; truth 0)")
    return results


if __name__ == "__main__":
    main()
