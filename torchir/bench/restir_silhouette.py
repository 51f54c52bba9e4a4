#!/usr/bin/env python
"""Primary silhouettes with resampled and reused light samples (Wang et al. 2023, §5.1, Alg. 5).

The derivative of ``sum(adjoint * image)`` for the ``pig`` blob's vertical displacement,
primary-silhouette term only, at a fixed adjoint (the L2 loss's, the blob 0.05 above its
target pose). Methods:

* **direct_projective**: Mitsuba's estimator of the term (``sppc=0, sppi=0``, no guiding): one
  emitter and one BSDF sample on either side of the silhouette;
* **RIS, c candidates**: torchir's (:mod:`torchir.integrators._silhouettes`), edges of the blob
  drawn by projected length, RIS with ``c`` shadowed light candidates either side;
* **ReSTIR (Alg. 5)**: the same, both sides combined with the reservoirs of the integrator's
  step at the same pose (the step is the forward pass a ReSTIR run makes anyway: not timed);
* **light oracle**: RIS with 64 candidates, the most better light sampling can gain here.

Each method makes ``--calls`` estimates with new seeds; the table gives the relative sd, the
seconds per call and the variance x time against ``direct_projective`` (higher is better).
``--dome-lights``: the pig's small extra lights (powers spanning 100x), where light selection is
hard.

Usage:
    python -m torchir.bench.restir_silhouette --quick   # 32², one light and 64 dome lights (< 1 min)
    python -m torchir.bench.restir_silhouette           # 128², 0, 64 and 256 dome lights

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/silhouette.png`` (relative sd
against seconds per call).
"""
from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torchir  # noqa: I001  (before torch)

import drjit as dr
import mitsuba as mi
import numpy as np

from torchir.bench import write_outputs

ORACLE = 64
LIFT = 0.05  # the blob's height above its target pose where the gradient is taken


def methods(candidates: Sequence[int]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {"direct_projective": {"kind": "mitsuba"}}
    for c in candidates:
        out[f"RIS, {c} candidates"] = {"kind": "ris", "candidates": c}
    out[f"ReSTIR (Alg. 5), {max(candidates)} candidates"] = {"kind": "restir", "candidates": max(candidates)}
    out[f"light oracle, {ORACLE} candidates"] = {"kind": "ris", "candidates": ORACLE}
    return out


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 128, quick 32)")
    p.add_argument("--dome-lights", default=None, help="comma-separated pig dome_lights per scene (default 0,64,256; quick 0,64)")
    p.add_argument("--candidates", default="4,16", help="RIS candidates of torchir's rows, comma-separated")
    p.add_argument("--samples", type=int, default=None, help="silhouette samples per call (default one per pixel)")
    p.add_argument("--calls", type=int, default=None, help="estimates per method (default 32, quick 4)")
    p.add_argument("--warmup", type=int, default=3, help="untimed calls per method (kernels, reservoirs)")
    p.add_argument("--out", default="results/bench_restir_silhouette")
    p.add_argument("--quick", action="store_true")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (32 if a.quick else 128)
    a.dome_lights = [int(d) for d in (a.dome_lights or ("0,64" if a.quick else "0,64,256")).split(",")]
    a.candidates = [int(c) for c in a.candidates.split(",")]
    a.samples = a.samples or a.resolution * a.resolution
    a.calls = a.calls or (4 if a.quick else 32)
    return a


class Problem:
    """The pig at ``LIFT`` above its target, and the loss's adjoint there (64 spp renders)."""

    def __init__(self, resolution: int, dome_lights: int) -> None:
        from torchir.scenes import pig

        # sequential loading: the emitters keep their order, so runs repeat exactly
        self.scene = mi.load_dict(pig.build(resolution, dome_lights=dome_lights), parallel=False)
        self.params = mi.traverse(self.scene)
        self.key = "pig.vertex_positions"
        self.v0 = mi.Float(self.params[self.key])
        self.mesh = [s for s in self.scene.shapes() if s.id() == "pig"]
        self.pose(mi.Float(0.0))
        target = mi.render(self.scene, spp=64, seed=1)
        self.pose(mi.Float(LIFT))
        self.adjoint = mi.TensorXf(2.0 * (mi.render(self.scene, spp=64, seed=2).array - target.array), target.shape)

    def pose(self, height) -> None:
        p = dr.unravel(mi.Point3f, self.v0)
        self.params[self.key] = dr.ravel(mi.Point3f(p.x, p.y, p.z + height))
        self.params.update()


