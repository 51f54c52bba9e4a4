"""The extremes matrix: every public piece against extreme and bad input.

Each :class:`Case` runs one piece (render, render_pixels, a sampler, a module, the trainer
step) under one condition and expects either a finite result or a specific, clear exception;
never a crash inside Dr.Jit and never a silent NaN. ``tests/test_extremes.py`` runs every
case in CI; ``torchir bench`` lists the matrix and its outcomes in its report.

Example:
    >>> from torchir.extremes import run
    >>> rows = run()            # [(piece, condition, expected, outcome, ok), ...]
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["Case", "CASES", "run", "run_case"]

FINITE = "finite"


@dataclass(frozen=True)
class Case:
    """One cell of the matrix: ``run(context)`` returns tensors (checked finite) or raises."""

    piece: str
    condition: str
    run: Callable[[dict[str, Any]], Any]
    expect: Any = FINITE  # FINITE, or an exception class (or tuple of classes)
    match: str = ""  # a substring the exception message must contain


# ----------------------------------------------------------------------------- context
def _context() -> dict[str, Any]:
    """Tiny scenes shared by all cases (built once: kernels compile once)."""
    import torchir

    torchir.backend.variant()
    return {
        "cbox": torchir.Scene.builtin("cbox", resolution=8),
        "wide": torchir.Scene.builtin("cbox", resolution=(4, 12)),
        "one": torchir.Scene.builtin("cbox", resolution=1),
    }


RED, LIGHT = "red.reflectance.value", "light.emitter.radiance.value"


def _render(scene: str, params: Callable[[], dict] | None = None, **kw) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.functions import render

        values = {} if params is None else params()
        image = render(ctx[scene], values, **{"spp": 2, "seed": 1, **kw})
        grads = [v for v in values.values() if v.requires_grad]
        if grads:
            image.sum().backward()
            return [image, *[g.grad for g in grads]]
        return image

    return run


def _pixels(scene: str, index: Callable[[dict], torch.Tensor], params: Callable[[], dict] | None = None, **kw) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.functions import render_pixels

        values = {} if params is None else params()
        out = render_pixels(ctx[scene], values, index(ctx), **{"spp": 1, "seed": 2, **kw})
        grads = [v for v in values.values() if v.requires_grad]
        if grads:
            out.sum().backward()
            return [out, *[g.grad for g in grads]]
        return out

    return run


def _grad(value: list[float]) -> Callable[[], dict]:
    return lambda: {RED: torch.tensor(value, requires_grad=True)}


def _sampler(strategy: str, maps: Callable[[], tuple] | None = None, **kw) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.samplers import SAMPLERS

        sampler = SAMPLERS[strategy](resolution=(8, 8), views=1, **{"budget": 16, **kw})
        if maps is not None:
            sampler.update_from_maps(*maps())
        batch = sampler.sample()
        return [batch.weight, sampler.pdf]

    return run


def _nan_map() -> tuple:
    p1 = torch.rand(1, 8, 8)
    p1[0, 2, 2] = math.nan
    return p1, torch.rand(1, 8, 8)


def _trainer_step(**model: Any) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        import lightning.pytorch as pl

        from torchir.training import InverseRenderingModule, ViewDataModule

        module = InverseRenderingModule(**{"scene": "cbox", "resolution": 8, "spp": 1, **model})
        trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
        trainer.fit(module, datamodule=ViewDataModule(target_spp=8))
        return [p.latent for p in module.scene_parameters]

    return run


CASES: list[Case] = [
    # render -------------------------------------------------------------------------
    Case("render", "NaN parameter", _render("cbox", lambda: {RED: torch.tensor([math.nan, 0.5, 0.5])}), ValueError, "NaN"),
    Case("render", "Inf parameter", _render("cbox", lambda: {RED: torch.tensor([math.inf, 0.5, 0.5])}), ValueError, "Inf"),
    Case("render", "unknown parameter name", _render("cbox", lambda: {"red.reflectance.valu": torch.zeros(3)}), KeyError, "red.reflectance.value"),
    Case("render", "wrong shape (4 values for a colour)", _render("cbox", lambda: {RED: torch.zeros(4)}), ValueError, "shape"),
    Case("render", "zero albedo (+ gradient)", _render("cbox", _grad([0.0, 0.0, 0.0]))),
    Case("render", "all-zero radiance (light off)", _render("cbox", lambda: {LIGHT: torch.zeros(3)})),
    Case("render", "1e6 radiance", _render("cbox", lambda: {LIGHT: torch.full((3,), 1e6)})),
    Case("render", "1 spp", _render("cbox", spp=1)),
    Case("render", "4096 spp (1x1 image)", _render("one", spp=4096)),
    Case("render", "1x1 image (+ gradient)", _render("one", _grad([0.5, 0.5, 0.5]))),
    Case("render", "non-square 4x12 image (+ gradient)", _render("wide", _grad([0.5, 0.5, 0.5]))),
    Case("render", "spp 0", _render("cbox", spp=0), ValueError, "spp"),
    Case("render", "seed_grad == seed", _render("cbox", seed=3, seed_grad=3), ValueError, "seed_grad"),
    # render_pixels --------------------------------------------------------------------
    Case("render_pixels", "one pixel (+ gradient)", _pixels("cbox", lambda c: torch.tensor([5]), _grad([0.5, 0.5, 0.5]))),
    Case("render_pixels", "full budget, every pixel twice", _pixels("cbox", lambda c: torch.arange(64).repeat(2))),
    Case("render_pixels", "index out of range", _pixels("cbox", lambda c: torch.tensor([64])), IndexError, "out of range"),
    Case("render_pixels", "empty index", _pixels("cbox", lambda c: torch.zeros(0, dtype=torch.int64)), ValueError, "non-empty"),
    Case("render_pixels", "float index", _pixels("cbox", lambda c: torch.tensor([1.0])), TypeError, "integer"),
    Case("render_pixels", "1e6 radiance", _pixels("cbox", lambda c: torch.arange(8), lambda: {LIGHT: torch.full((3,), 1e6)})),
    Case("render_pixels", "non-square image", _pixels("wide", lambda c: torch.arange(48))),
    # pixel samplers --------------------------------------------------------------------
    Case("AdaptivePixelSampler", "budget 1", _sampler("adaptive", budget=1)),
    Case("AdaptivePixelSampler", "budget > pixels (with replacement)", _sampler("adaptive", budget=1000)),
    Case("AdaptivePixelSampler", "budget 0", _sampler("adaptive", budget=0), ValueError, "budget"),
    Case("AdaptivePixelSampler", "negative budget", _sampler("adaptive", budget=-4), ValueError, "budget"),
    Case("AdaptivePixelSampler", "all-zero p1 (uniform fallback)", _sampler("adaptive", lambda: (torch.zeros(1, 8, 8), torch.rand(1, 8, 8)))),
    Case("AdaptivePixelSampler", "all-zero p2 (uniform fallback)", _sampler("adaptive", lambda: (torch.rand(1, 8, 8), torch.zeros(1, 8, 8)))),
    Case("AdaptivePixelSampler", "one hot pixel", _sampler("adaptive", lambda: (torch.nn.functional.one_hot(torch.tensor(9), 64).reshape(1, 8, 8).float(), torch.ones(1, 8, 8)))),
    Case("AdaptivePixelSampler", "1e30 in the maps", _sampler("adaptive", lambda: (torch.full((1, 8, 8), 1e30), torch.ones(1, 8, 8)))),
    Case("LossPixelSampler", "NaN in p1 (warning, uniform)", _sampler("loss", _nan_map)),
    Case("UniformPixelSampler", "2^25 pixels", lambda ctx: __import__("torchir.samplers", fromlist=["x"]).UniformPixelSampler(resolution=(4096, 8192), budget=8).sample().weight),
    # trainer step ------------------------------------------------------------------------
    Case("trainer step", "1x1-pixel sampler budget", _trainer_step(sampler={"type": "adaptive", "budget": 1})),
    Case("trainer step", "unknown loss", _trainer_step(loss="l3"), ValueError, "model.loss"),
    Case("trainer step", "unknown sampler type", _trainer_step(sampler={"type": "magic"}), ValueError, "sampler.type"),
]


def _finite(result: Any) -> bool:
    tensors = result if isinstance(result, (list, tuple)) else [result]
    return all(bool(torch.isfinite(t).all()) for t in tensors if isinstance(t, torch.Tensor))


def run_case(case: Case, ctx: dict[str, Any]) -> tuple[bool, str]:
    """Run one case: ``(ok, outcome)`` where outcome is "finite", "non-finite" or the exception."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = case.run(ctx)
    except Exception as error:  # noqa: BLE001 - the outcome is what we report
        outcome = f"{type(error).__name__}: {str(error).splitlines()[0][:120]}"
        ok = case.expect is not FINITE and isinstance(error, case.expect) and case.match in str(error)
        return ok, outcome
    finite = _finite(result)
    return case.expect is FINITE and finite, FINITE if finite else "non-finite output"


def run(cases: list[Case] | None = None) -> list[tuple[str, str, str, str, bool]]:
    """Run the matrix: ``[(piece, condition, expected, outcome, ok)]``."""
    ctx = _context()
    rows = []
    for case in CASES if cases is None else cases:
        ok, outcome = run_case(case, ctx)
        expected = case.expect if case.expect is FINITE else f"{getattr(case.expect, '__name__', case.expect)}"
        rows.append((case.piece, case.condition, expected, outcome, ok))
    return rows
