"""Coarse-to-fine grid resolution of a volume parameter: ``ParameterConfig.resolution``.

A ``gridvolume``'s data (``<...>.data``, Mitsuba's ``(Z, Y, X, C)``) can be optimised on a grid
that grows during the run, as Mitsuba's volume tutorial (16³, then 64³ after 20 steps) and Yan et
al. 2025 (resolution doubled every 200 iterations) do: ``resolution: {16: 0, 64: 20}`` maps each
resolution to the first step it is used at (``16`` is ``16³``; ``"16x32x32"`` or ``"[16, 32, 32]"``
give ``(Z, Y, X)``). The parameter starts at the first resolution (its ``init`` there: a constant
broadcast, ``random`` drawn, ``scene`` resampled from the loaded grid); before the step that starts
a stage renders, :func:`apply_schedule` resamples it (:func:`torchir.volumes.resample`, trilinear,
Mitsuba's voxel convention):

* the *value* ``x = T(u)`` is resampled and the latent set to ``T^{-1}`` of it, so the field
  Mitsuba renders is unchanged by the resize (for transform ``none`` this is the latent itself;
  ``log`` and ``sigmoid`` keep their range, as trilinear weights are convex);
* the optimiser's state of the latent is resampled (Adam's ``exp_avg`` and ``exp_avg_sq``, linear
  and non-negative), its step count kept; per-entry ``bounds`` are resampled too, and ``bounds``
  still clamp after every step;
* a checkpoint holds the latent at its own size: :func:`match_checkpoint` (from
  ``on_load_checkpoint``) resizes the parameter to it before Lightning loads the state dict and the
  optimiser state, so a run resumed after a resize continues the uninterrupted run.

The parameter error against a truth grid of another resolution (the truth is the grid the scene
was loaded with unless ``truth`` says otherwise) compares the current grid resampled to the
truth's resolution (:func:`on_truth_grids`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional

import torch
from torch import nn

from ..volumes import check_grid_shape, resample
from . import param_swap
from .param_swap import map_state, swap_parameter

__all__ = ["ResolutionSchedule", "parse_schedule", "apply_schedule", "match_checkpoint", "on_truth_grids", "resize_parameter"]

Shape3 = tuple[int, int, int]


@dataclass(frozen=True)
class ResolutionSchedule:
    """Stages ``(first step, (Z, Y, X))``, steps strictly increasing from 0."""

    stages: tuple[tuple[int, Shape3], ...]

    @property
    def first(self) -> Shape3:
        return self.stages[0][1]

    def shape_at(self, step: int) -> Shape3:
        """The ``(Z, Y, X)`` of the stage that step ``step`` belongs to."""
        shape = self.first
        for start, stage_shape in self.stages:
            if step >= start:
                shape = stage_shape
        return shape


def parse_schedule(key: str, spec: object) -> ResolutionSchedule:
    """The checked schedule of ``parameters[key].resolution`` (``{resolution: first step}``)."""
    where = f"parameters[{key!r}].resolution"
    if not isinstance(spec, Mapping) or not spec:
        raise ValueError(f"{where} must be a non-empty mapping {{resolution: first step}}, e.g. {{16: 0, 64: 20}} "
                         f"(16³ from step 0, 64³ from step 20), got {spec!r}")
    stages = []
    for size, step in spec.items():
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise ValueError(f"{where}: the first step of resolution {size!r} must be an int >= 0, got {step!r}")
        stages.append((step, _shape(where, size)))
    if stages[0][0] != 0:
        raise ValueError(f"{where}: the first resolution must start at step 0 (the parameter is built at it), "
                         f"got {spec!r}; e.g. {{16: 0, 64: 20}}")
    for (a, _), (b, shape) in zip(stages, stages[1:]):
        if b <= a:
            raise ValueError(f"{where}: list the resolutions in the order they are used, with strictly increasing "
                             f"first steps; {shape} starts at step {b}, after a stage starting at step {a} ({spec!r})")
    return ResolutionSchedule(tuple(stages))


def _shape(where: str, size: object) -> Shape3:
    """A schedule key as ``(Z, Y, X)``: ``n`` (n³), ``"n"``, ``"ZxYxX"``, ``"[Z, Y, X]"`` or a sequence."""
    value: Any = size
    if isinstance(size, str):
        text = size.strip().strip("[]()")
        parts = [p for p in text.replace("x", ",").replace("X", ",").split(",") if p.strip()]
        try:
            value = [int(p) for p in parts]
        except ValueError:
            value = size
        if isinstance(value, list) and len(value) == 1:
            value = value[0]
    if isinstance(value, int) and not isinstance(value, bool):
        value = (value, value, value)
    try:
        return check_grid_shape(tuple(value) if isinstance(value, (list, tuple)) else value)
    except ValueError:
        raise ValueError(f"{where}: a resolution must be an int n >= 1 (an n³ grid) or (Z, Y, X) written as "
                         f"'ZxYxX' or '[Z, Y, X]', got {size!r}") from None


def schedules(scene: Any, configs: Mapping[str, Any]) -> dict[str, ResolutionSchedule]:
    """``{key: schedule}`` of the ``configs`` (``{key: ParameterConfig}``) that give ``resolution``, checked."""
    out = {}
    for key, config in configs.items():
        if config.resolution is not None:
            check_key(scene, key, config)
            out[key] = parse_schedule(key, config.resolution)
    return out


def check_key(scene: Any, key: str, config: Any) -> None:
    """Refuse a schedule on what is not a grid volume's data, or with a mesh parametrization."""
    info = scene.info(key)  # an unknown key: KeyError with close matches
    if not scene.is_grid_volume_data(key):
        raise ValueError(f"parameters[{key!r}].resolution applies to the data of a gridvolume ('<...>.data', e.g. "
                         f"'object.interior_medium.sigma_t.data'), not to {key!r} (type {info.type_name}, shape {info.shape})")
    if config.parametrization is not None:
        raise ValueError(f"parameters[{key!r}]: resolution and parametrization cannot be combined")


