"""The extremes matrix: every public piece against extreme and bad input.

Each :class:`Case` runs one piece (render, render_pixels, a sampler, a module, the trainer
step) under one condition and expects either a finite result or a specific, clear exception;
never a crash inside Dr.Jit and never a silent NaN. Where the right value is known (a light
switched off renders exactly zero, emission scales the image linearly, a constant pmf gives
weights 1/N, a saturated LOI term has zero gradient, ...), the case's ``check`` verifies it. ``tests/core/test_extremes.py`` runs every
case in CI; ``torchir bench`` lists the matrix and its outcomes in its report.

Example:
    >>> from torchir.extremes import CASES, run
    >>> rows = run(CASES[:2])   # run() runs them all: [(piece, condition, expected, outcome, ok), ...]
    >>> [ok for *_, ok in rows]
    [True, True]
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from . import backend

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
    check: Callable[[Any, dict[str, Any]], str | None] | None = None  # finite result -> None, or what is wrong


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
RESTIR_CBOX = {"resolution": 8, "max_depth": 2}  # the ReSTIR cases' cbox: direct light only


def _cached(ctx: dict[str, Any], name: str, **options: Any) -> Any:
    """``Scene.builtin(name, **options)``, built once per context: every render binds its own
    values onto the loaded scene, and one scene instead of one per case lets the cases share
    their kernels (each live scene changes the virtual calls' code)."""
    import torchir

    key = (name, tuple(sorted(options.items())))
    if key not in ctx.setdefault("scenes", {}):
        ctx["scenes"][key] = torchir.Scene.builtin(name, **options)
    return ctx["scenes"][key]


def _with_gradients(out: torch.Tensor, values: dict[str, torch.Tensor]) -> Any:
    """``out``, and the gradients of its sum w.r.t. the values that require grad."""
    leaves = [v for v in values.values() if v.requires_grad]
    if not leaves:
        return out
    out.sum().backward()
    return [out, *[v.grad for v in leaves]]


def _render(scene: str, params: Callable[[], dict] | None = None, **kw) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.functions import render

        values = {} if params is None else params()
        return _with_gradients(render(ctx[scene], values, **{"spp": 2, "seed": 1, **kw}), values)

    return run


def _pixels(scene: str, index: Callable[[dict], torch.Tensor], params: Callable[[], dict] | None = None, **kw) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.functions import render_pixels

        values = {} if params is None else params()
        return _with_gradients(render_pixels(ctx[scene], values, index(ctx), **{"spp": 1, "seed": 2, **kw}), values)

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


def _module(make: Callable[[], Any], inputs: Callable[[], tuple], backward: bool = True) -> Callable[[dict], Any]:
    """Call an nn.Module on ``inputs()``; backpropagate the sum through the first input."""

    def run(ctx: dict) -> Any:
        args = inputs()
        first = args[0].clone().requires_grad_()
        out = make()(first, *args[1:])
        if backward:
            out.sum().backward()
            return [out, first.grad]
        return out

    return run


def _images(*shapes_and_fills: tuple) -> Callable[[], tuple]:
    def make() -> tuple:
        g = torch.Generator(device="cpu").manual_seed(0)
        out = []
        for shape, fill in shapes_and_fills:
            x = torch.rand(shape, generator=g, device="cpu")
            out.append(fill(x) if fill is not None else x)
        return tuple(out)

    return make


def _firefly(x: torch.Tensor) -> torch.Tensor:
    x = x.clone()
    x[..., 3, 3] = 1e6
    return x


def _nan(x: torch.Tensor) -> torch.Tensor:
    x = x.clone()
    x[..., 0, 0] = math.nan
    return x


def _restir(light: float | None = None, albedo: float | None = None, **options: Any) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        from torchir.functions import render
        from torchir.samplers import ReSTIRSampler

        scene = _cached(ctx, "cbox", **RESTIR_CBOX)
        values: dict[str, torch.Tensor] = {RED: torch.full((3,), 0.5 if albedo is None else albedo, requires_grad=True)}
        if light is not None:
            values[LIGHT] = torch.full((3,), light)
        sampler = ReSTIRSampler(scene, **{"burn_in": 2, "seed": 0, **options})
        images = []
        for step in range(3):
            image = render(scene, values, spp=1, seed=step, sampler=sampler)
            image.sum().backward()
            images.append(image)
        d = sampler.diagnostics()
        return [*images, values[RED].grad, torch.tensor([float(d.get("max_W", 0.0)), float(d.get("mean_M", 0.0))])]

    return run


def _trainer_step(**model: Any) -> Callable[[dict], Any]:
    def run(ctx: dict) -> Any:
        import lightning.pytorch as pl

        from torchir.training import InverseRenderingModule, ViewDataModule
        from torchir.training.cli import quiet_lightning

        module = InverseRenderingModule(**{"scene": "cbox", "resolution": 8, "spp": 1, **model})
        initial = [p.latent.detach().clone() for p in module.scene_parameters]
        with quiet_lightning():  # the report's console: its tables, not Lightning's notices
            trainer = pl.Trainer(accelerator=backend.device(), max_steps=2, logger=False, enable_checkpointing=False,
                                 enable_progress_bar=False, enable_model_summary=False)
            trainer.fit(module, datamodule=ViewDataModule(target_spp=8))
        ctx["trainer_module"] = module
        return [*(p.latent for p in module.scene_parameters), *initial]

    return run


# ------------------------------------------------------------------------------ checks
def _first(result: Any) -> torch.Tensor:
    return result[0] if isinstance(result, (list, tuple)) else result


def _all_zero(result: Any, ctx: dict) -> str | None:
    tensors = result if isinstance(result, (list, tuple)) else [result]
    bad = [i for i, t in enumerate(tensors) if torch.count_nonzero(t)]
    return f"outputs {bad} should be exactly zero" if bad else None


def _non_negative_with_positive_gradient(result: Any, ctx: dict, strict: bool = True) -> str | None:
    """Radiance is >= 0, and no path throughput falls when an albedo grows: d(sum)/d(albedo)
    >= 0, and > 0 (``strict``) when the image has enough paths to reach the wall."""
    out, *grads = result if isinstance(result, (list, tuple)) else [result]
    out = out.detach()
    if float(out.min()) < 0:
        return f"negative radiance {float(out.min())}"
    if grads and not bool((grads[0] > 0 if strict else grads[0] >= 0).all()):
        return f"albedo gradient {grads[0].tolist()} should be {'>' if strict else '>='} 0 in every channel"
    return None


def _scales_with_emission(baseline: Callable[[dict], torch.Tensor], factor: Callable[[dict], torch.Tensor]) -> Callable[[Any, dict], str | None]:
    """Radiance is linear in the emitted radiance: the same paths at ``L`` give ``L / L0`` times
    the image at the scene's ``L0`` (``factor`` broadcasts ``L / L0`` over the output)."""

    def check(result: Any, ctx: dict) -> str | None:
        out, expected = _first(result), baseline(ctx) * factor(ctx)
        if not torch.allclose(out, expected, rtol=1e-4, atol=0):
            return f"not linear in emission: max relative error {float(((out - expected).abs() / expected.abs().clamp_min(1e-30)).max()):.3g}"
        return None

    return check


def _light_ratio(shape: tuple[int, ...]) -> Callable[[dict], torch.Tensor]:
    return lambda ctx: (1e6 / ctx["cbox"].get(LIGHT)).view(shape)


def _weights_and_pdf(weight: float, pixels: int = 64) -> Callable[[Any, dict], str | None]:
    """A uniform pmf over ``pixels`` and weights ``1 / (N m p) = weight`` for every draw."""

    def check(result: Any, ctx: dict) -> str | None:
        w, pdf = result if isinstance(result, (list, tuple)) else (result, None)
        if not torch.allclose(w, torch.full_like(w, weight), rtol=1e-6, atol=0):
            return f"weights {w[:4].tolist()}... should all be {weight}"
        if pdf is not None and not torch.allclose(pdf, torch.full_like(pdf, 1.0 / pixels), rtol=1e-9, atol=0):
            return "pmf should be uniform"
        return None

    return check


def _valid_pmf(alpha: float = 0.1, pixels: int = 64) -> Callable[[Any, dict], str | None]:
    """Sums to 1, keeps ``p >= alpha / m``, and ``w = 1 / (N m p)`` for the drawn pixels."""

    def check(result: Any, ctx: dict) -> str | None:
        w, pdf = result
        if abs(float(pdf.sum()) - 1) > 1e-12 or float(pdf.min()) < alpha / pixels * (1 - 1e-9):
            return f"pmf sums to {float(pdf.sum())}, min {float(pdf.min())} < alpha / m"
        if float(w.max()) > 1.0 / (w.numel() * alpha) * (1 + 1e-6):
            return f"weight {float(w.max())} above 1 / (N alpha)"
        return None

    return check


def _shape(*shape: int) -> Callable[[Any, dict], str | None]:
    def check(result: Any, ctx: dict) -> str | None:
        out = _first(result)
        if tuple(out.shape) != shape:
            return f"shape {tuple(out.shape)}, expected {shape}"
        return _non_negative_with_positive_gradient(result, ctx, strict=False)  # 1-2 paths may miss the wall

    return check


def _loi_gradient(where: Callable[[torch.Tensor], torch.Tensor], sign: str) -> Callable[[Any, dict], str | None]:
    """LOI's gradient on the pixels ``where(grad)`` selects: ``"zero"`` (saturated: the point
    CDFs are flat that far outside the range; near the borders the zero padding, blurred in,
    brings values back into range, hence the interior crop) or ``"negative"`` (raising the image lowers the loss)."""

    def check(result: Any, ctx: dict) -> str | None:
        loss, grad = result
        g = where(grad)
        loss = float(loss.detach())
        if loss <= 0:
            return f"loss {loss} should be > 0 for different images"
        if sign == "zero" and torch.count_nonzero(g):
            return f"gradient should be exactly zero there, max |g| = {float(g.abs().max())}"
        if sign == "negative" and not bool((g < 0).all()):
            return "gradient should be < 0 everywhere (the target is brighter everywhere)"
        return None

    return check


def _restir_door_closed(**options: Any) -> Callable[[dict], Any]:
    """``ajar_painting`` with the door shut and no fill light: every light candidate of every
    shading point is occluded, every reservoir stays empty."""

    def run(ctx: dict) -> Any:
        from torchir.functions import render
        from torchir.samplers import ReSTIRSampler

        scene = _cached(ctx, "ajar_painting", resolution=8, texture=2, door=0.0, fill=0.0)
        key = "painting.bsdf.reflectance.data"
        texture = torch.full_like(scene.get(key), 0.5).requires_grad_()
        sampler = ReSTIRSampler(scene, **{"burn_in": 2, "seed": 0, **options})
        images = []
        for step in range(3):
            image = render(scene, {key: texture}, spp=1, seed=step, sampler=sampler)
            (image * (1.0 + torch.rand_like(image))).sum().backward()  # a non-zero adjoint everywhere
            images.append(image)
        d = sampler.diagnostics()
        return [*images, texture.grad, torch.tensor([float(d.get("max_W", 0.0)), float(d.get("mean_M", 0.0))])]

    return run


def _restir_light_on_after_burn_in(**options: Any) -> Callable[[dict], Any]:
    """Burn-in and two steps with the light off, then a step with it on: the old (empty)
    reservoirs are not reused for that step, the fresh candidates find the light."""

    def run(ctx: dict) -> Any:
        from torchir.functions import render
        from torchir.samplers import ReSTIRSampler

        scene = _cached(ctx, "cbox", **RESTIR_CBOX)
        red = torch.full((3,), 0.5, requires_grad=True)
        sampler = ReSTIRSampler(scene, **{"burn_in": 2, "seed": 0, **options})
        off = {RED: red, LIGHT: torch.zeros(3)}
        for step in range(2):
            render(scene, off, spp=1, seed=step, sampler=sampler)
        image = render(scene, {RED: red}, spp=1, seed=2, sampler=sampler)
        image.sum().backward()
        return [image, red.grad]

    return run


def _lit_with_gradient(result: Any, ctx: dict) -> str | None:
    image, grad = (t.detach() for t in result)
    if not (torch.isfinite(image).all() and float(image.mean()) > 0 and torch.isfinite(grad).all() and float(grad.abs().sum()) > 0):
        return "the light switched on must light the image and give a finite, non-zero albedo gradient"
    return None


def _restir_positive_gradient(result: Any, ctx: dict) -> str | None:
    """Images >= 0, and the red wall's direct light gives d(sum)/d(albedo) > 0 in every
    channel (the ReSTIR estimate of a positive integrand is positive), also for a black wall."""
    *images, grad, _ = result
    return _non_negative_with_positive_gradient([images[-1], grad], ctx)


def _restir_light_off(result: Any, ctx: dict) -> str | None:
    *images, grad, stats = result
    if any(torch.count_nonzero(t) for t in (*images, grad)) or float(stats[0]) != 0:
        return "a switched-off light must give zero images, zero gradient and max W = 0"
    return None


def _restir_scales_with_emission(result: Any, ctx: dict) -> str | None:
    """ReSTIR's resampling is invariant to a constant factor on the emission (the target
    ``p_hat`` and the weights ``W`` scale inversely), so the same seeds give the default
    light's images and albedo gradient times ``L / L0``, channel by channel."""
    *images, grad, _ = result
    *base_images, base_grad, _ = _restir()(ctx)
    ratio = 1e6 / _cached(ctx, "cbox", **RESTIR_CBOX).get(LIGHT)
    for i, (out, base) in enumerate(zip(images, base_images)):
        if not torch.allclose(out, base * ratio.view(3, 1, 1), rtol=1e-4, atol=0):
            return f"image {i} not linear in emission"
    if not torch.allclose(grad, base_grad * ratio, rtol=1e-4, atol=0):
        return f"albedo gradient {grad.tolist()} is not {(base_grad * ratio).tolist()}"
    return None


def _towards_target(inputs: Callable[[], tuple]) -> Callable[[Any, dict], str | None]:
    """The loss is > 0 and its gradient points from the image towards the target, per value."""

    def check(result: Any, ctx: dict) -> str | None:
        loss, grad = result
        x, y = inputs()[:2]
        if float(loss.detach()) <= 0:
            return f"loss {float(loss)} should be > 0 for different images"
        if not bool((grad * (x - y) > 0).all()):
            return f"gradient {grad.flatten().tolist()} should have the sign of image - target {(x - y).flatten().tolist()}"
        return None

    return check


def _denoised_as_reference(inputs: Callable[[], tuple], radius: int = 3) -> Callable[[Any, dict], str | None]:
    """The target-aware denoiser's output equals the float64 least-squares reference (per pixel,
    to float32 rounding of the largest input its window sees), and its gradient is that of a
    linear map clamped at 0: ``out = clamp(L f, 0)`` is positively homogeneous of degree 1 in
    ``f``, so ``sum_i f_i d(sum out)/d f_i == sum out`` (Euler), for any ``L``."""

    def check(result: Any, ctx: dict) -> str | None:
        from torchir.modules.target_aware import target_aware_denoise_reference

        out, grad = result[0].detach(), result[1]
        noisy, target = inputs()
        reference = target_aware_denoise_reference(noisy, target, radius=radius).to(out.dtype)
        seen = torch.nn.functional.max_pool2d(noisy.abs(), 2 * radius + 1, stride=1, padding=radius)
        if not bool(((out - reference).abs() <= 1e-5 * (1 + seen)).all()):
            return f"differs from the least-squares reference by {float((out - reference).abs().max()):.3g}"
        return _euler(out, grad, noisy)

    return check


def _euler(out: torch.Tensor, grad: torch.Tensor, noisy: torch.Tensor) -> str | None:
    """``sum_i f_i d(sum out)/d f_i == sum out`` for a linear map clamped at 0 (Euler)."""
    euler, total = float((grad.double() * noisy.double()).sum()), float(out.double().sum())
    if abs(euler - total) > 1e-5 * float((grad.double() * noisy.double()).abs().sum()):
        return f"sum_i f_i dL/df_i = {euler:.6g}, expected sum(out) = {total:.6g}: not the clamped linear map's gradient"
    return None


def _denoised_black_target(result: Any, ctx: dict) -> str | None:
    """A black target makes every weight 1 and every regressor 0: the fit is the plain mean of
    the noisy image over each pixel's window (3 pixels each side, truncated at the border)."""
    out, grad = result[0].detach(), result[1]
    noisy = _images(((1, 3, 16, 16), None))()[0]
    mean = torch.nn.functional.avg_pool2d(noisy, 7, stride=1, padding=3, count_include_pad=False)
    if not torch.allclose(out, mean, rtol=1e-5, atol=1e-6):
        return f"not the window mean: max error {float((out - mean).abs().max()):.3g}"
    return _euler(out, grad, noisy)


def _denoised_identity(result: Any, ctx: dict) -> str | None:
    """One pixel: its window is itself, so the denoiser returns the input and a unit gradient."""
    out, grad = result[0].detach(), result[1]
    noisy = _images(((1, 3, 1, 1), None))()[0]
    if not (torch.equal(out, noisy) and torch.equal(grad, torch.ones_like(grad))):
        return f"1x1: out {out.flatten().tolist()} should be the input {noisy.flatten().tolist()} with gradient 1"
    return None


def _one_pixel_step(result: Any, ctx: dict) -> str | None:
    """A 1-pixel step traces exactly budget x (spp + spp_grad) = 2 paths (Stage 1 ran at step 0
    only), and Adam moves each latent by at most ~lr per step (|m^ / sqrt(v^)| <= 1.0014 for two
    steps with the default betas), so never more than 2.01 lr over the two steps."""
    module = ctx["trainer_module"]
    half = len(result) // 2
    paths = module.step_metrics.get("paths_per_step")
    if paths != 2.0:
        return f"paths_per_step {paths}, expected 1 pixel x 2 paths"
    moved = max(float((after - before).abs().max()) for after, before in zip(result[:half], result[half:]))
    if moved > 2.01 * module.lr:
        return f"a latent moved by {moved:.3g} in two Adam steps of lr {module.lr}"
    return None


def _restir_b1(result: Any, ctx: dict) -> str | None:
    *images, grad, stats = result
    if float(stats[1]) != 1.0:
        return f"B.1 has M = 1 everywhere, got mean M {float(stats[1])}"
    return _non_negative_with_positive_gradient([images[-1], grad], ctx)


CASES: list[Case] = [
    # render -------------------------------------------------------------------------
    Case("render", "NaN parameter", _render("cbox", lambda: {RED: torch.tensor([math.nan, 0.5, 0.5])}), ValueError, "NaN"),
    Case("render", "Inf parameter", _render("cbox", lambda: {RED: torch.tensor([math.inf, 0.5, 0.5])}), ValueError, "Inf"),
    Case("render", "unknown parameter name", _render("cbox", lambda: {"red.reflectance.valu": torch.zeros(3)}), KeyError, "red.reflectance.value"),
    Case("render", "wrong shape (4 values for a colour)", _render("cbox", lambda: {RED: torch.zeros(4)}), ValueError, "shape"),
    Case("render", "zero albedo (+ gradient)", _render("cbox", _grad([0.0, 0.0, 0.0])), check=_non_negative_with_positive_gradient),
    Case("render", "all-zero radiance (light off)", _render("cbox", lambda: {LIGHT: torch.zeros(3)}), check=_all_zero),
    Case("render", "1e6 radiance", _render("cbox", lambda: {LIGHT: torch.full((3,), 1e6)}), check=_scales_with_emission(lambda c: _render("cbox")(c), _light_ratio((3, 1, 1)))),
    Case("render", "1 spp", _render("cbox", spp=1), check=_shape(3, 8, 8)),
    Case("render", "4096 spp (1x1 image)", _render("one", spp=4096), check=_shape(3, 1, 1)),
    Case("render", "1x1 image (+ gradient)", _render("one", _grad([0.5, 0.5, 0.5])), check=_shape(3, 1, 1)),
    Case("render", "non-square 4x12 image (+ gradient)", _render("wide", _grad([0.5, 0.5, 0.5])), check=_shape(3, 4, 12)),
    Case("render", "spp 0", _render("cbox", spp=0), ValueError, "spp"),
    Case("render", "seed_grad == seed", _render("cbox", seed=3, seed_grad=3), ValueError, "seed_grad"),
    # render_pixels --------------------------------------------------------------------
    Case("render_pixels", "one pixel (+ gradient)", _pixels("cbox", lambda c: torch.tensor([5]), _grad([0.5, 0.5, 0.5])), check=_shape(1, 3)),
    Case("render_pixels", "full budget, every pixel twice", _pixels("cbox", lambda c: torch.arange(64).repeat(2)), check=_shape(128, 3)),
    Case("render_pixels", "index out of range", _pixels("cbox", lambda c: torch.tensor([64])), IndexError, "out of range"),
    Case("render_pixels", "empty index", _pixels("cbox", lambda c: torch.zeros(0, dtype=torch.int64)), ValueError, "non-empty"),
    Case("render_pixels", "float index", _pixels("cbox", lambda c: torch.tensor([1.0])), TypeError, "integer"),
    Case("render_pixels", "1e6 radiance", _pixels("cbox", lambda c: torch.arange(8), lambda: {LIGHT: torch.full((3,), 1e6)}), check=_scales_with_emission(lambda c: _pixels("cbox", lambda _: torch.arange(8))(c), _light_ratio((1, 3)))),
    Case("render_pixels", "non-square image", _pixels("wide", lambda c: torch.arange(48)), check=_shape(48, 3)),
    # pixel samplers --------------------------------------------------------------------
    Case("AdaptivePixelSampler", "budget 1", _sampler("adaptive", budget=1), check=_weights_and_pdf(1.0)),
    Case("AdaptivePixelSampler", "budget > pixels (with replacement)", _sampler("adaptive", budget=1000), check=_weights_and_pdf(1 / 1000)),
    Case("AdaptivePixelSampler", "budget 0", _sampler("adaptive", budget=0), ValueError, "budget"),
    Case("AdaptivePixelSampler", "negative budget", _sampler("adaptive", budget=-4), ValueError, "budget"),
    Case("AdaptivePixelSampler", "all-zero p1 (uniform fallback)", _sampler("adaptive", lambda: (torch.zeros(1, 8, 8), torch.rand(1, 8, 8))), check=_weights_and_pdf(1 / 16)),
    Case("AdaptivePixelSampler", "all-zero p2 (uniform fallback)", _sampler("adaptive", lambda: (torch.rand(1, 8, 8), torch.zeros(1, 8, 8))), check=_weights_and_pdf(1 / 16)),
    Case("AdaptivePixelSampler", "one hot pixel", _sampler("adaptive", lambda: (torch.nn.functional.one_hot(torch.tensor(9), 64).reshape(1, 8, 8).float(), torch.ones(1, 8, 8))), check=_valid_pmf()),
    Case("AdaptivePixelSampler", "1e30 in the maps", _sampler("adaptive", lambda: (torch.full((1, 8, 8), 1e30), torch.ones(1, 8, 8))), check=_weights_and_pdf(1 / 16)),
    Case("LossPixelSampler", "NaN in p1 (warning, uniform)", _sampler("loss", _nan_map), check=_weights_and_pdf(1 / 16)),
    Case("UniformPixelSampler", "2^25 pixels", lambda ctx: __import__("torchir.samplers", fromlist=["x"]).UniformPixelSampler(resolution=(4096, 8192), budget=8).sample().weight, check=_weights_and_pdf(1 / 8)),
    # modules (pure torch) ----------------------------------------------------------------
    Case("TargetAwareDenoiser", "1e6 firefly in noisy", _module(lambda: _denoiser(), _images(((1, 3, 16, 16), _firefly), ((1, 3, 16, 16), None))), check=_denoised_as_reference(_images(((1, 3, 16, 16), _firefly), ((1, 3, 16, 16), None)))),
    Case("TargetAwareDenoiser", "black target", _module(lambda: _denoiser(), _images(((1, 3, 16, 16), None), ((1, 3, 16, 16), torch.zeros_like))), check=_denoised_black_target),
    Case("TargetAwareDenoiser", "1x1 image", _module(lambda: _denoiser(), _images(((1, 3, 1, 1), None), ((1, 3, 1, 1), None))), check=_denoised_identity),
    Case("TargetAwareDenoiser", "non-square 5x17 image", _module(lambda: _denoiser(), _images(((2, 3, 5, 17), None), ((2, 3, 5, 17), None))), check=_denoised_as_reference(_images(((2, 3, 5, 17), None), ((2, 3, 5, 17), None)))),
    Case("TargetAwareDenoiser", "NaN in noisy", _module(lambda: _denoiser(), _images(((1, 3, 8, 8), _nan), ((1, 3, 8, 8), None))), ValueError, "NaN"),
    Case("LOILoss", "constant images", _module(lambda: _loi(), _images(((1, 3, 16, 16), lambda x: torch.full_like(x, 0.3)), ((1, 3, 16, 16), lambda x: torch.full_like(x, 0.7)))), check=_loi_gradient(lambda g: g, "negative")),
    Case("LOILoss", "values far outside the range (bins with no mass)", _module(lambda: _loi(), _images(((1, 3, 16, 16), lambda x: x + 50), ((1, 3, 16, 16), lambda x: -x))), check=_loi_gradient(lambda g: g[..., 6:-6, 6:-6], "zero")),
    Case("LOILoss", "1e6 firefly", _module(lambda: _loi(), _images(((1, 3, 16, 16), _firefly), ((1, 3, 16, 16), None))), check=_loi_gradient(lambda g: g[..., 3, 3], "zero")),
    Case("LOILoss", "1x1 image", _module(lambda: _loi(), _images(((1, 3, 1, 1), None), ((1, 3, 1, 1), None))), check=_towards_target(_images(((1, 3, 1, 1), None), ((1, 3, 1, 1), None)))),
    Case("LOILoss", "NaN in target", _module(lambda: _loi(), _images(((1, 3, 8, 8), None), ((1, 3, 8, 8), _nan))), ValueError, "target"),
    Case("LOILoss", "Mitsuba (H,W,C) layout", _module(lambda: _loi(), _images(((8, 8, 3), None), ((8, 8, 3), None))), ValueError, "(H, W, C)"),
    # ReSTIR --------------------------------------------------------------------------------
    Case("ReSTIRSampler", "light switched off (empty reservoirs)", _restir(light=0.0), check=_restir_light_off),
    Case("ReSTIRSampler", "1e6 radiance", _restir(light=1e6), check=_restir_scales_with_emission),
    Case("ReSTIRSampler", "zero albedo", _restir(albedo=0.0), check=_restir_positive_gradient),
    Case("ReSTIRSampler", "every candidate occluded (door closed, no fill)", _restir_door_closed(), check=_restir_light_off),
    Case("ReSTIRSampler", "every candidate occluded, unshadowed target", _restir_door_closed(target="unshadowed"), check=_restir_light_off),
    Case("ReSTIRSampler", "light switched on after burn-in", _restir_light_on_after_burn_in(), check=_lit_with_gradient),
    Case("ReSTIRSampler", "persistent offsets: light switched off", _restir(light=0.0, preset="persistent"), check=_restir_light_off),
    Case("ReSTIRSampler", "persistent offsets: every candidate occluded", _restir_door_closed(preset="persistent"), check=_restir_light_off),
    Case("ReSTIRSampler", "persistent offsets: light switched on after burn-in", _restir_light_on_after_burn_in(preset="persistent"),
         check=_lit_with_gradient),
    Case("ReSTIRSampler", "persistent offsets: 1e6 radiance", _restir(light=1e6, preset="persistent"),
         check=_restir_positive_gradient),
    Case("ReSTIRSampler", "one candidate, no reuse (B.1)", _restir(preset="b1"), check=_restir_b1),
    Case("ReSTIRSampler", "light-position gradient (unsupported)", _trainer_step(scene="glossy_highlight", parameters={"light.azimuth": {"init": 0.5}}, sampler={"type": "restir"}), ValueError, "light parameter"),
    Case("ReSTIRSampler", "indirect light requested", lambda ctx: _restir_on_depth4(ctx), ValueError, "direct"),
    # trainer step ------------------------------------------------------------------------
    Case("trainer step", "1x1-pixel sampler budget", _trainer_step(sampler={"type": "adaptive", "budget": 1}), check=_one_pixel_step),
    Case("trainer step", "unknown loss", _trainer_step(loss="l3"), ValueError, "model.loss"),
    Case("trainer step", "unknown sampler type", _trainer_step(sampler={"type": "magic"}), ValueError, "sampler.type"),
]


def _denoiser() -> Any:
    from torchir.modules import TargetAwareDenoiser

    return TargetAwareDenoiser(radius=3)


def _loi() -> Any:
    from torchir.modules import LOILoss

    return LOILoss(alphas=(1, 5), sigmas=(1,))


def _restir_on_depth4(ctx: dict) -> Any:
    from torchir.samplers import ReSTIRSampler

    return ReSTIRSampler(ctx["cbox"])  # cbox renders with max_depth 4: not direct-only


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
    if not finite:
        return False, "non-finite output"
    if case.expect is not FINITE:
        return False, FINITE
    wrong = case.check(result, ctx) if case.check is not None else None
    return (False, f"finite but wrong: {wrong}") if wrong else (True, FINITE)


def run(cases: list[Case] | None = None) -> list[tuple[str, str, str, str, bool]]:
    """Run the matrix: ``[(piece, condition, expected, outcome, ok)]``."""
    ctx = _context()
    rows = []
    for case in CASES if cases is None else cases:
        ok, outcome = run_case(case, ctx)
        expected = case.expect if case.expect is FINITE else f"{getattr(case.expect, '__name__', case.expect)}"
        rows.append((case.piece, case.condition, expected, outcome, ok))
    return rows
