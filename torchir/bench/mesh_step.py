#!/usr/bin/env python
"""A shape step's cost, and its gradient's quality, against plain Mitsuba: interleaved, one process.

The step of Mitsuba's shape tutorial (``direct_projective``, ``sppi: 0``, one view, L1 loss,
Large Steps λ = 25, uniform Adam lr 0.1; :mod:`torchir.bench.shape_tutorial` has the assets) in
three arms, run in turn within every step so that machine load hits them alike:

- **mitsuba**: the notebook's step on the mesh as loaded (``ico_10k.ply`` repeats 351 seam
  vertices; Mitsuba takes each seam for an open border and recomputes the normals over the
  index topology, so its seams are shading creases);
- **mitsuba welded**: the same step on the mesh welded by hand (one vertex per position, faces
  remapped): what the seams cost Mitsuba itself;
- **torchir**: ``torchir.functions.render`` + ``LargeSteps`` + ``AdamUniform`` in a torch loop on
  the mesh as loaded (torchir welds for the boundary terms and keeps the normals smooth across
  seams: :mod:`torchir.welding`).

Reported per arm: the mean step after ``2 x views`` warm-up steps, its ratio to ``mitsuba``'s,
and the kernels compiled after warm-up (0 is the goal: each costs seconds on LLVM).

A cheaper step is only a win at equal gradient quality, so the suite also measures each arm's
gradient at the start mesh on view 0: the derivative of a linear functional ``mean(w * image)``
(``w``: the L2 residual of a high-spp render against the target, so its estimator is unbiased at
any spp), per surface position (a seam's copies summed), ``--repeats`` times at the step's spp.
The reference is ``mitsuba welded`` at ``--reference-spp`` (many independent renders summed).
Reported: relative RMS error, relative bias (the repeats' mean's distance from the reference,
its own variance taken out), seconds per gradient and the
efficiency ``1 / (error² x seconds)`` (work-normalised variance; its ratio says how much faster an
arm reaches a given gradient error).

Usage::

    torchir bench mesh_step --tutorials mitsuba-tutorials/scenes [--quick]

Writes ``results.json``, ``summary.md`` and ``step_times.png``.
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchir.bench import environment, write_outputs
from torchir.bench._common import fmt, markdown_table
from torchir.bench.shape_tutorial import (LAMBDA, LR, VIEWS, Assets, fill_sizes, run_assets, scene_dict, sensor_dicts,
                                          tutorial_parser)

ARMS = ("mitsuba", "mitsuba welded", "torchir")
KEY = "shape.vertex_positions"


def welded_mesh(path: Path) -> tuple[Any, np.ndarray]:
    """The mesh at ``path`` welded by hand (:func:`torchir.bench.mesh_gradients.welded_copy`: one
    vertex per position, smooth normals), id ``shape``, and for each vertex of the file its welded index."""
    import mitsuba as mi

    from torchir.bench.mesh_gradients import welded_copy
    from torchir.welding import mesh_weld

    loaded = mi.load_dict({"type": "ply", "filename": str(path)})
    mesh = welded_copy(loaded)
    mesh.set_id("shape")
    return mesh, np.unique(mesh_weld(loaded).rep, return_inverse=True)[1].ravel()


class MitsubaArm:
    """The notebook's step on one scene (``mesh``: a PLY path or a Mitsuba mesh)."""

    def __init__(self, mesh: Any, assets: Assets, sensors: list, refs: list, spp: int) -> None:
        import mitsuba as mi

        spec = scene_dict(assets.start, assets)
        if not isinstance(mesh, Path):
            spec["shape"] = mesh
        self.scene = mi.load_dict(spec)
        self.params = mi.traverse(self.scene)
        self.sensors, self.refs, self.spp = sensors, refs, spp
        self.ls = mi.ad.LargeSteps(self.params[KEY], self.params["shape.faces"], LAMBDA)
        self.opt = mi.ad.Adam(lr=LR, uniform=True)
        self.opt["u"] = self.ls.to_differential(self.params[KEY])
        self.start = type(self.params[KEY])(self.params[KEY])

    def step(self, step: int, view: int) -> None:
        import drjit as dr
        import mitsuba as mi

        self.params[KEY] = self.ls.from_differential(self.opt["u"])
        self.params.update()
        image = mi.render(self.scene, self.params, sensor=self.sensors[view], seed=step, spp=self.spp)
        dr.backward(dr.mean(dr.abs(image - self.refs[view])))
        self.opt.step()
        dr.eval(self.opt["u"])
        dr.sync_thread()

    def gradient(self, weights: Any, seed: int, spp: int) -> np.ndarray:
        """``d mean(weights * image) / d positions`` at the start mesh, ``(V, 3)``."""
        import drjit as dr
        import mitsuba as mi

        positions = type(self.start)(self.start)
        dr.enable_grad(positions)
        self.params[KEY] = positions
        self.params.update()
        image = mi.render(self.scene, self.params, sensor=self.sensors[0], seed=seed, spp=spp)
        dr.backward(dr.mean(image * weights))
        grad = np.array(dr.grad(positions), np.float64).reshape(-1, 3)
        dr.disable_grad(positions)
        return grad