def initial_grid(spec: Any, scene_value: torch.Tensor, shape: Shape3, bounds: Any, seed: int, what: str) -> torch.Tensor:
    """The ``init`` (or any config value) of a scheduled grid at ``shape``: ``scene`` resampled from
    the loaded grid, other forms as :func:`~torchir.training.parameters.resolve_value` at that size."""
    from .parameters import is_image_file, resolve_value

    if spec == "scene":
        return resample(scene_value, shape)
    if is_image_file(spec):
        raise ValueError(f"{what}: an image file cannot initialise a volume grid; give a number, 'random' or 'scene'")
    return resolve_value(spec, torch.Size((*shape, scene_value.shape[-1])), scene_value, bounds, seed, what)


@torch.no_grad()
def resize_parameter(parameter: nn.Module, shape: Shape3, values: bool = True) -> tuple[nn.Parameter, nn.Parameter]:
    """Give a :class:`~torchir.training.parameters.SceneParameter` a new latent of grid size
    ``shape`` (``values``: its value resampled, else a placeholder to be loaded); per-entry bounds
    are resampled. Returns ``(old latent, new latent)``."""
    old = parameter.latent
    value = resample(parameter(), shape) if values else None
    bounds = parameter.bounds
    if bounds is not None and isinstance(bounds[0], torch.Tensor):
        parameter.bounds = tuple(resample(b, shape) for b in bounds)
    latent = parameter._inverse(value) if values else old.new_zeros((*shape, old.shape[-1]))
    parameter.latent = nn.Parameter(latent, requires_grad=old.requires_grad)
    return old, parameter.latent


def _resize(module: Any, index: int, shape: Shape3, values: bool) -> None:
    """Resize parameter ``index`` of ``module`` and carry the optimisers' state of its latent."""
    old, new = resize_parameter(module.scene_parameters[index], shape, values)
    trainer = module._trainer
    for optimizer in (trainer.optimizers if trainer is not None else []):
        if any(p is old for g in optimizer.param_groups for p in g["params"]):
            state = optimizer.state.get(old)
            moved = map_state(state, old, lambda t: resample(t, shape)) if state and values else None
            swap_parameter(optimizer, old, new, moved)


def apply_schedule(module: Any, step: int) -> list[str]:
    """Resize every scheduled parameter of ``module`` whose grid is not the size step ``step``
    renders at (``module.resolutions``: ``{key: ResolutionSchedule}``); the resized keys."""
    resized = []
    for index, key in enumerate(module.keys):
        schedule = module.resolutions.get(key)
        if schedule is None:
            continue
        shape = schedule.shape_at(step)
        if tuple(module.scene_parameters[index].latent.shape[:3]) != shape:
            _resize(module, index, shape, values=True)
            resized.append(key)
    if resized and module._trainer is not None:  # under DDP: a reducer over the new tensors (every process resizes alike)
        param_swap.rewrap_distributed(module._trainer)
    return resized


def match_checkpoint(module: Any, state_dict: Mapping[str, torch.Tensor]) -> None:
    """Give each scheduled parameter the grid size its latent has in ``state_dict`` (a checkpoint
    taken after a resize), so that loading the state dict and the optimiser state fits."""
    for index, key in enumerate(module.keys):
        saved = state_dict.get(f"scene_parameters.{index}.latent")
        if key in module.resolutions and saved is not None and saved.shape != module.scene_parameters[index].latent.shape:
            _resize(module, index, check_grid_shape(tuple(saved.shape[:3]), f"the checkpoint's {key!r}"), values=False)


def on_truth_grids(values: Mapping[str, torch.Tensor], truth: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``values`` with each grid ``(Z, Y, X, C)`` whose truth has another resolution resampled to
    the truth's (the parameter error of a coarse-to-fine grid is taken at the truth's resolution)."""
    out = dict(values)
    for key, t in truth.items():
        v = values.get(key)
        if v is not None and v.dim() == 4 and t.dim() == 4 and v.shape != t.shape and v.shape[-1] == t.shape[-1]:
            out[key] = resample(v.detach(), tuple(t.shape[:3]))
    return out
