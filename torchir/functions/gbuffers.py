"""``render_gbuffers``: albedo, shading normal and depth of a scene (for G-buffer denoisers)."""
from __future__ import annotations

from collections.abc import Mapping

import drjit as dr
import mitsuba as mi
import torch

from .. import backend
from ..backend import gc_paused
from ..scene import Scene
from . import _args

__all__ = ["GBUFFER_CHANNELS", "render_gbuffers"]

GBUFFER_CHANNELS = ("albedo.r", "albedo.g", "albedo.b", "normal.x", "normal.y", "normal.z", "depth")
_AOVS = "albedo:albedo,nn:sh_normal,dd:depth"
_INTEGRATORS: dict[str, mi.Integrator] = {}  # one aov integrator per variant


def _aov_integrator() -> mi.Integrator:
    variant = backend.variant()
    if variant not in _INTEGRATORS:
        _INTEGRATORS[variant] = mi.load_dict({"type": "aov", "aovs": _AOVS})
    return _INTEGRATORS[variant]


def render_gbuffers(
    scene: Scene,
    params: Mapping[str, torch.Tensor] | None = None,
    spp: int = 4,
    seed: int = 0,
    sensor: int | mi.Sensor = 0,
) -> torch.Tensor:
    """G-buffers of ``scene`` with ``params`` bound, through Mitsuba's ``aov`` integrator.

    No gradients: values are bound detached and Dr.Jit's AD is suspended. Safe next to a
    differentiable :func:`~torchir.functions.render`: called before it, or between it and its
    ``backward()`` (the render's backward re-binds its own values; writing detached values into
    the scene after a plain ``mi.render`` would break Mitsuba's replay).
    Background pixels are 0 in every channel. Use a box reconstruction filter (the built-in
    scenes do): a wider filter averages normals across pixels.

    Args:
        scene: a :class:`torchir.Scene`.
        params: ``{Mitsuba key: tensor}`` as for :func:`~torchir.functions.render` (optional).
        spp: samples per pixel (averaged: anti-aliased albedo, normal and depth).
        seed: sampler seed.
        sensor: sensor index, or one of the scene's ``mi.Sensor`` objects (as :func:`~torchir.functions.render`).

    Returns:
        ``(7, H, W)`` float32: albedo RGB, shading normal XYZ (world space), depth (world units
        along each camera ray, Mitsuba's ``depth`` AOV: not the distance along the camera axis,
        so a wall facing the camera reads deeper towards the corners), in the order of
        ``GBUFFER_CHANNELS``.

    Example:
        >>> scene = torchir.Scene.builtin("cbox", resolution=16)
        >>> render_gbuffers(scene).shape
        torch.Size([7, 16, 16])
    """
    scene = _args.check_scene(scene)
    spp = _args.check_count("spp", spp)
    seed = _args.check_seed("seed", seed)
    sensor_obj = scene.sensor(scene.sensor_index(sensor))
    values, _ = _args.split_params(scene, params)
    with torch.no_grad(), dr.suspend_grad(), gc_paused():
        native = {name: scene.to_drjit(name, mi.TensorXf(t.detach().contiguous())) for name, t in values.items()}
        scene.bind(native)
        image = _aov_integrator().render(scene.mi_scene, sensor_obj, seed=seed, spp=spp, develop=True)
        sensor_obj.sampler().seed(0, 1)  # as Mitsuba's render op: do not keep the loop alive
        out = image.torch().clone()  # (H, W, 7)
    if out.shape[-1] != len(GBUFFER_CHANNELS):
        raise RuntimeError(f"aov integrator returned {out.shape[-1]} channels, expected {len(GBUFFER_CHANNELS)}")
    return out.permute(2, 0, 1).contiguous()
