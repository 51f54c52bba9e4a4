#!/usr/bin/env python
"""ReSTIR for inverse direct illumination (Wang et al. 2023) vs Mitsuba, B.1 and B.2, with the camera-sampling floor.

Methods (every one recovers the scene's albedo texture: ``torchir.scenes.get(name).parameters[0]``, a
held-out scene's :func:`torchir.bench.heldout.spec` key):

* **direct**: the scene's own integrator (``prb``, ``max_depth`` 2: plain Mitsuba direct
  illumination, what a user runs without ReSTIR): ``render(scene, params)`` without ``sampler=``;
* **B.1** (the paper's path-tracing baseline): one light sample per camera ray, no reuse
  (``ReSTIRSampler(preset="b1")``);
* **B.2** (the paper's RIS baseline): streaming RIS over ``--candidates`` shadowed candidates, no
  reuse (``preset="b2"``);
* **ReSTIR (shadowed)** / **ReSTIR (unshadowed)**: RIS + spatiotemporal reuse of the previous
  step's reservoirs, ``target="shadowed"`` (p̂ includes visibility, the paper) or
  ``"unshadowed"`` (one shadow ray for the chosen sample);
* **ReSTIR (persistent)**: ``preset="persistent"``: every camera sample keeps its offset in the
  pixel (redrawn every 2048 steps on average) and resamples with its own previous reservoir
  (temporal reuse at the same shading point, M capped at 64 x candidates), no spatial reuse;
* **ReSTIR (auto)** (``--restirs auto``, not run by default): ``preset="auto"`` and nothing else:
  the sampler probes the scene at its first render and picks its own settings;
* **floor**: an oracle, RIS over ``--oracle-candidates`` (256) shadowed
  candidates, no reuse, at the same seeds and spp as the method: the camera rays of a
  ``ReSTIRSampler`` render depend only on the seed, so the oracle sees the same camera rays
  and almost no light noise. Its error is the *camera-sampling floor*: with ``e`` a method's
  error, ``e² = floor² + light²`` and ``light = sqrt(max(e² − floor², 0))`` is what a light
  sampler can remove; no light sampler gains more than ``e_baseline / floor`` (the *bound*,
  printed beside every gain: "gain 3.1x of possible 8.2x").

Scenes (``--scenes``): built-in scenes by name, and held-out scenes, procedural layouts nobody
tuned against, as ``heldout:<family>:<seed>`` (:mod:`torchir.bench.heldout`: ``slit_lights``,
``holes``, ``open``, ``fine_texture``); ``--heldout N`` adds N fresh seeds per family, drawn from
the clock (printed and saved in ``results.json``: ``--scenes`` repeats them).

Experiments, per scene:

* **Gradient error**: the adjoint of the L2 loss at the grey (0.5) texture, held
  fixed (the error is the estimator's, not the loss's); ``relerr = ||g − g_ref|| / ||g_ref||``
  with ``g_ref`` from ``prb`` at ``--ref-spp`` (four independent batches: their spread gives the
  reference's own relative standard error, printed; it adds to every error in quadrature).
  Reported as the RMS over ``--grad-steps`` steps (squared errors add, so floor and light parts
  separate), at *equal samples* (every method at ``--spp``) and at *equal time*: every method's
  spp is raised until its seconds per step match the slower ReSTIR variant's at ``--spp``,
  burn-in charged (``step + burn-in / grad_steps``: the burn-in is spent to produce these
  ``grad_steps`` gradients). The budget comes from the equal-samples runs; each other method's
  spp from up to ``--cal-rounds`` timing probes (interpolated between the probes around the
  budget: step time is not proportional to spp). Each baseline then runs at the whole spps
  on either side of that estimate and its error is read at exactly the budget (``1/e²``, the
  effective sample count, linear in time between the two runs): rounding to a whole spp
  would favour one side by up to a sample per pixel, which at 1-2 spp is a large share. The
  table shows the seconds per step of the ReSTIR runs as they took them and the budget for
  the baselines. The runs of each group step in lockstep (interleaved), so
  load drift hits every method alike.
* **Reconstruction at equal wall time, through the trainer**: a real
  ``InverseRenderingModule`` + ``ViewDataModule`` + ``lightning.pytorch.Trainer`` run per method
  (Adam, ``--lr``, L2 loss, grey init, bounds [1e-3, 1], every method at ``--spp``). The slower
  ReSTIR variant trains ``--recon-steps`` steps (its burn-in falls in its first step, so it is
  charged); every other method trains for that wall time (Lightning's ``max_time``): cheaper
  methods take more steps. Texture RMSE against the ground truth after the budget. Once per
  ``--grad-paths`` mode of the samplers: ``decorrelated`` (the default: the
  gradient's light samples come from a second pass on ``seed_grad``) and ``shared`` (the paper:
  the gradient re-uses the image's paths, which correlates them, a bias of the L2 loss that
  grows with the image noise); ``direct`` (prb) is always decorrelated. The first
  mode also sets the samplers' paths in the gradient-error runs (at a fixed adjoint either is
  unbiased, but decorrelated paths cost a second resampling pass a step: the equal-time
  budget and every sampler's step time include it).
* **Cost per stage**: seconds per step of each method at equal samples, the
  ReSTIR integrator's stage timers (RIS, NN search, combination, develop, backward; ``other``:
  the rest, e.g. the torch/Dr.Jit boundary; a pass replayed by ``dr.freeze`` has a single
  ``pass`` timer, so B.2 and ReSTIR are then also timed a few steps with ``freeze=False``),
  its burn-in once, the ratio of a ReSTIR step to a B.2 step at equal samples, and of a ReSTIR
  training step to a direct training step through the trainer.

Usage (``torchir bench restir [--quick]`` runs the same in a fresh process):
    python -m torchir.bench.restir --quick     # 32², first default scene, burn-in 8, 8 gradient / 10 training steps (< 1 min)
    python -m torchir.bench.restir             # 128², default scenes, 32 gradient steps, 150 training steps (~6-8 min)
    python -m torchir.bench.restir --grad-paths shared   # the paper's shared paths
    python -m torchir.bench.restir --scenes oxalis_lite --resolution 64 --spp 2
    python -m torchir.bench.restir --heldout 2 --restirs persistent,auto   # two fresh layouts per held-out family
    python -m torchir.bench.restir --scenes heldout:slit_lights:7,heldout:open:3

Writes ``<out>/results.json``, ``<out>/tables.md`` (= ``summary.md``, which the bench report
shows), ``<out>/gradient_<scene>.png`` (gradient error against seconds per step) and
``<out>/reconstruction_<scene>.png`` (texture RMSE against wall time; a held-out spec's ``:`` as ``_``).
"""
from __future__ import annotations