class TorchirArm:
    """``render`` + ``LargeSteps`` + ``AdamUniform`` on the mesh as loaded."""

    def __init__(self, assets: Assets, sensors: list, refs: list, spp: int) -> None:
        import torch

        import torchir
        from torchir.geometry import AdamUniform, LargeSteps

        self.scene = torchir.Scene.from_dict(scene_dict(assets.start, assets), sensors=sensors)
        self.ls = LargeSteps(self.scene, "shape", LAMBDA)
        self.start = self.scene.get(KEY).detach().clone()
        self.u = self.ls.to_differential(self.start).requires_grad_()
        self.opt = AdamUniform([self.u], lr=LR)
        self.refs = [torch.from_numpy(np.array(r)).permute(2, 0, 1).contiguous() for r in refs]
        self.spp = spp

    def step(self, step: int, view: int) -> None:
        from torchir.functions import render

        self.opt.zero_grad()
        image = render(self.scene, {KEY: self.ls.from_differential(self.u)}, spp=self.spp, seed=step, sensor=view)
        (image - self.refs[view]).abs().mean().backward()
        self.opt.step()

    def gradient(self, weights: Any, seed: int, spp: int) -> np.ndarray:
        import torch

        from torchir.functions import render

        x = self.start.clone().requires_grad_()
        image = render(self.scene, {KEY: x}, spp=spp, seed=seed, sensor=0)
        w = torch.from_numpy(np.array(weights)).permute(2, 0, 1)
        (image * w).mean().backward()
        return x.grad.detach().double().cpu().numpy().reshape(-1, 3)


def time_steps(arms: dict[str, Any], iterations: int, views: int = VIEWS) -> dict[str, dict[str, Any]]:
    """Every arm's steps (``arm.step(step, view)``, ``iterations`` x ``views``), interleaved (the
    order alternates), timed and their kernels counted; the first ``2 x views`` are warm-up."""
    from torchir.backend import count_kernels

    times: dict[str, list[float]] = {name: [] for name in arms}
    kernels: dict[str, list[int]] = {name: [] for name in arms}
    step = 0
    for _ in range(iterations):
        for view in range(views):
            names = list(arms) if step % 2 == 0 else list(arms)[::-1]
            for name in names:
                with count_kernels() as stats:
                    start = time.perf_counter()
                    arms[name].step(step, view)
                    seconds = time.perf_counter() - start
                times[name].append(seconds)
                kernels[name].append(stats.compiled)
            step += 1
    warm = 2 * views
    return {name: {"step_s": float(np.mean(times[name][warm:])), "step_sd_s": float(np.std(times[name][warm:])),
                   "kernels_after_warmup": int(sum(kernels[name][warm:])), "kernels_warmup": int(sum(kernels[name][:warm])),
                   "steps": times[name]} for name in arms}


