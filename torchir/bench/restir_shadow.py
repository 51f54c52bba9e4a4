#!/usr/bin/env python
"""ReSTIR for a pose seen only through its shadow (Wang et al. 2023, Fig. 10 "Tree"), at equal time.

``occluded_lights``: the ``blocker`` hangs outside the camera's view and casts a sharp shadow on
the floor. Its rotation about the vertical axis (:func:`torchir.derived.rigid_transform`) is
recovered from the image alone, from several starts, with Adam on the L2 loss. Methods:

* **ReSTIR**: spatiotemporal reuse (``ReSTIRSampler`` defaults) + boundary terms, the shadow-edge
  samples as ``edge_strategy`` picks them ("auto": fresh guided samples where the step's samples
  cover the blocker's (edge, light) pairs, else chains by length);
* **ReSTIR, edge chains**: ReSTIR with the shadow-edge samples always reused across steps
  (``edge_temporal``);
* **ReSTIR, no edge chains**: ReSTIR with fresh shadow-edge samples each step;
* **forward-only**: reuse for the image; plain RIS for the interior gradient, and shadow-edge
  samples without reuse, by edge length (the paper's edge guiding, Eq. 27, is a by-product of
  its edge reservoirs);
* **B.2**: RIS with the same candidates, no reuse, edges by length (as the paper's B.2);
* **B.2, guided edges**: B.2 with torchir's edge guide always on (a running estimate across
  steps; every preset's "auto" keeps it where the samples cover the pairs): a stronger baseline
  than the paper's where it can learn;
* **ReSTIR, projective edges**: ReSTIR with the shadow edges from ``direct_projective`` (every
  edge of the scene) instead of edge samples on the blocker alone;
* **direct_projective**: Mitsuba's own integrator (no guiding), no ``ReSTIRSampler``.

The blocker's gradient is entirely a shadow-boundary term, weighted by the loss's adjoint
``2 (image - target)``: the samplers estimate it from points on the blocker's edges. Reuse helps
twice: through the image (a less noisy adjoint, which forward-only shares) and, for ReSTIR alone,
through edge samples kept across steps (Wang et al. 2023, Alg. 6, with the whole edge sample in the
reservoir). The gradient spread is measured as in a run: the pose alternates between
``--spread-angle`` and ``--spread-angle + --spread-move`` (0: one pose, the chains' samples then
stay on unmoved geometry, an optimistic case for them). Beside the per-step variance it gives
the variance of Adam's first moment (the exponential average, beta 0.9, the optimizer follows),
and that against what independent steps would give: temporal reuse correlates the steps, and
the average then keeps more of their noise. **Equal time**: ReSTIR runs ``--steps``
steps from each start (burn-in included in its time); every other method then steps until it
has used the same wall time (at most ``4 x --steps``). A start converges when the angle's rms
over the last quarter of its time is within ``--tolerance`` degrees of the truth (the final angle
alone is one draw of the jitter); the time it settled is when it entered that band for good.

Usage:
    python -m torchir.bench.restir_shadow --quick    # 32², 2 starts, 20 steps (under 2 min with all eight methods)
    python -m torchir.bench.restir_shadow            # 64², starts +-20, +-30 degrees, 80 steps
    python -m torchir.bench.restir_shadow --blocker crown --rings 144   # 123 000 edges, few on the outline
    python -m torchir.bench.restir_shadow --blocker crown --optimizer sgd   # steps proportional to the gradient
    python -m torchir.bench.restir_shadow --methods ReSTIR "B.2, guided edges"   # some methods only

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/shadow.png`` (angle against
wall time).
"""
from __future__ import annotations

import argparse
import math
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

ADAM_BETA1 = 0.9  # torch.optim.Adam's default: the average whose noise the steps follow
SGD_LR = 1000.0  # degrees per unit of d(loss)/d(angle) (about 1e-3 per degree at 10 degrees off on the crown)