def measure(problem: Problem, options: dict[str, Any], a) -> dict[str, float]:
    """``a.calls`` estimates of the term (after ``a.warmup``): mean, sd, median seconds."""
    from torchir.integrators._silhouettes import silhouette_backward
    from torchir.integrators.restir_di import ReSTIRDirectIntegrator

    kind = options["kind"]
    if kind == "mitsuba":
        mitsuba = mi.load_dict({"type": "direct_projective", "sppc": 0, "sppi": 0, "guiding": "none"})
        spp = max(1, round(a.samples / a.resolution**2))
    else:
        reuse = kind == "restir"
        integrator = ReSTIRDirectIntegrator(candidates=options["candidates"], temporal=reuse, spatial=reuse)
    grads, seconds = [], []
    for i in range(a.warmup + a.calls):
        prev = None
        if kind == "restir":
            problem.pose(mi.Float(LIFT))
            with dr.suspend_grad():
                _, cache = integrator.step(problem.scene, 0, 500 + i, 1, zero_remainder=False)
            prev = cache.prev
            dr.eval(prev)
        height = mi.Float(LIFT)
        dr.enable_grad(height)
        problem.pose(height)
        dr.sync_thread()
        t0 = time.perf_counter()
        if kind == "mitsuba":
            mitsuba.render_backward(problem.scene, problem.params, problem.adjoint, seed=100 + i, spp=spp)
        else:
            silhouette_backward(integrator, problem.scene, 0, problem.adjoint, problem.mesh, a.samples, 100 + i, prev)
        g = dr.grad(height)[0]
        dr.sync_thread()
        if i >= a.warmup:
            seconds.append(time.perf_counter() - t0)
            grads.append(float(g))
    problem.pose(mi.Float(LIFT))
    g = np.array(grads)
    return {"mean": float(g.mean()), "sd": float(g.std(ddof=1)), "seconds": float(np.median(seconds)),
            "se": float(g.std(ddof=1) / math.sqrt(len(g)))}


def compare(rows: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Each row's variance and variance x time ratios against ``direct_projective`` (> 1: lower)."""
    base = rows["direct_projective"]
    out = {}
    for name, r in rows.items():
        var, base_var = r["sd"] ** 2, base["sd"] ** 2
        out[name] = {**r, "variance_gain": base_var / var if var > 0 else float("inf"),
                     "equal_time_gain": base_var * base["seconds"] / (var * r["seconds"]) if var > 0 else float("inf")}
    return out


def summarize(results: dict[str, dict[str, dict[str, float]]], a) -> str:
    lines = [f"# Primary silhouettes, pig, {a.resolution}², {a.samples} samples a call, {a.calls} calls", "",
             "| dome lights | method | mean | relative sd | ms / call | variance gain | variance x time gain |",
             "|---|---|---|---|---|---|---|"]
    for scene, rows in results.items():
        for name, r in rows.items():
            rel = r["sd"] / abs(r["mean"]) if r["mean"] else float("inf")
            lines.append(f"| {scene} | {name} | {r['mean']:.4g} | {rel:.3f} | {1e3 * r['seconds']:.1f} | "
                         f"{r['variance_gain']:.2f} | {r['equal_time_gain']:.2f} |")
    return "\n".join(lines) + "\n\nGains are against direct_projective (higher is better).\n"


def draw(results: dict[str, dict[str, dict[str, float]]]):
    """Relative sd against seconds per call: one marker per method, one colour per scene."""
    markers = "osD^vP*X"

    def on(ax) -> None:
        for i, (scene, rows) in enumerate(results.items()):
            for j, (name, r) in enumerate(rows.items()):
                rel = r["sd"] / abs(r["mean"]) if r["mean"] else float("nan")
                ax.scatter([r["seconds"]], [rel], color=f"C{i}", marker=markers[j % len(markers)],
                           label=f"{scene} dome lights: {name}", s=30)
        ax.set_xscale("log")
    return on


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    torchir.backend.set_variant()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, dict[str, float]]] = {}
    for dome in a.dome_lights:
        problem = Problem(a.resolution, dome)
        rows = {}
        for name, options in methods(a.candidates).items():
            rows[name] = measure(problem, options, a)
            r = rows[name]
            print(f"dome {dome} {name}: mean {r['mean']:.4g} sd {r['sd']:.3g} {1e3 * r['seconds']:.1f} ms", flush=True)
        results[str(dome)] = compare(rows)
    write_outputs(out, summarize(results, a), {"args": vars(a), "results": results}, draw(results), "silhouette.png",
                  "seconds per call", "relative sd of the derivative", log_y=True)
    return results


if __name__ == "__main__":
    main()