def gradient_quality(arms: dict[str, Any], weld_index: np.ndarray, weights: Any, spp: int, repeats: int,
                     reference_spp: int) -> dict[str, dict[str, float]]:
    """Each arm's per-position gradient at the start mesh against the welded reference."""
    positions = int(weld_index.max()) + 1

    def per_position(name: str, grad: np.ndarray) -> np.ndarray:
        if name == "mitsuba welded":
            return grad
        out = np.zeros((positions, 3))
        np.add.at(out, weld_index, grad)
        return out

    welded = arms["mitsuba welded"]
    chunks = max(1, reference_spp // 64)
    reference = sum(welded.gradient(weights, 1_000_000 + k, reference_spp // chunks) for k in range(chunks)) / chunks
    scale = float(np.linalg.norm(reference))
    out = {}
    for name, arm in arms.items():
        arm.gradient(weights, 999, spp)  # warm-up: its kernels
        grads, seconds = [], []
        for k in range(repeats):
            start = time.perf_counter()
            grads.append(per_position(name, arm.gradient(weights, 2_000 + k, spp)))
            seconds.append(time.perf_counter() - start)
        g = np.stack(grads)
        error = float(np.sqrt(np.mean(np.sum((g - reference) ** 2, axis=(1, 2)))) / scale)
        # |mean - reference|² holds the mean's own variance (error² / repeats): take it out
        bias2 = float(np.sum((g.mean(0) - reference) ** 2)) / scale ** 2 - error ** 2 / repeats
        bias = float(np.sqrt(max(bias2, 0.0)))
        out[name] = {"relative_error": error, "relative_bias": bias, "gradient_s": float(np.median(seconds)),
                     "efficiency": 1.0 / (error ** 2 * float(np.median(seconds)))}
    return out


def residual_weights(assets: Assets, sensors: list, refs: list, spp: int) -> Any:
    """``2 (image - target)`` of the start mesh on view 0 at ``spp``: the L2 loss's clean adjoint."""
    import mitsuba as mi

    scene = mi.load_dict(scene_dict(assets.start, assets))
    image = mi.render(scene, sensor=sensors[0], spp=spp, seed=77)
    return 2.0 * (image - refs[0])


def summary(results: dict[str, Any]) -> str:
    s, steps, grads = results["settings"], results["steps"], results["gradients"]
    base, base_eff = steps["mitsuba"]["step_s"], grads["mitsuba"]["efficiency"]
    lines = [f"## Shape step vs plain Mitsuba ({s['assets']})", "",
             f"{s['resolution']}², {s['spp']} spp, {VIEWS} views, {s['iterations']} iterations interleaved "
             f"(first {2 * VIEWS} steps left out); gradients: view 0, {s['repeats']} repeats at {s['spp']} spp, "
             f"reference `mitsuba welded` at {s['reference_spp']} spp.", ""]
    lines += markdown_table(
        ["arm", "step (ms)", "vs mitsuba", "kernels after warm-up", "gradient error", "bias", "gradient (ms)",
         "efficiency vs mitsuba"],
        [[name, fmt(1e3 * steps[name]["step_s"]), fmt(steps[name]["step_s"] / base), steps[name]["kernels_after_warmup"],
          fmt(grads[name]["relative_error"]), fmt(grads[name]["relative_bias"]), fmt(1e3 * grads[name]["gradient_s"]),
          fmt(grads[name]["efficiency"] / base_eff)] for name in ARMS])
    floor = grads["mitsuba welded"]["relative_error"] * (s["spp"] / s["reference_spp"]) ** 0.5
    lines += ["", f"bias: below about {fmt(floor)} it is the reference's own noise (the welded arm's error x "
              "sqrt(spp / reference spp)).",
              "gradient error: relative RMS error per surface position against the reference; efficiency: "
              "1 / (error² x seconds per gradient), as a ratio to mitsuba's (> 1: the same gradient error in less time)."]
    return "\n".join(lines)


def draw_steps(results: dict[str, Any]) -> Callable[[Any], None]:
    """Each arm's step times in the order they ran (for :func:`torchir.bench.write_outputs`)."""
    def draw(ax: Any) -> None:
        for name in ARMS:
            ax.plot(np.array(results["steps"][name]["steps"]) * 1e3, label=name)
    return draw


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = tutorial_parser(__doc__, "mesh_step", "48², 4 spp, 3 iterations, 4 gradient repeats")
    p.add_argument("--resolution", type=int, default=None)
    p.add_argument("--spp", type=int, default=None)
    p.add_argument("--iterations", type=int, default=None, help="iterations of 8 steps (default 5; --quick 3)")
    p.add_argument("--repeats", type=int, default=None, help="gradients per arm (default 16; --quick 4)")
    p.add_argument("--reference-spp", type=int, default=None, help="default 2048; --quick 256")
    args = fill_sizes(p.parse_args(argv), {"resolution": 48, "spp": 4, "iterations": 3, "repeats": 4, "reference_spp": 256},
                      {"resolution": 96, "spp": 8, "iterations": 5, "repeats": 16, "reference_spp": 2048})
    if args.iterations < 3:
        p.error("--iterations must be >= 3 (two are warm-up)")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    import mitsuba as mi

    import torchir
    from torchir.bench.shape_tutorial import read_target, write_targets

    torchir.backend.variant()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    assets = run_assets(args, out)
    sensor_specs = sensor_dicts(args.resolution)
    sensors = [mi.load_dict(s) for s in sensor_specs]
    refs = [read_target(t) for t in write_targets(assets, args.resolution, 64, out)]
    welded, weld_index = welded_mesh(assets.start)
    arms: dict[str, Any] = {
        "mitsuba": MitsubaArm(assets.start, assets, sensors, refs, args.spp),
        "mitsuba welded": MitsubaArm(welded, assets, sensors, refs, args.spp),
        "torchir": TorchirArm(assets, sensor_specs, refs, args.spp),
    }
    steps = time_steps(arms, args.iterations)
    weights = residual_weights(assets, sensors, refs, 256)
    grads = gradient_quality(arms, weld_index, weights, args.spp, args.repeats, args.reference_spp)
    results = {"settings": {"assets": assets.label, "resolution": args.resolution, "spp": args.spp,
                            "iterations": args.iterations, "repeats": args.repeats, "reference_spp": args.reference_spp},
               "steps": steps, "gradients": grads, "environment": environment()}
    write_outputs(out, summary(results), results, draw_steps(results), "step_times.png", "step (interleaved)", "ms", log_y=True)
    return results


if __name__ == "__main__":
    main()
