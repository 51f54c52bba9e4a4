#!/usr/bin/env python
"""Pixel-level antithetic sampling and ReSTIR (Wang et al. 2023, §6, Fig. 8 "Pig"), at equal time.

``pig``: a smooth diffuse blob lit by one area light, box filter. The derivative image of its
vertical displacement, camera-ray term (:mod:`torchir.integrators._primary_forms`), is scored
on the pixels the blob covers entirely, with a margin of one pixel: there both forms have the
same expectation (silhouettes and shadow edges are separate estimators, the same for every
method). Methods, each with a fresh ``ReSTIRDirectIntegrator`` stepped on the scene:

* **attached, ReSTIR**: torchir's form (the hit point slides along the fixed camera ray),
  spatiotemporal reuse;
* **attached, RIS (B.2)**: the same form, no reuse;
* **material, ReSTIR**: the paper's form (the surface point is fixed, its pixel moves: an
  interior and a pixel-edge term), no antithetic sampling (Fig. 8c);
* **material, ReSTIR, antithetic**: each point with its reflection about the pixel centre and
  the same random numbers, each combining with its own neighbours (Yu et al. 2022, Fig. 8d);
* **material, ReSTIR, antithetic, shared**: the pair combines with one neighbour set (Eq. 29,
  Fig. 8e);
* **material, RIS, antithetic**: antithetic sampling without reuse.

A step is the forward image (``integrator.step``, which advances the reservoirs) plus one
derivative image of 1 sample per pixel against the step's previous reservoirs, after
``--warmup`` untimed steps. **Equal time** as variance x time: each method's error is scaled by
``sqrt(its seconds per step / the slowest method's)``, the error it would reach with more
samples in the slowest step's time (for reuse methods an optimistic figure: samples that share
the previous step's reservoirs are not independent). Oracle rows (64 light candidates, no
reuse) bound what any light sampler can gain. The reference is the attached form, RIS with 64
candidates, ``--ref-spp`` per pixel over ``--ref-passes`` passes; its own error is subtracted in
quadrature. Relative error is ``|D - D_ref| / |D_ref|`` over the scored pixels, root mean
square over ``--steps`` steps; burn-in (32 passes) is not charged (it runs once per
optimisation).

Usage:
    python -m torchir.bench.restir_antithetic --quick   # 48², 4 steps (< 1 min)
    python -m torchir.bench.restir_antithetic           # 256², 8 steps (several minutes)
    python -m torchir.bench.restir_antithetic --resolution 128 --dome-lights 64 --steps 6   # hard light selection

Writes ``<out>/results.json``, ``<out>/summary.md``, ``<out>/antithetic.png`` (error against
seconds per step) and ``<out>/derivative_images.png``.
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torchir  # noqa: I001  (before torch)

import drjit as dr
import mitsuba as mi
import numpy as np

from torchir.bench import write_outputs

METHODS: dict[str, dict[str, Any]] = {
    "attached, ReSTIR": {"form": "attached", "reuse": True},
    "attached, RIS (B.2)": {"form": "attached", "reuse": False},
    "material, ReSTIR": {"form": "material", "reuse": True},
    "material, ReSTIR, antithetic": {"form": "material", "reuse": True, "antithetic": True, "shared": False},
    "material, ReSTIR, antithetic, shared": {"form": "material", "reuse": True, "antithetic": True, "shared": True},
    "material, RIS, antithetic": {"form": "material", "reuse": False, "antithetic": True},
    "attached, light oracle": {"form": "attached", "reuse": False, "candidates": "oracle"},
    "material, antithetic, light oracle": {"form": "material", "reuse": False, "antithetic": True, "candidates": "oracle"},
}
ORACLE = 64  # light candidates of the oracle rows (RIS, no reuse)
KEY, UP = "pig.vertex_positions", (0.0, 0.0, 1.0)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=None, help="film size (default 256, quick 48)")
    p.add_argument("--steps", type=int, default=None, help="scored steps per method (default 8, quick 4)")
    p.add_argument("--candidates", type=int, default=4, help="light candidates per shading point")
    p.add_argument("--light-size", type=float, default=1.0, help="side of the pig scene's square light")
    p.add_argument("--dome-lights", type=int, default=0, help="small lights around the blob (pig's dome_lights: hard light selection)")
    p.add_argument("--blind", type=float, default=0.0, help="slat period of a blind before the light (pig's blind: visibility the hard part)")
    p.add_argument("--warmup", type=int, default=4, help="untimed steps per method (burn-in, kernels)")
    p.add_argument("--ref-spp", type=int, default=None, help="reference samples per pixel and pass (default 16)")
    p.add_argument("--ref-passes", type=int, default=None, help="reference passes (default 8, quick 4)")
    p.add_argument("--out", default="results/bench_restir_antithetic")
    p.add_argument("--quick", action="store_true")
    a = p.parse_args(argv)
    a.resolution = a.resolution or (48 if a.quick else 256)
    a.steps = a.steps or (4 if a.quick else 8)
    a.ref_spp = a.ref_spp or 16
    a.ref_passes = a.ref_passes or (4 if a.quick else 8)
    return a


def scored_pixels(scene: mi.Scene, shape: str = "pig", sub: int = 8) -> np.ndarray:
    """(H, W) bool: pixels whose ``sub x sub`` sample grid hits ``shape`` everywhere, and whose
    8 neighbours do too (so no silhouette crosses a pixel or its edges)."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    target = next(s for s in scene.shapes() if s.id() == shape)
    n = w * h * sub * sub
    i = dr.arange(mi.UInt32, n)
    pixel, k = i // (sub * sub), i % (sub * sub)
    offset = mi.Point2f((mi.Float(k % sub) + 0.5) / sub, (mi.Float(k // sub) + 0.5) / sub)
    pos = (mi.Point2f(mi.Float(pixel % w), mi.Float(pixel // w)) + offset) * dr.rcp(mi.ScalarVector2f(w, h))
    with dr.suspend_grad():
        ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        ids = dr.reinterpret_array(mi.UInt32, si.shape)
        hit = np.asarray(si.is_valid() & (ids == dr.reinterpret_array(mi.UInt32, mi.ShapePtr(target))))
    covered = hit.reshape(h * w, sub * sub).all(1).reshape(h, w)
    padded = np.pad(covered, 1)
    return np.all([padded[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)


def relative_error(d: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    return float(np.linalg.norm(d[mask] - ref[mask]) / np.linalg.norm(ref[mask]))


class Method:
    """One method's integrator, stepped on the scene; ``step(spp, seed)`` returns the derivative
    image (H, W, 3) and the seconds of the whole step."""

    def __init__(self, scene: mi.Scene, options: dict[str, Any], candidates: int) -> None:
        from torchir.integrators import ReSTIRDirectIntegrator

        self.scene, self.options = scene, options
        reuse = options["reuse"]
        if options.get("candidates") == "oracle":
            candidates = ORACLE
        self.integrator = ReSTIRDirectIntegrator(candidates=candidates, temporal=reuse, spatial=reuse)

    def step(self, spp: int, seed: int) -> tuple[np.ndarray, float]:
        from torchir.integrators._primary_forms import derivative_image

        dr.sync_thread()
        t0 = time.perf_counter()
        image, cache = self.integrator.step(self.scene, 0, seed, 1, zero_remainder=False)
        d = derivative_image(self.integrator, self.scene, KEY, UP, seed=seed + 7919, spp=spp,
                             form=self.options["form"], antithetic=self.options.get("antithetic", False),
                             shared=self.options.get("shared", True), prev=cache.prev)
        dr.eval(image, d)
        dr.sync_thread()
        return np.asarray(d), time.perf_counter() - t0


def reference(scene: mi.Scene, a) -> tuple[np.ndarray, np.ndarray]:
    """``(mean, standard error)`` per pixel of the attached form, RIS with the oracle's candidates."""
    from torchir.integrators import ReSTIRDirectIntegrator
    from torchir.integrators._primary_forms import derivative_image

    integrator = ReSTIRDirectIntegrator(candidates=ORACLE, temporal=False, spatial=False)
    passes = [np.asarray(derivative_image(integrator, scene, KEY, UP, seed=10_000 + i, spp=a.ref_spp))
              for i in range(a.ref_passes)]
    stack = np.stack(passes)
    return stack.mean(0), stack.std(0, ddof=1) / np.sqrt(len(passes))


def run(a) -> dict[str, Any]:
    torchir.backend.set_variant()
    from torchir.scenes import pig

    scene = mi.load_dict(pig.build(a.resolution, light_size=a.light_size, dome_lights=a.dome_lights, blind=a.blind))
    mask = scored_pixels(scene)
    ref, ref_se = reference(scene, a)
    ref_norm = float(np.linalg.norm(ref[mask]))
    ref_error = float(np.linalg.norm(ref_se[mask]) / ref_norm)
    results: dict[str, Any] = {}
    for name, options in METHODS.items():
        m = Method(scene, options, a.candidates)
        for i in range(a.warmup):  # burn-in, kernels, the neighbour search's timed choice
            m.step(1, i)
        sq, seconds, last = [], [], None
        for i in range(a.steps):
            d, sec = m.step(1, 100 + i)
            sq.append(relative_error(d, ref, mask) ** 2)
            seconds.append(sec)
            last = d
        # the reference's own error adds to every method's: E|D - ref|^2 = E|D - D*|^2 + |ref - D*|^2
        error = float(np.sqrt(max(np.mean(sq) - ref_error**2, 0.0)))
        results[name] = {"seconds_per_step": float(np.median(seconds)), "relative_error": error,
                         "raw_relative_error": float(np.sqrt(np.mean(sq))),
                         "bias": float(np.sum(last[mask] - ref[mask]) / np.sum(np.abs(ref[mask])))}
        print(f"{name:44s} {results[name]['seconds_per_step']:.3f} s/step  rel. error {error:.3f}", flush=True)
    budget = max(r["seconds_per_step"] for r in results.values())
    for r in results.values():  # variance falls as 1 / samples: the error after `budget` seconds
        r["equal_time_error"] = r["relative_error"] * float(np.sqrt(r["seconds_per_step"] / budget))
    return {"resolution": a.resolution, "scored_pixels": int(mask.sum()), "reference_error": ref_error,
            "budget_seconds": budget, "methods": results, "images": {"reference": ref, "mask": mask}}


def summarize(res: dict[str, Any], a) -> str:
    m = res["methods"]
    shared = m["material, ReSTIR, antithetic, shared"]["equal_time_error"]
    lines = [
        f"# Antithetic sampling and ReSTIR: the blob's vertical displacement ({res['resolution']}², "
        f"{res['scored_pixels']} scored pixels, light size {a.light_size}, {a.dome_lights} dome lights, blind {a.blind})",
        "",
        f"One derivative sample per pixel a step. Equal time: errors scaled to {res['budget_seconds']:.2f} s a "
        f"step (the slowest method's) as variance x time; the reference's own error "
        f"({res['reference_error']:.4f}) is subtracted in quadrature. Oracle rows: {ORACLE} light "
        "candidates, no reuse: the most any light sampler (reuse, shared reservoirs) can gain.",
        "",
        "| method | s/step | relative error, 1 spp | at equal time | vs material, ReSTIR, antithetic, shared |",
        "|---|---|---|---|---|",
    ]
    for name, r in m.items():
        lines.append(f"| {name} | {r['seconds_per_step']:.3f} | {r['relative_error']:.4f} | "
                     f"{r['equal_time_error']:.4f} | {r['equal_time_error'] / shared:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    a = parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = run(a)
    images = res.pop("images")
    _draw_images(out / "derivative_images.png", images)

    def draw(ax):
        for name, r in res["methods"].items():
            ax.scatter([r["seconds_per_step"]], [r["relative_error"]], label=name)

    write_outputs(out, summarize(res, a), res, draw, "antithetic.png", "seconds per step", "relative error of the derivative image", log_y=True)
    return res


def _draw_images(path: Path, images: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = images["reference"].mean(-1)
    scale = float(np.percentile(np.abs(ref[images["mask"]]), 99)) or 1.0
    fig, axes = plt.subplots(1, 2, figsize=(8, 4))
    axes[0].imshow(ref, cmap="RdBu_r", vmin=-scale, vmax=scale)
    axes[0].set_title("reference dI/dθ (camera-ray term)")
    axes[1].imshow(images["mask"], cmap="gray")
    axes[1].set_title("scored pixels")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