import argparse
import datetime
import gc
import json
import math
import statistics
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchir.bench import combined, heldout, save_results
from .. import backend
from ._common import sync_time
from .restir_report import (ALL_RESTIRS, AUTO, BASELINES, DEFAULT_RESTIRS, DEFAULT_SCENES, METHODS, ORACLE, ORACLE_LOW,
                            REFERENCE_BATCHES, bracketing_spps, camera_floor, equal_time_error, equal_time_estimate,
                            equal_time_spp, error_beyond_reference, methods_in, plot_results, restir_variants,
                            summarize_scene, tables)

__all__ = ["ALL_RESTIRS", "AUTO", "BASELINES", "DEFAULT_RESTIRS", "METHODS", "ORACLE", "ORACLE_LOW", "bracketing_spps", "camera_floor", "equal_time_error",
           "error_beyond_reference",
           "main", "methods_in", "parse_args", "plot_results", "restir_variants", "summarize_scene", "tables"]

BOUNDS = [0.001, 1.0]


# ------------------------------------------------------------------------------- options
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default=None,
                   help=f"comma-separated built-in scenes and held-out scenes heldout:<family>:<seed> (families: "
                        f"{', '.join(heldout.FAMILIES)}; default: those of {','.join(DEFAULT_SCENES)} that exist; quick: the first)")
    p.add_argument("--heldout", type=int, default=0, metavar="N",
                   help="add N held-out scenes per family, seeds drawn from the clock (printed and saved: --scenes repeats them)")
    p.add_argument("--resolution", type=int, default=None, help="film size (default 128, quick 32)")
    p.add_argument("--spp", type=int, default=1, help="samples per pixel of ReSTIR and of every method at equal samples")
    p.add_argument("--candidates", type=int, default=16, help="M of B.2 and ReSTIR (the sampler default)")
    p.add_argument("--oracle-candidates", default="256,1024",
                   help="two candidate counts M1 < M2 of the floor oracle (RIS, no reuse, >= 256): the floor is "
                        "extrapolated to M -> infinity from e² = floor² + L/M (one count: that oracle's error)")
    p.add_argument("--burn-in", type=int, default=None, help="ReSTIR burn-in passes, charged to ReSTIR (default 32, quick 8)")
    p.add_argument("--nn-backend", default="auto", choices=("auto", "kdtree", "grid", "screen"))
    p.add_argument("--chain-cap", type=int, default=None,
                   help="M cap of the persistent chains (default: the preset's, 64 x candidates; scripts/restir_chains.py measures longer ones)")
    p.add_argument("--chain-candidates", type=int, default=None,
                   help="candidates a step of the persistent chains (default: --candidates); their burn-in is --burn-in passes of these")
    p.add_argument("--light-guide", type=float, default=0.0,
                   help="light_guide of the persistent chains: the share of candidates drawn from each lane's learned guide (0: off)")
    p.add_argument("--grad-steps", type=int, default=None, help="gradient steps per method (default 32, quick 8)")
    p.add_argument("--cal-steps", type=int, default=None, help="timed steps per calibration probe (default 6, quick 2)")
    p.add_argument("--cal-rounds", type=int, default=None, help="calibration probes per method (default 3, quick 1)")
    p.add_argument("--max-spp", type=int, default=256, help="largest equal-time spp of a method")
    p.add_argument("--ref-spp", type=int, default=None, help="spp of the reference gradient and images (default 16384, quick 1024)")
    p.add_argument("--recon-steps", type=int, default=None, help="training steps of the budget's ReSTIR run (default 150, quick 10)")
    p.add_argument("--recon-seeds", type=int, default=1, help="reconstruction seeds (medians over them)")
    p.add_argument("--target-spp", type=int, default=None,
                   help="spp of the trainer's target image (default 8192, quick 128): the scene's own integrator renders "
                        "it, and where light sampling is hard its noise sets the RMSE every fit stalls at (on a held-out "
                        "scene, 1024 spp capped any light sampler's gain at 2.3x; 8192 let ReSTIR reach 3.3x)")
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--grad-paths", default=None,
                   help="comma list of the samplers' gradient paths, decorrelated and/or shared (default decorrelated: "
                        "unbiased baselines; shared paths bias B.1's and B.2's L2 fits): the reconstruction runs once per "
                        "mode; the first also sets the gradient-error runs' paths and fills the main table; direct (prb) is "
                        "always decorrelated")
    p.add_argument("--no-reconstruction", action="store_true", help="skip the trainer runs")
    p.add_argument("--recon-oracle", action="store_true",
                   help="also train the floor oracle (RIS over --oracle-candidates, no reuse) for as many steps as the budget's "
                        "ReSTIR took, its time not charged: the texture RMSE no light sampler can beat in those steps, so "
                        "the best baseline's RMSE / the oracle's bounds every reconstruction gain")
    p.add_argument("--lr-half-life", type=int, default=None,
                   help="steps over which the trainer's learning rate halves (default: constant, as the configs)")
    p.add_argument("--restirs", default=",".join(DEFAULT_RESTIRS),
                   help="ReSTIR variants to run, of shadowed, unshadowed, persistent and auto (preset='auto': the sampler "
                        f"picks its own settings); the slowest sets the equal-time budget (default {','.join(DEFAULT_RESTIRS)})")
    p.add_argument("--quick", action="store_true",
                   help="32², the first default scene, burn-in 8, 8 gradient / 10 training steps, decorrelated paths only: under a minute")
    p.add_argument("--out", default="results/bench_restir")
    a = p.parse_args(argv)
    q = a.quick
    a.resolution = a.resolution or (32 if q else 128)
    a.burn_in = (8 if q else 32) if a.burn_in is None else a.burn_in
    a.grad_steps = a.grad_steps or (8 if q else 32)
    a.cal_steps = a.cal_steps or (2 if q else 6)
    a.cal_rounds = (1 if q else 3) if a.cal_rounds is None else a.cal_rounds
    a.ref_spp = a.ref_spp or (1024 if q else 16384)
    a.recon_steps = a.recon_steps or (10 if q else 150)
    a.target_spp = a.target_spp or (128 if q else 8192)
    a.grad_paths = [m.strip() for m in (a.grad_paths or "decorrelated").split(",") if m.strip()]
    if not a.grad_paths or any(m not in ("shared", "decorrelated") for m in a.grad_paths):
        p.error("--grad-paths takes shared and/or decorrelated")
    try:
        counts = sorted({int(v) for v in str(a.oracle_candidates).split(",") if v.strip()})
    except ValueError:
        p.error("--oracle-candidates takes one or two integers, e.g. 256,1024")
    if not 1 <= len(counts) <= 2 or counts[0] < 1:
        p.error("--oracle-candidates takes one or two positive integers, e.g. 256,1024")
    a.oracle_low, a.oracle_candidates = counts[0] if len(counts) == 2 else None, counts[-1]
    if a.chain_candidates is not None and a.chain_candidates < 1:
        p.error(f"--chain-candidates must be >= 1, got {a.chain_candidates}")
    if a.heldout < 0:
        p.error(f"--heldout must be >= 0, got {a.heldout}")
    for name in ("resolution", "spp", "candidates", "oracle_candidates", "cal_steps", "max_spp", "recon_steps", "recon_seeds", "target_spp"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    if a.grad_steps < 2:
        p.error("--grad-steps must be >= 2 (the first step holds the burn-in and is left out of the step time)")
    if a.ref_spp < 4:
        p.error("--ref-spp must be >= 4 (four reference batches)")
    a.restirs = [v.strip() for v in a.restirs.split(",") if v.strip()]
    try:
        a.restir_methods = restir_variants(a.restirs)
    except ValueError as error:
        p.error(str(error))
    a.methods = (*BASELINES, *a.restir_methods)
    return a


def resolve_scenes(spec: str | None, quick: bool = False) -> tuple[list[str], list[str]]:
    """(scenes to run, default scenes not run). Default: the scenes of ``DEFAULT_SCENES`` that
    are built in; with ``quick`` only the first of them (one scene keeps it under a minute).
    ``spec``: comma-separated built-in names and held-out specs ``heldout:<family>:<seed>``
    (written back in canonical form); ``ValueError`` names what is wrong."""
    import torchir

    available = torchir.scenes.available()
    if spec is None:
        present = [s for s in DEFAULT_SCENES if s in available]
        chosen = present[:1] if quick else present
        return chosen, [s for s in DEFAULT_SCENES if s not in chosen]
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise ValueError(f"--scenes is empty; available: {', '.join(available)} or heldout:<family>:<seed>")
    chosen = []
    for name in names:
        if heldout.is_spec(name):
            family, seed = heldout.parse_spec(name)  # ValueError naming the families
            name = f"{heldout.PREFIX}:{family}:{seed}"
        elif name not in available:
            raise ValueError(f"unknown scene {name!r} in --scenes; available: {', '.join(available)}, or held-out scenes "
                             f"heldout:<family>:<seed> with family one of {', '.join(heldout.FAMILIES)}")
        chosen.append(name)
    return list(dict.fromkeys(chosen)), []


def load_scene(name: str, resolution: int) -> tuple[Any, str]:
    """``(torchir.Scene, texture key)`` of a built-in scene or a held-out spec."""
    import torchir

    if heldout.is_spec(name):
        return heldout.load(name, resolution)
    return torchir.Scene.builtin(name, resolution=resolution), torchir.scenes.get(name).parameters[0]


def trainer_scene(name: str) -> dict[str, Any]:
    """``InverseRenderingModule``'s ``scene=`` (and ``scene_options=``) for a built-in name or a held-out spec."""
    if heldout.is_spec(name):
        factory, options = heldout.factory(name)
        return {"scene": factory, "scene_options": options}
    return {"scene": name}


def sampler_options(method: str, a: argparse.Namespace) -> dict[str, Any] | None:
    """``ReSTIRSampler`` keyword arguments of ``method`` (None: the scene's own integrator)."""
    if method == "direct":
        return None
    if method == "B.1":
        return {"preset": "b1"}
    if method == "B.2":
        return {"preset": "b2", "candidates": a.candidates}
    if method == ORACLE:
        return {"preset": "b2", "candidates": a.oracle_candidates}
    if method == ORACLE_LOW:
        return {"preset": "b2", "candidates": a.oracle_low}
    if method == AUTO:
        return {"preset": "auto"}  # nothing else: it chooses (Problem.sampler adds the run's grad_paths)
    if method == "ReSTIR (persistent)":
        return {"preset": "persistent", "candidates": a.chain_candidates or a.candidates, "burn_in": a.burn_in, "m_cap": a.chain_cap,
                "light_guide": a.light_guide}
    if method in ALL_RESTIRS:
        target = "unshadowed" if "unshadowed" in method else "shadowed"
        return {"candidates": a.candidates, "burn_in": a.burn_in, "target": target, "nn_backend": a.nn_backend}
    raise ValueError(f"unknown method {method!r}")


# ----------------------------------------------------------------------- gradient error
@dataclass
class Problem:
    """One scene's fixed gradient problem: the L2 adjoint at the grey texture and its reference."""

    name: str
    scene: Any
    key: str
    grey: Any
    adjoint: Any
    g_ref: Any
    ref_relative_se: float
    ref_seconds: float

    def sampler(self, method: str, a: argparse.Namespace, burn_in: int | None = None, **extra: Any):
        """``method``'s sampler (None: the scene's own integrator), with the run's first
        ``--grad-paths`` mode."""
        from torchir.samplers import ReSTIRSampler

        options = sampler_options(method, a)
        if options is None:
            return None
        if burn_in is not None and "burn_in" in options:
            options = {**options, "burn_in": burn_in}
        modes = getattr(a, "grad_paths", None)
        if modes:
            options = {"grad_paths": modes[0], **options}
        if method == AUTO:  # told the run's length, as the trainer tells it its max_steps
            options["planned_steps"] = a.grad_steps
        return ReSTIRSampler(self.scene, **{**options, **extra})

    def step(self, sampler, spp: int, seed: int) -> tuple[float, float, dict[str, float]]:
        """One gradient at the grey texture: (seconds of render + backward, relative error, diagnostics)."""
        from torchir.functions import render

        t = self.grey.clone().requires_grad_()
        extra = {} if sampler is None else {"sampler": sampler}
        t0 = sync_time()
        image = render(self.scene, {self.key: t}, spp=spp, seed=seed, **extra)
        (image * self.adjoint).sum().backward()
        seconds = sync_time() - t0
        error = float((t.grad - self.g_ref).norm() / self.g_ref.norm())
        return seconds, error, (sampler.diagnostics() if sampler is not None else {})


def make_problem(name: str, a: argparse.Namespace) -> Problem:
    """Scene, target, adjoint at the grey texture and the prb reference gradient (4 batches)."""
    import torch

    from torchir.functions import render

    started = time.perf_counter()
    scene, key = load_scene(name, a.resolution)
    grey = torch.full_like(scene.get(key), 0.5)
    target = render(scene, {}, spp=a.ref_spp, seed=1)
    at_grey = render(scene, {key: grey}, spp=a.ref_spp, seed=2)
    adjoint = (2.0 * (at_grey - target) / at_grey.numel()).detach()  # d(L2)/dI at the grey texture
    batches = []
    n_batches = REFERENCE_BATCHES
    for b in range(n_batches):
        t = grey.clone().requires_grad_()
        (render(scene, {key: t}, spp=max(1, a.ref_spp // n_batches), seed=3 + b) * adjoint).sum().backward()
        batches.append(t.grad)
    g = torch.stack(batches)
    g_ref = g.mean(0)
    # relative error of the batch mean: ||sd|| / sqrt(batches) (15 degrees of freedom)
    relative_se = float(g.std(0).norm() / math.sqrt(n_batches) / g_ref.norm())
    return Problem(name, scene, key, grey, adjoint, g_ref, relative_se, time.perf_counter() - started)


def oracles(a: argparse.Namespace) -> tuple[str, ...]:
    return (ORACLE,) if a.oracle_low is None else (ORACLE_LOW, ORACLE)


def warm_up(problem: Problem, a: argparse.Namespace) -> None:
    """Compile every method's kernels (and the burn-in's) before anything is timed."""
    for method in (*a.methods, *oracles(a)):
        # a burn-in pass, then a reuse step; lane chains burn in with one pass over all the
        # burn-in's candidates, a kernel of its own: compiled here at the real count
        burn_in = a.burn_in if method == "ReSTIR (persistent)" else 1
        problem.step(problem.sampler(method, a, burn_in=burn_in), a.spp, 90_000)


def probe(problem: Problem, method: str, spp: int, a: argparse.Namespace, seed0: int) -> dict[str, float]:
    """Seconds per step of ``method`` at ``spp``: the median of ``cal_steps`` steps after two
    untimed ones (the first holds the burn-in, kernel compilation and, at a new spp, the
    recording of a frozen pass; the second, re-recordings), the burn-in once, and the step with
    the burn-in charged over ``grad_steps``."""
    sampler = problem.sampler(method, a)
    steps, burn_in = [], 0.0
    for i in range(a.cal_steps + 2):
        seconds, _, diag = problem.step(sampler, spp, seed0 + i)
        if i == 0:
            burn_in = float(diag.get("time_burn_in", 0.0))
        elif i > 1:
            steps.append(seconds)
    step = statistics.median(steps)
    return {"spp": spp, "step": step, "burn_in": burn_in, "charged": step + burn_in / a.grad_steps}


def calibrate(problem: Problem, a: argparse.Namespace, equal_samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Equal-time spp of every method. The budget is the charged seconds per step of the slower
    ReSTIR variant in the equal-samples runs (``grad_steps`` interleaved steps: a steadier
    measure than a short probe); each other method starts from its own equal-samples timing
    and gets up to ``cal_rounds`` probes, each at the spp the probes so far point to."""
    runs = {r["method"]: r for r in equal_samples if r["spp"] == a.spp}
    first = {m: {"spp": a.spp, "step": runs[m]["seconds_per_step"], "burn_in": runs[m]["burn_in_seconds"],
                 "charged": runs[m]["charged_seconds_per_step"]} for m in a.methods}
    owner = max(a.restir_methods, key=lambda m: first[m]["charged"])
    budget = first[owner]["charged"]
    probes = {m: [first[m]] for m in a.methods}
    spp_eq, exact = {owner: a.spp}, {owner: float(a.spp)}
    for m in a.methods:
        if m == owner:
            continue
        spp_eq[m] = equal_time_spp(probes[m], budget, a.spp, a.max_spp)
        for round_ in range(a.cal_rounds):
            if spp_eq[m] in {q["spp"] for q in probes[m]}:
                break
            probes[m].append(probe(problem, m, spp_eq[m], a, 30_000 + 100 * round_))
            spp_eq[m] = equal_time_spp(probes[m], budget, a.spp, a.max_spp)
        exact[m] = equal_time_estimate(probes[m], budget, a.spp, a.max_spp)
    return {"budget_method": owner, "budget_seconds": budget, "equal_time_spp": {m: spp_eq[m] for m in a.methods},
            "equal_time_spp_exact": {m: exact[m] for m in a.methods}, "probes": probes}


def stage_breakdown(problem: Problem, a: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Where the time of a step goes when the pass is not frozen: ``cal_steps`` steps of B.2 and
    each ReSTIR variant with ``freeze=False`` (per-stage timers with syncs; the Python tracing a
    frozen pass saves shows up in the stages)."""
    out = {}
    for m in ("B.2", *a.restir_methods):
        sampler = problem.sampler(m, a, burn_in=min(a.burn_in, 2), freeze=False)
        steps, per_step = [], []
        for i in range(a.cal_steps + 1):
            seconds, _, diag = problem.step(sampler, a.spp, 40_000 + i)
            if i > 0:
                steps.append(seconds)
                per_step.append(_stages(diag, seconds))
        out[f"{m}, unfrozen"] = {"seconds_per_step": statistics.median(steps), "stages": _median_stages(per_step)}
    return out


def _stages(diag: dict[str, float], seconds: float) -> dict[str, float]:
    """A step's stage timers (``time_*`` of the diagnostics, burn-in left out) and ``other``: the
    rest of the step's ``seconds``. Empty for the scene's own integrator."""
    stages = {k[5:]: float(v) for k, v in diag.items() if k.startswith("time_") and k != "time_burn_in"}
    if stages:
        stages["other"] = max(0.0, seconds - sum(stages.values()))
    return stages


def _median_stages(steps: list[dict[str, float]]) -> dict[str, float]:
    names = dict.fromkeys(k for s in steps for k in s)
    return {k: statistics.median(s.get(k, 0.0) for s in steps) for k in names}


def gradient_runs(problem: Problem, a: argparse.Namespace, keys: list[tuple[str, int]]) -> list[dict[str, Any]]:
    """The runs ``keys`` (``(method, spp)``) stepped in lockstep (interleaved) for ``grad_steps``
    steps. Step ``i`` uses seed ``1000 + i`` in every run, so the ReSTIRSampler runs at one spp
    share their camera rays (the floor oracle's with the method's)."""
    keys = list(dict.fromkeys(keys))
    runs = {k: {"method": k[0], "spp": k[1], "sampler": problem.sampler(k[0], a), "relerr_steps": [], "seconds": [],
                "burn_in": 0.0, "stage_steps": []} for k in keys}
    started = time.perf_counter()
    for i in range(a.grad_steps):
        if i and i % max(1, a.grad_steps // 4) == 0:  # a long run shows that it moves
            print(f"[restir] {problem.name}: gradient step {i}/{a.grad_steps} of {len(keys)} runs "
                  f"({time.perf_counter() - started:.0f} s)", flush=True)
        for k in keys:
            r = runs[k]
            seconds, error, diag = problem.step(r["sampler"], k[1], 1000 + i)
            r["relerr_steps"].append(error)
            if i == 0:
                r["burn_in"] = float(diag.get("time_burn_in", 0.0))
                continue
            r["seconds"].append(seconds)
            r["stage_steps"].append(_stages(diag, seconds))
    out = []
    for k in keys:
        r = runs.pop(k)
        relerr, relerr_sq_se = error_beyond_reference(r["relerr_steps"], problem.ref_relative_se)
        step = statistics.median(r["seconds"])
        stages = _median_stages(r["stage_steps"])
        out.append({
            "method": r["method"], "spp": r["spp"], "relerr_steps": r["relerr_steps"],
            "relerr": relerr, "relerr_sq_se": relerr_sq_se,
            "seconds_per_step": step, "burn_in_seconds": r["burn_in"],
            "charged_seconds_per_step": step + r["burn_in"] / a.grad_steps, "stages": stages,
        })
    return out


# ------------------------------------------------------------------------ reconstruction
def train(name: str, key: str, method: str, a: argparse.Namespace, seed: int, targets, workdir: Path,
          max_seconds: float | None, grad_paths: str = "decorrelated", steps: int | None = None) -> tuple[dict[str, Any], Any]:
    """One training run of ``method`` through the real trainer: ``steps`` (default
    ``recon_steps``) steps, or (with ``max_seconds``) as many as fit into that wall time.
    ``targets``: ``(images, views)`` of an earlier run (None: render them). Returns the
    measurements and the targets."""
    import lightning.pytorch as pl

    from torchir.training import InverseRenderingModule, ViewDataModule

    options = sampler_options(method, a)
    sampler = None if options is None else {"type": "restir", **options, "grad_paths": grad_paths, "seed": seed}
    module = InverseRenderingModule(
        **trainer_scene(name), resolution=a.resolution, parameters={key: {"init": 0.5, "bounds": BOUNDS}}, loss="l2",
        sampler=sampler, spp=a.spp, lr=a.lr, seed=seed, preview_spp=1, lr_half_life=getattr(a, "lr_half_life", None),
    )
    data = ViewDataModule(target_spp=a.target_spp)
    if targets is not None:  # setup() keeps targets that are already there
        data.targets, data.views = targets
    pl.seed_everything(seed, verbose=False)
    recorder = combined._recorder()  # step seconds, elapsed time, texture RMSE after each step
    trainer = pl.Trainer(
        accelerator=backend.device(),
        max_steps=(steps or a.recon_steps) if max_seconds is None else 1000 * a.recon_steps,
        max_time=None if max_seconds is None else datetime.timedelta(seconds=max_seconds),
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        log_every_n_steps=1, default_root_dir=str(workdir), callbacks=[recorder],
    )
    trainer.fit(module, data)
    if module.nonfinite is not None:
        raise RuntimeError(f"{method}: {module.nonfinite}")
    return {
        "method": method, "grad_paths": grad_paths, "seed": seed, "steps": len(recorder.step_seconds), "step_seconds": recorder.step_seconds,
        "elapsed": recorder.elapsed, "param_error": recorder.param_error, "final_param_error": recorder.param_error[-1],
        "train_seconds": recorder.elapsed[-1],
    }, (data.targets, data.views)


def reconstruction(name: str, key: str, a: argparse.Namespace, budget_method: str) -> dict[str, list[dict[str, Any]]]:
    """Per gradient-paths mode and seed: ``budget_method`` (the ReSTIR variant that set the
    equal-time budget of the gradient runs) for ``recon_steps`` steps (its first step holds the
    burn-in), then every other method for that wall time. Each run's module (and Mitsuba scene)
    is freed before the next is built: the next scene then gets the same Dr.Jit instance ids, so
    the kernels compiled for the gradient runs serve it and no run's first step is charged for
    compiling (a live earlier scene made every kernel new: 0.5-4.6 s in a 32² first step)."""
    out: dict[str, list[dict[str, Any]]] = {}
    targets = None
    with tempfile.TemporaryDirectory(prefix="torchir_bench_restir_") as workdir:
        for mode in a.grad_paths:
            runs = out.setdefault(mode, [])
            for seed in range(a.recon_seeds):
                budget = None
                for method in (budget_method, *[m for m in a.methods if m != budget_method]):
                    t0 = time.perf_counter()
                    gc.collect()
                    run, targets = train(name, key, method, a, seed, targets, Path(workdir), budget, mode)
                    runs.append(run)
                    if budget is None and getattr(a, "recon_oracle", False):  # the budget's steps, time not charged
                        oracle, _ = train(name, key, ORACLE, a, seed, targets, Path(workdir), None, mode, steps=run["steps"])
                        runs.append(oracle)
                        print(f"[restir] {name} reconstruction ({mode} paths) seed {seed} {ORACLE}: {oracle['steps']} steps, "
                              f"RMSE {oracle['param_error'][0]:.4f} -> {oracle['final_param_error']:.4f}", flush=True)
                    budget = run["train_seconds"] if budget is None else budget
                    print(f"[restir] {name} reconstruction ({mode} paths) seed {seed} {method}: {run['steps']} steps, "
                          f"{run['train_seconds']:.1f} s (first step {run['step_seconds'][0]:.2f} s), "
                          f"RMSE {run['param_error'][0]:.4f} -> {run['final_param_error']:.4f} ({time.perf_counter() - t0:.1f} s)", flush=True)
    return out


def run_scene(name: str, a: argparse.Namespace) -> dict[str, Any]:
    t0 = time.perf_counter()
    problem = make_problem(name, a)
    ref_seconds = problem.ref_seconds
    print(f"[restir] {name}: reference ({a.ref_spp} spp, relative SE {problem.ref_relative_se:.4f}) in {problem.ref_seconds:.1f} s", flush=True)
    warm_up(problem, a)
    runs = gradient_runs(problem, a, [(m, a.spp) for m in (*a.methods, *oracles(a))])  # equal samples
    cal = calibrate(problem, a, runs)
    spp_eq = cal["equal_time_spp"]
    print(f"[restir] {name}: budget {cal['budget_seconds']:.4f} s/step ({cal['budget_method']}); equal-time spp {spp_eq} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)
    exact = cal["equal_time_spp_exact"]
    equal_time = ([(m, s) for m in BASELINES for s in bracketing_spps(exact[m], a.spp, a.max_spp)]  # interpolated to the budget
                  + [(m, spp_eq[m]) for m in a.restir_methods] + [(ORACLE, spp_eq[m]) for m in a.restir_methods])  # the floor under each ReSTIR
    runs += gradient_runs(problem, a, [k for k in equal_time if k[1] != a.spp])
    unfrozen = stage_breakdown(problem, a)
    print(f"[restir] {name}: gradient runs done ({time.perf_counter() - t0:.1f} s)", flush=True)
    key, texture, ref_se = problem.key, list(problem.grey.shape), problem.ref_relative_se
    del problem  # free its Mitsuba scene: the trainer's scenes reuse its Dr.Jit instance ids (see reconstruction)
    gc.collect()
    recon = None if a.no_reconstruction else reconstruction(name, key, a, cal["budget_method"])
    summary = summarize_scene(runs, a.spp, cal["equal_time_spp"], recon, (a.oracle_low, a.oracle_candidates), cal["budget_seconds"],
                              cal["equal_time_spp_exact"])
    held = None
    if heldout.is_spec(name):
        family, seed = heldout.parse_spec(name)
        held = {"family": family, "seed": seed, "light_bound": heldout.FAMILIES[family].light_bound}
    return {"key": key, "heldout": held, "texture_shape": texture, "reference": {"spp": a.ref_spp, "relative_se": ref_se, "seconds": ref_seconds}, "calibration": cal,
            "gradient_runs": runs, "reconstruction": recon or {}, **summary, "unfrozen_stages": unfrozen,
            "seconds": time.perf_counter() - t0}


def summary(results: dict[str, Any]) -> str:
    """The suite's Markdown, from its ``results.json`` alone (the docs' results page uses it)."""
    return tables(results)


def main(argv: Sequence[str] | None = None) -> None:
    a = parse_args(argv)
    import torchir

    torchir.backend.set_variant("auto")
    combined._quiet()
    from . import environment

    drawn = heldout.draw_specs(a.heldout) if a.heldout else []
    if drawn:  # saved with the config: --scenes repeats the run
        a.scenes = ",".join([*([a.scenes] if a.scenes else []), *drawn])
        print(f"[restir] held-out scenes drawn from the clock: {','.join(drawn)} (repeat with --scenes {a.scenes})", flush=True)
    try:
        scenes, skipped = resolve_scenes(a.scenes, a.quick)
    except ValueError as error:
        raise SystemExit(f"torchir bench restir: {error}") from None
    if skipped:
        print(f"[restir] default scenes not run{' (--quick runs one)' if a.quick else ' (not built in)'}: {', '.join(skipped)}", flush=True)
    if not scenes:
        raise SystemExit("no scene to run")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    results: dict[str, Any] = {"config": vars(a), "environment": environment(), "scenes": {}, "skipped_scenes": skipped,
                               "heldout_drawn": drawn}
    for name in scenes:
        results["scenes"][name] = run_scene(name, a)
        results["wall_seconds"] = time.perf_counter() - started
        (out / "results.json").write_text(json.dumps({**results, "complete": False}, indent=1))  # a long run's scenes so far
    results["complete"] = True
    text = tables(results)
    print("\n" + text, flush=True)
    save_results(out, results, text)
    (out / "tables.md").write_text(text)
    plots = plot_results(results, out)
    print(f"wrote {out}/results.json, tables.md, summary.md and {len(plots)} plot(s) ({results['wall_seconds']:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