METHODS = ("ReSTIR", "ReSTIR, edge chains", "ReSTIR, no edge chains", "forward-only", "B.2", "B.2, guided edges", "ReSTIR, projective edges", "direct_projective")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 64, quick 32)")
    p.add_argument("--starts", default=None,
                   help="start angles in degrees, comma-separated (default 20,-20,30,-30: beyond about 40 the loss is flat; quick 20,-20)")
    p.add_argument("--steps", type=int, default=None, help="ReSTIR steps per start (default 80, quick 20)")
    p.add_argument("--burn-in", type=int, default=32)
    p.add_argument("--optimizer", choices=("adam", "sgd"), default="adam",
                   help="adam: steps of about lr whatever the gradient's scale; sgd: lr x the gradient, so its noise moves the pose")
    p.add_argument("--lr", type=float, default=None,
                   help=f"learning rate (default: adam 1 degree; sgd {SGD_LR:g}, about 1 degree a step at 10 degrees off on the crown)")
    p.add_argument("--target-spp", type=int, default=256)
    p.add_argument("--tolerance", type=float, default=5.0, help="converged: the last quarter's rms angle below this (degrees)")
    p.add_argument("--spread-steps", type=int, default=None, help="gradients per method for the spread table (default 96, quick 16)")
    p.add_argument("--spread-angle", type=float, default=10.0, help="angle (degrees) where the gradient spread is measured")
    p.add_argument("--spread-move", type=float, default=0.5,
                   help="the pose alternates by this many degrees between the spread's steps, as in a run (0: one pose)")
    p.add_argument("--blocker", choices=("box", "crown"), default="box",
                   help="occluded_lights' blocker: a box (12 edges) or a lumpy crown (3312 edges, most never on a shadow's outline)")
    p.add_argument("--rings", type=int, default=24,
                   help="the crown's latitude bands (6 rings (rings - 1) edges; more: a smaller share of them on the shadow's outline)")
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
    a.spread_steps = a.spread_steps or (16 if a.quick else 96)
    a.lr = a.lr if a.lr is not None else (1.0 if a.optimizer == "adam" else SGD_LR)
    return a


def shadow_problem(resolution: int, integrator: dict[str, Any] | None = None, blocker: str = "box",
                   rings: int = 24) -> tuple[torchir.Scene, str]:
    """``occluded_lights`` with the blocker's rotation about z as a derived parameter."""
    scene = torchir.Scene.builtin("occluded_lights", resolution=resolution, override_integrator=integrator, blocker=blocker, rings=rings)
    return scene, rigid_transform(scene, "blocker", rotation_axis=[0, 0, 1], pivot=list(BLOCKER_CENTER))[1]


def sampler_for(method: str, scene: torchir.Scene, burn_in: int, edge_candidates: int = 1) -> ReSTIRSampler | None:
    if method == "direct_projective":
        return None
    preset = {"ReSTIR": "restir", "ReSTIR, edge chains": "restir", "ReSTIR, no edge chains": "restir", "forward-only": "forward_only", "B.2": "b2", "B.2, guided edges": "b2",
              "ReSTIR, projective edges": "restir"}[method]
    edges: dict = {"edge_candidates": edge_candidates}
    if method == "ReSTIR, projective edges":
        edges["shadow_edge_sampling"] = False
    if method in ("ReSTIR, edge chains", "ReSTIR, no edge chains"):
        edges["edge_temporal"] = method == "ReSTIR, edge chains"
    if method == "B.2, guided edges":
        edges["edge_guiding"] = True
    if method in ("forward-only", "B.2"):  # the paper's: edge guiding is a by-product of its edge reservoirs (Eq. 27)
        edges["edge_guiding"] = False
    return ReSTIRSampler(scene, preset=preset, burn_in=burn_in, **edges)


def optimizer_for(theta: torch.Tensor, a: argparse.Namespace) -> torch.optim.Optimizer:
    """Adam (steps of about ``a.lr`` degrees) or plain SGD (``a.lr`` x the gradient)."""
    return torch.optim.Adam([theta], lr=a.lr) if a.optimizer == "adam" else torch.optim.SGD([theta], lr=a.lr)


