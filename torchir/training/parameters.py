"""Optimised scene quantities: configuration, initial values, reparameterisation and bounds.

Each optimised Mitsuba key becomes one :class:`SceneParameter`: an ``nn.Parameter`` holding a
*latent* value ``u`` and a transform giving the scene value ``x = T(u)``:

============  =====================  ==========================================
transform     x = T(u)               use
============  =====================  ==========================================
``none``      ``u``                  plain values; ``bounds`` clamp after each step
``sigmoid``   ``lo + (hi-lo)σ(u)``   values in ``bounds`` (default (0, 1)) without clamping
``log``       ``exp(u)``             positive values spanning magnitudes
============  =====================  ==========================================

A mesh's ``<shape>.vertex_positions`` can instead take ``parametrization: {type: large_steps,
lambda: λ}`` (:class:`LargeStepsParameter`): the latent is the Large Steps differential
``u = (I + λL) x`` of the scene's mesh and the scene value ``x = (I + λL)^{-1} u``
(:class:`torchir.geometry.LargeSteps`).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Literal, Optional, Union

import torch
from torch import nn

from .._specs import split_typed

__all__ = ["ParameterConfig", "SceneParameter", "LargeStepsParameter", "PARAMETRIZATIONS", "large_steps_lambda"]

PARAMETRIZATIONS = ("large_steps",)  # the types of ParameterConfig.parametrization
MESH_SUFFIXES = (".ply", ".obj")  # mesh files (a truth mesh), read by torchir.geometry.read_mesh

InitValue = Union[float, list, str]


@dataclass
class ParameterConfig:
    """How one Mitsuba parameter is optimised (a ``model.parameters`` entry of the YAML config).

    Attributes:
        init: a constant (broadcast to the parameter's shape), an explicit nested list of the
            parameter's shape, ``"random"`` (uniform in ``bounds``, default [0, 1], drawn with
            ``seed``), ``"scene"`` (the value the scene was loaded with) or an image file
            (``.png``/``.jpg``/``.exr``...: a texture, read as linear values like a target).
        bounds: ``[lo, hi]``: clamped after every optimiser step (transform ``none``) or the
            range of the sigmoid (transform ``sigmoid``). ``lo`` and ``hi`` are numbers, or lists
            of one value per entry of the last axis (``[[0, 0, 0.2], [1, 1, 0.2]]`` for a colour
            or a translation); with transform ``none`` an entry whose ``lo == hi`` is pinned there
            (e.g. one axis of a rigid transform's translation).
        lr: learning rate of this parameter (default: the model's ``lr``).
        transform: ``none``, ``sigmoid`` or ``log`` (see the module docstring).
        seed: seed of a ``random`` init.
        truth: the ground-truth value (same forms as ``init``) for synthetic targets and the
            parameter error; default: the value the scene was loaded with. For a mesh's
            ``vertex_positions``, also a mesh file (``.ply``/``.obj``): the parameter's error is
            then its Chamfer and Hausdorff distances to that mesh (any topology); synthetic
            targets render it when it has the scene mesh's vertex count.
        parametrization: ``{type: large_steps, lambda: λ}`` (``λ > 0``, default 19) for a mesh's
            ``<shape>.vertex_positions``: optimise the Large Steps latent of the scene's mesh
            (:class:`LargeStepsParameter`). ``init`` is then the scene's mesh (the default, or
            ``scene``) or explicit positions; ``transform`` must stay ``none``, without ``bounds``.
        resolution: a coarse-to-fine schedule ``{resolution: first step}`` for a ``gridvolume``'s
            data (``<...>.data``, ``(Z, Y, X, C)``), e.g. ``{16: 0, 64: 20}``: 16³ from step 0,
            64³ from step 20 (a key ``n`` is ``n³``; ``"ZxYxX"`` or ``"[Z, Y, X]"`` give other
            shapes). ``init`` is taken at the first resolution; at each later stage the value is
            resampled trilinearly, with the optimiser's moments (:mod:`torchir.training.resolution`).
    """

    init: InitValue = 0.5
    bounds: Optional[tuple[Union[float, list], Union[float, list]]] = None
    lr: Optional[float] = None
    transform: Literal["none", "sigmoid", "log"] = "none"
    seed: int = 0
    truth: Optional[InitValue] = None
    parametrization: Optional[dict[str, Any]] = None
    resolution: Optional[dict[Union[int, str], int]] = None


def is_mesh_file(spec: object) -> bool:
    """Whether a config value names a mesh file (by its suffix: ``.ply``, ``.obj``)."""
    return isinstance(spec, str) and spec.lower().endswith(MESH_SUFFIXES)


def large_steps_lambda(key: str, spec: Any) -> float:
    """The ``λ`` of a checked ``parametrization`` mapping ``{type: large_steps, lambda: λ}``."""
    from ..geometry.largesteps import DEFAULT_LAMBDA

    where = f"parameters[{key!r}].parametrization"
    kind, options = split_typed(spec, PARAMETRIZATIONS, where, "{type: large_steps, lambda: λ}", mapping=dict)
    lambda_ = options.pop("lambda", DEFAULT_LAMBDA)
    if options:
        raise ValueError(f"{where} ({kind}) has unknown option(s) {sorted(options)}; allowed: ['lambda']")
    if isinstance(lambda_, bool) or not isinstance(lambda_, (int, float)) or not math.isfinite(lambda_) or lambda_ <= 0:
        raise ValueError(f"{where}.lambda must be a finite number > 0 (how far a gradient spreads over the surface; "
                         f"Mitsuba's tutorial uses 25), got {lambda_!r}")
    return float(lambda_)


def is_image_file(spec: object) -> bool:
    """Whether a config value names an image file (by its suffix)."""
    from ..imageio import ENCODED_SUFFIXES, LINEAR_SUFFIXES

    return isinstance(spec, str) and spec.lower().endswith(LINEAR_SUFFIXES + ENCODED_SUFFIXES)


def resolve_value(spec: InitValue, shape: torch.Size, scene_value: torch.Tensor, bounds, seed: int, what: str) -> torch.Tensor:
    """A float32 tensor of ``shape`` from a config value (see :class:`ParameterConfig`), on
    ``scene_value``'s device."""
    device = scene_value.device
    if isinstance(spec, str):
        if spec == "scene":
            return scene_value.clone()
        if spec == "random":
            lo, hi = (torch.as_tensor(b, dtype=torch.float32, device="cpu") for b in (bounds if bounds is not None else (0.0, 1.0)))
            generator = torch.Generator(device="cpu").manual_seed(seed)  # drawn on the host: the same values on every device
            return (lo + (hi - lo) * torch.rand(shape, generator=generator, device="cpu")).to(device)
        if is_image_file(spec):
            from ..imageio import read_image

            image = read_image(spec).permute(1, 2, 0)  # Mitsuba's (H, W, C)
            if tuple(image.shape) != tuple(shape):
                raise ValueError(f"{what}: image {spec!r} is {tuple(image.shape)} (H, W, C), the parameter is {tuple(shape)}")
            return image.contiguous().to(device)
        raise ValueError(f"{what} must be a number, a list, 'random', 'scene' or an image file, got {spec!r}")
    value = torch.as_tensor(spec, dtype=torch.float32, device=device)
    try:
        return value.expand(shape).clone() if value.dim() <= len(shape) else value.reshape(shape)
    except RuntimeError:
        raise ValueError(f"{what} has shape {tuple(value.shape)}, which does not fit the parameter's shape {tuple(shape)}") from None


class SceneParameter(nn.Module):
    """One optimised scene quantity: a latent ``nn.Parameter`` and its transform.

    Args:
        key: the Mitsuba key.
        initial: the initial scene value ``x0`` (the latent starts at ``T^{-1}(x0)``).
        config: its :class:`ParameterConfig`.
    """

    def __init__(self, key: str, initial: torch.Tensor, config: ParameterConfig) -> None:
        super().__init__()
        self.key, self.transform = key, config.transform
        bounds = config.bounds
        if config.transform == "sigmoid":
            bounds = bounds or (0.0, 1.0)
        elif config.transform == "log" and bounds is not None:
            raise ValueError(f"parameter {key!r}: transform 'log' keeps values positive; drop 'bounds'")
        if config.lr is not None and not (isinstance(config.lr, (int, float)) and config.lr == config.lr and abs(config.lr) != float("inf") and config.lr > 0):
            raise ValueError(f"parameter {key!r}: lr must be a finite number > 0 (gradient descent), got {config.lr!r}")
        self.bounds = _bounds(key, bounds, initial.shape, config.transform, initial.device)
        if self.bounds is not None:
            lo, hi = self.bounds
            outside = (initial < lo) | (initial > hi)
            if bool(outside.any()):
                bad = initial[outside].flatten()[:4].tolist()
                raise ValueError(
                    f"parameter {key!r}: init has {int(outside.sum())} value(s) outside bounds {_show(self.bounds)} "
                    f"(e.g. {[round(b, 6) for b in bad]}): change init or bounds"
                )
            if config.transform == "sigmoid":
                on_end = (initial <= lo) | (initial >= hi)
                if bool(on_end.any()):
                    raise ValueError(
                        f"parameter {key!r}: init has {int(on_end.sum())} value(s) on an end of the sigmoid's range "
                        f"{_show(self.bounds)} (e.g. {initial[on_end].flatten()[0].item():g}), which the sigmoid only reaches at "
                        "infinity: its slope there is ~0 and the parameter would barely move. Start inside the range "
                        "(e.g. its middle), widen bounds, or use transform: none with bounds"
                    )
        self.latent = nn.Parameter(self._inverse(initial.float()))

    def _inverse(self, x: torch.Tensor) -> torch.Tensor:
        if self.transform == "sigmoid":
            lo, hi = self.bounds
            t = ((x - lo) / (hi - lo)).clamp(1e-4, 1 - 1e-4)  # keep the logit finite at the bounds
            return torch.logit(t)
        if self.transform == "log":
            if bool((x <= 0).any()):
                raise ValueError(f"parameter {self.key!r}: transform 'log' needs a positive initial value")
            return x.log()
        if self.bounds is not None:
            x = x.clamp(*self.bounds)
        return x.clone()

    def forward(self) -> torch.Tensor:
        """The scene value ``T(latent)``, float32 in the parameter's Mitsuba shape."""
        u = self.latent
        if self.transform == "sigmoid":
            lo, hi = self.bounds
            return lo + (hi - lo) * torch.sigmoid(u)
        if self.transform == "log":
            return u.exp()
        return u

    @torch.no_grad()
    def project(self) -> None:
        """Enforce ``bounds`` after an optimiser step (only ``none`` needs it)."""
        if self.transform == "none" and self.bounds is not None:
            self.latent.clamp_(*self.bounds)

    def extra_repr(self) -> str:
        bounds = self.bounds if self.bounds is None or isinstance(self.bounds[0], float) else _show(self.bounds)
        return f"key={self.key!r}, shape={tuple(self.latent.shape)}, transform={self.transform!r}, bounds={bounds}"


class LargeStepsParameter(nn.Module):
    """A mesh's vertex positions optimised through Large Steps: the ``nn.Parameter`` ``latent``
    is ``u = (I + λL) x`` (flat ``(3n,)``, ``n`` welded vertices) and :meth:`forward` gives the
    scene value ``x = (I + λL)^{-1} u`` (flat ``(3V,)``, Mitsuba's ``vertex_positions``).

    Args:
        key: the Mitsuba key ``<shape>.vertex_positions``.
        large_steps: the mesh's :class:`torchir.geometry.LargeSteps`.
        initial: the initial positions ``x0`` (flat ``(3V,)``).
    """

    transform = "none"
    bounds = None

    def __init__(self, key: str, large_steps: Any, initial: torch.Tensor) -> None:
        super().__init__()
        self.key, self.large_steps = key, large_steps
        self.latent = nn.Parameter(large_steps.to_differential(initial.detach().float().reshape(-1)).detach())

    def forward(self) -> torch.Tensor:
        """The vertex positions ``(I + λL)^{-1} latent``, flat ``(3V,)`` float32."""
        return self.large_steps.from_differential(self.latent)

    def project(self) -> None:
        """Nothing to enforce (no bounds on a mesh)."""

    def extra_repr(self) -> str:
        return (f"key={self.key!r}, parametrization='large_steps', lambda={self.large_steps.lambda_}, "
                f"vertices={self.large_steps.vertex_count}, welded={self.large_steps.welded_count}")


Bounds = Union[tuple[float, float], tuple[torch.Tensor, torch.Tensor]]


def _bounds(key: str, bounds: Optional[tuple], shape: torch.Size, transform: str, device: torch.device | str = "cpu") -> Optional[Bounds]:
    """``bounds`` as two floats, or, where either end is a list, two float32 tensors of ``shape``
    (a list gives one value per entry of the last axis) on ``device``; checked: ``lo < hi``, or ``lo <= hi``
    per entry with transform ``none`` (an equal pair pins that entry)."""
    if bounds is None:
        return None
    if len(bounds) != 2:
        raise ValueError(f"parameter {key!r}: bounds must be [lo, hi], got {list(bounds)}")
    lo, hi = bounds
    if not isinstance(lo, (list, tuple, torch.Tensor)) and not isinstance(hi, (list, tuple, torch.Tensor)):
        if not lo < hi:
            raise ValueError(f"parameter {key!r}: bounds must satisfy lo < hi, got {list(bounds)}")
        return float(lo), float(hi)
    ends = []
    for name, end in (("lo", lo), ("hi", hi)):
        value = torch.as_tensor(end, dtype=torch.float32, device=device)
        try:
            ends.append(value.expand(shape).clone())
        except RuntimeError:
            raise ValueError(f"parameter {key!r}: bounds' {name} has shape {tuple(value.shape)}, which does not broadcast "
                             f"to the parameter's shape {tuple(shape)} (give one value per entry of its last axis)") from None
    lo, hi = ends
    bad = (lo >= hi) if transform == "sigmoid" else (lo > hi)
    if bool(bad.any()):
        rule = "lo < hi (the sigmoid's range)" if transform == "sigmoid" else "lo <= hi"
        raise ValueError(f"parameter {key!r}: bounds must satisfy {rule} for every entry, got {list(bounds)}")
    return lo, hi


def _show(bounds: Bounds) -> str:
    lo, hi = bounds
    if isinstance(lo, float):
        return f"[{lo}, {hi}]"
    return f"[{lo.flatten()[:6].tolist()}, {hi.flatten()[:6].tolist()}]" + (" (per entry)" if lo.numel() <= 6 else " (per entry, first 6)")
