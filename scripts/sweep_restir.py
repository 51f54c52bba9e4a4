#!/usr/bin/env python
"""ReSTIR design sweep: gradient error and seconds per step of sampler option sets on one scene.

Each option set is a ``ReSTIRSampler`` keyword list (``preset="direct"``: the scene's own
integrator; ``spp=N``: samples per pixel). The error is the RMS over ``--steps`` steps of
``||g - g_ref|| / ||g_ref||`` at the grey texture with the L2 adjoint held fixed, the
reference's own error (64 batches of 256 spp, cached in ``--cache``) removed in quadrature;
seconds per step are medians (render + backward, after a first step that holds the burn-in
and the compilation, timed apart). How the defaults (16 candidates, 8 neighbours) were chosen:

    python scripts/sweep_restir.py ajar_painting \
        'preset="b2"' 'burn_in=32' 'burn_in=32,m_cap=160' 'burn_in=32,neighbors=8' \
        'burn_in=32,candidates=32' 'burn_in=32,neighbors=8,candidates=16' 'burn_in=32,target="unshadowed"'

Options of the scene: ``--scene-options 'door=0.005'``. Gradient paths: the sampler's default
(``decorrelated`` since issue 39, a second resampling pass a step); add ``grad_paths="shared"``
to an option set for the paper's shared paths (the step times measured before).
"""
from __future__ import annotations

import argparse
import ast
import math
import statistics
import time
from pathlib import Path

import torchir  # before torch: it sets OMP_WAIT_POLICY (torch's threads must not spin)


def keywords(text: str) -> dict:
    """``'a=1,b="x"'`` -> ``{"a": 1, "b": "x"}`` (literals only)."""
    call = ast.parse(f"f({text})", mode="eval").body
    return {k.arg: ast.literal_eval(k.value) for k in call.keywords}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene")
    p.add_argument("options", nargs="+", help="option sets, e.g. 'burn_in=32,neighbors=8'")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--scene-options", default="", help="built-in scene options, e.g. 'door=0.005'")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--cache", default="results/sweep_restir")
    a = p.parse_args(argv)

    import drjit as dr
    import torch

    from torchir.functions import render
    from torchir.samplers import ReSTIRSampler

    torchir.backend.set_variant("auto")
    scene_options = keywords(a.scene_options)
    scene = torchir.Scene.builtin(a.scene, resolution=a.resolution, **scene_options)
    key = torchir.scenes.get(a.scene).parameters[0]
    grey = torch.full_like(scene.get(key), 0.5)
    cache = Path(a.cache) / f"reference_{a.scene}_{a.resolution}_{sorted(scene_options.items())}.pt"
    if cache.is_file():
        adjoint, g_ref, ref_error = torch.load(cache)
    else:
        target = render(scene, {}, spp=2048, seed=1)
        at_grey = render(scene, {key: grey}, spp=2048, seed=2)
        adjoint = (2 * (at_grey - target) / at_grey.numel()).detach()
        batches = []
        for b in range(64):
            t = grey.clone().requires_grad_()
            (render(scene, {key: t}, spp=256, seed=3 + b) * adjoint).sum().backward()
            batches.append(t.grad)
        g = torch.stack(batches)
        g_ref = g.mean(0)
        ref_error = float(g.std(0).norm() / math.sqrt(len(batches)) / g_ref.norm())
        cache.parent.mkdir(parents=True, exist_ok=True)
        torch.save((adjoint, g_ref, ref_error), cache)
    print(f"{a.scene} {a.resolution}²: reference relative error {ref_error:.4f}")
    print(f"| options | relerr | s/step | first step s (burn-in, compile) |\n|---|---|---|---|")
    for text in a.options:
        options = keywords(text)
        spp = options.pop("spp", 1)
        sampler = None if options.get("preset") == "direct" else ReSTIRSampler(scene, **options)
        errors, seconds = [], []
        for i in range(a.steps + 1):
            t = grey.clone().requires_grad_()
            extra = {} if sampler is None else {"sampler": sampler}
            dr.sync_thread()
            t0 = time.perf_counter()
            (render(scene, {key: t}, spp=spp, seed=1000 + i, **extra) * adjoint).sum().backward()
            dr.sync_thread()
            if i == 0:
                first = time.perf_counter() - t0
            else:
                seconds.append(time.perf_counter() - t0)
                errors.append(float((t.grad - g_ref).norm() / g_ref.norm()))
        error = math.sqrt(max(statistics.fmean(e * e for e in errors) - ref_error**2, 0.0))
        print(f"| {text} | {error:.4f} | {statistics.median(seconds):.4f} | {first:.2f} |", flush=True)


if __name__ == "__main__":
    main()
