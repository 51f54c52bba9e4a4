"""Argument checks shared by the render Functions (the public boundary)."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import mitsuba as mi
import torch

from ..scene import Scene

_UINT32 = 2**32


@dataclass(frozen=True)
class RenderSettings:
    """Validated sample counts, seeds and sensor of one render call."""

    sensor: int
    spp: int
    seed: int
    spp_grad: int
    seed_grad: int


def render_settings(scene: Scene, sensor: int | mi.Sensor, spp: object, seed: object, spp_grad: object | None,
                    seed_grad: object | None) -> RenderSettings:
    """Check the arguments every render Function takes; ``spp_grad`` defaults to ``spp``; a
    ``sensor`` given as one of the scene's ``mi.Sensor`` objects becomes its index."""
    spp = check_count("spp", spp)
    spp_grad = spp if spp_grad is None else check_count("spp_grad", spp_grad)
    seed, seed_grad = seeds(seed, seed_grad)
    sensor = scene.sensor_index(sensor)
    return RenderSettings(sensor=sensor, spp=spp, seed=seed, spp_grad=spp_grad, seed_grad=seed_grad)


def check_scene(scene: object) -> Scene:
    if not isinstance(scene, Scene):
        raise TypeError(
            f"scene must be a torchir.Scene (Scene.builtin / from_file / from_dict), got {type(scene).__name__}"
        )
    return scene


def check_count(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return value


def check_seed(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if not 0 <= value < _UINT32:
        raise ValueError(f"{name} must be in [0, 2^32), got {value}")
    return value


def seeds(seed: object, seed_grad: object | None) -> tuple[int, int]:
    """(seed, seed_grad): ``seed_grad`` defaults to a hash of ``seed``, and must differ from it
    (reusing the primal's random numbers in the adjoint pass biases the gradient)."""
    seed = check_seed("seed", seed)
    if seed_grad is None:
        seed_grad = int(mi.sample_tea_32(seed, 1)[0])
    seed_grad = check_seed("seed_grad", seed_grad)
    if seed_grad == seed:
        raise ValueError("seed_grad must differ from seed: a gradient pass that reuses the primal's samples is biased")
    return seed, seed_grad


def split_params(scene: Scene, params: Mapping[str, torch.Tensor] | None) -> tuple[dict[str, torch.Tensor], frozenset[str]]:
    """Validated ``{name: tensor}`` and the names to differentiate (those requiring grad)."""
    params = {} if params is None else params
    scene.check_values(params)
    params = scene.expand_derived(params)  # derived parameters (e.g. light.azimuth) -> Mitsuba keys
    # dr.wrap converts only exact torch.Tensor objects: view subclasses such as nn.Parameter
    # as plain tensors (a differentiable view, so gradients still reach the Parameter).
    values = {n: t if type(t) is torch.Tensor else t.as_subclass(torch.Tensor) for n, t in params.items()}
    grad_names = frozenset(n for n, t in values.items() if t.requires_grad and torch.is_grad_enabled())
    return values, grad_names