def fit(scene, key, target, start, sampler, a, max_steps: int, budget: float | None) -> dict[str, Any]:
    """Adam from ``start`` until ``max_steps`` or, with ``budget``, that many seconds."""
    theta = torch.tensor([start], requires_grad=True)
    opt = optimizer_for(theta, a)
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
    rms = last_quarter_rms(angles, clock)
    return {"start": start, "angles": angles, "clock": clock, "seconds": elapsed, "steps": len(angles),
            "final": angles[-1], "last_quarter_rms": rms, "converged": rms < a.tolerance,
            "settled": settled_at(angles, clock, a.tolerance)}


def last_quarter_rms(angles: Sequence[float], clock: Sequence[float]) -> float:
    """The rms angle (degrees from the truth) over the steps in the last quarter of the wall time
    (at least the last step)."""
    start = 0.75 * clock[-1]
    tail = [angle for angle, t in zip(angles, clock) if t >= start] or [angles[-1]]
    return math.sqrt(sum(angle * angle for angle in tail) / len(tail))


def settled_at(angles: Sequence[float], clock: Sequence[float], tolerance: float) -> float | None:
    """The wall time after which every angle stays within ``tolerance`` of the truth (0), or
    None if the last one is outside."""
    settled = None
    for angle, t in zip(angles, clock):
        if abs(angle) >= tolerance:
            settled = None
        elif settled is None:
            settled = t
    return settled


def momentum_variance(grads: Sequence[float], beta: float = ADAM_BETA1, shuffles: int = 32) -> tuple[float, float]:
    """The variance of the exponential average (weight ``1 - beta`` on the newest, Adam's first
    moment) of a sequence of per-step gradients (N,), after ``1 / (1 - beta)`` warm-up steps, and
    its ratio to the same for the steps in random orders (``shuffles`` fixed-seed permutations:
    the same gradients, independent steps, and the same small-N bias): above 1 where steps share
    samples. (nan, nan) with too few steps."""
    g = torch.as_tensor(grads, dtype=torch.float64, device="cpu")
    warm_up = int(round(1.0 / (1.0 - beta)))
    if len(g) < warm_up + 2:
        return float("nan"), float("nan")

    def window(steps: torch.Tensor) -> float:
        average, averages = steps[:warm_up].mean(), []
        for x in steps[warm_up:]:
            average = beta * average + (1.0 - beta) * x
            averages.append(average)
        return float(torch.stack(averages).var())

    generator = torch.Generator(device="cpu").manual_seed(0)
    independent = sum(window(g[torch.randperm(len(g), generator=generator, device="cpu")]) for _ in range(shuffles)) / shuffles
    ordered = window(g)
    return ordered, ordered / independent if independent > 0 else float("nan")


def gradient_spread(problems: dict[str, tuple], target, a) -> dict[str, dict[str, float]]:
    """Per method, ``a.spread_steps`` gradients of the L2 loss, the pose alternating between
    ``a.spread_angle`` and ``a.spread_angle + a.spread_move`` (new seeds, the sampler's state
    carried as in a run): mean and standard deviation (of the steps at ``a.spread_angle``), median
    seconds per step, ``var_x_time`` = variance x seconds (the figure equal time compares), and
    ``momentum_var`` / ``momentum_x_independent`` (:func:`momentum_variance`, over every step)."""
    out = {}
    for method in a.methods:
        scene, key = problems[method]
        sampler = sampler_for(method, scene, a.burn_in, a.edge_candidates)
        extra = {} if sampler is None else {"sampler": sampler}
        grads, seconds = [], []
        for i in range(a.spread_steps + 2):  # two first steps (burn-in, kernels) not counted
            theta = torch.tensor([a.spread_angle + a.spread_move * (i % 2)], requires_grad=True)
            t0 = time.perf_counter()
            ((render(scene, {key: theta}, spp=1, seed=5000 + i, **extra) - target) ** 2).mean().backward()
            if i >= 2:
                seconds.append(time.perf_counter() - t0)
                grads.append(float(theta.grad))
        g = torch.tensor(grads[::2] if a.spread_move else grads, dtype=torch.float64)  # at spread_angle
        sd, step = float(g.std()), float(torch.tensor(seconds).median())
        window, inflation = momentum_variance(grads)
        out[method] = {"mean": float(g.mean()), "sd": sd, "seconds_per_step": step, "var_x_time": sd * sd * step,
                       "momentum_var": window, "momentum_x_independent": inflation}
    return out


def summarize_spread(spread: dict[str, dict[str, float]], angle: float, move: float = 0.0) -> str:
    """The spread table: per step, and through Adam's average (both x seconds per step, against
    the best method: the figures equal time compares)."""
    nan = float("nan")
    rows = {name: {**r, "step": r["sd"] ** 2 * r["seconds_per_step"],
                   "window": r.get("momentum_var", nan) * r["seconds_per_step"]} for name, r in spread.items()}

    def against_best(field: str) -> dict[str, float]:
        best = min((r[field] for r in rows.values() if r[field] > 0), default=0.0)  # 0: no sample found an edge
        return {name: r[field] / best if best > 0 and r[field] > 0 else nan for name, r in rows.items()}

    step_x, window_x = against_best("step"), against_best("window")
    pose = f"alternating with {angle + move:g} degrees, as in a run" if move else "one pose"
    lines = [f"Gradient d(loss)/d(angle) at {angle:g} degrees ({pose}), spp 1; Adam's average: its first moment (beta {ADAM_BETA1:g}):", "",
             "| method | mean | sd | sd / mean | s/step | variance x time | x best | Adam's average: variance x time | x best | x independent steps |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        rel = r["sd"] / abs(r["mean"]) if r["mean"] else float("inf")
        lines.append(f"| {name} | {r['mean']:.3g} | {r['sd']:.3g} | {rel:.2f} | {r['seconds_per_step']:.3f} | {r['var_x_time']:.3g} | "
                     f"{step_x[name]:.3g} | {r['window']:.3g} | {window_x[name]:.3g} | {r.get('momentum_x_independent', nan):.2f} |")
    return "\n".join(lines) + "\n"


def summarize(results: dict[str, list[dict[str, Any]]], tolerance: float) -> str:
    lines = [f"| method | converged (last quarter's rms within {tolerance:g} degrees) | last quarter's rms | final angles | steps | seconds | "
             f"settled within {tolerance:g} (s) |", "|---|---|---|---|---|---|---|"]
    for name, runs in results.items():
        done = sum(r["converged"] for r in runs)
        rms = ", ".join(f"{r['last_quarter_rms']:.1f}" if "last_quarter_rms" in r else "-" for r in runs)
        finals = ", ".join(f"{r['final']:.1f}" for r in runs)
        steps = ", ".join(str(r["steps"]) for r in runs)
        settled = ", ".join("-" if r.get("settled") is None else f"{r['settled']:.1f}" for r in runs)
        lines.append(f"| {name} | {done} of {len(runs)} | {rms} | {finals} | {steps} | {sum(r['seconds'] for r in runs):.1f} | {settled} |")
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
    scene, key = shadow_problem(a.resolution, blocker=a.blocker, rings=a.rings)
    plain, plain_key = shadow_problem(a.resolution, {"type": "direct_projective", "guiding": "none"}, blocker=a.blocker, rings=a.rings)
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
    summary = (f"# Pose from a shadow (occluded_lights, {a.blocker} blocker{f' of {a.rings} rings' if a.blocker == 'crown' else ''}, edge candidates {a.edge_candidates}), {a.resolution}², {a.optimizer} lr {a.lr:g}, equal time per start\n\n"
               + summarize(results, a.tolerance) + "\n" + summarize_spread(spread, a.spread_angle, a.spread_move))
    write_outputs(out, summary, {"args": vars(a), "results": results, "spread": spread}, draw(results), "shadow.png",
                  "wall time (s; ReSTIR's burn-in included)", "blocker rotation (degrees; truth 0)")
    return results


if __name__ == "__main__":
    main()
