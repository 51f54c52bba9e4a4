"""Derived parameters for any scene: a shape's pose, or a function of your own.

A derived parameter is optimised in torch and mapped to a Mitsuba key before the render
(:meth:`torchir.Scene.derive`). This module builds the common ones:

- :func:`rigid_transform`: ``<name>.translation`` (3,), ``<name>.rotation`` (degrees: (3,) Euler
  angles about x, then y, then z; or (1,) about a fixed ``rotation_axis``) and ``<name>.scale``
  (1,), applied to a mesh's ``vertex_positions`` or to an analytic shape's ``to_world``, as in
  Mitsuba's pose-estimation tutorial.
- :func:`from_function`: ``target = fn(*inputs)`` with ``fn`` given as ``"module:attr"`` or
  ``"file.py:attr"`` (how YAML names it).

YAML (``model.derived`` of :class:`~torchir.training.InverseRenderingModule`)::

    derived:
      bunny: {type: rigid, shape: bunny, rotation_axis: [0, 1, 0], pivot: [0, 0, 0]}
      lamp:  {type: function, target: light.position, function: lamp.py:at_height, inputs: {lamp.height: [1.0]}}
"""
from __future__ import annotations

import importlib
import importlib.util
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Optional, Union

import torch

from ._specs import split_typed
from .scene import Scene

__all__ = ["rigid_transform", "from_function", "declare", "rotation_matrix", "load_callable"]

Pivot = Union[str, Sequence[float]]


def rotation_matrix(angles_deg: torch.Tensor, axis: Optional[torch.Tensor] = None) -> torch.Tensor:
    """A (3, 3) rotation, differentiable in the angles.

    Args:
        angles_deg: (3,) Euler angles in degrees, applied about x, then y, then z
            (``R = Rz Ry Rx``); or (1,) an angle about ``axis``.
        axis: (3,) unit axis (Rodrigues' formula) when ``angles_deg`` has one entry.
    """
    rad = angles_deg * (math.pi / 180.0)
    if axis is not None:
        k = axis / axis.norm()
        kx = torch.zeros(3, 3, dtype=rad.dtype, device=rad.device)
        rows, cols = (torch.tensor(i, device=rad.device) for i in ([0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]))
        kx = kx.index_put((rows, cols), torch.stack([-k[2], k[1], k[2], -k[0], -k[1], k[0]]))
        eye = torch.eye(3, dtype=rad.dtype, device=rad.device)
        return eye + torch.sin(rad[0]) * kx + (1 - torch.cos(rad[0])) * (kx @ kx)
    cx, cy, cz = torch.cos(rad)
    sx, sy, sz = torch.sin(rad)
    one, zero = torch.ones_like(cx), torch.zeros_like(cx)
    rx = torch.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx]).reshape(3, 3)
    ry = torch.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy]).reshape(3, 3)
    rz = torch.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one]).reshape(3, 3)
    return rz @ ry @ rx


def _pivot(pivot: Pivot, points: torch.Tensor) -> torch.Tensor:
    if isinstance(pivot, str):
        if pivot != "center":
            raise ValueError(f"pivot must be 'center' or a point [x, y, z], got {pivot!r}")
        return 0.5 * (points.min(0).values + points.max(0).values)
    p = torch.as_tensor(pivot, dtype=torch.float64, device=points.device)
    if p.shape != (3,):
        raise ValueError(f"pivot must be 'center' or a point [x, y, z], got {pivot!r}")
    return p


def rigid_transform(
    scene: Scene,
    shape: str,
    name: Optional[str] = None,
    rotation_axis: Optional[Sequence[float]] = None,
    pivot: Pivot = "center",
    translation: Sequence[float] = (0.0, 0.0, 0.0),
    rotation: Union[float, Sequence[float]] = 0.0,
    scale: float = 1.0,
) -> list[str]:
    """Declare the pose of shape ``shape`` as derived parameters of ``scene``.

    ``x' = pivot + s R (x - pivot) + t`` for every vertex ``x`` of a mesh (target
    ``<shape>.vertex_positions``), or the same map composed with an analytic shape's
    ``<shape>.to_world``. The load-time pose is the identity unless ``translation``,
    ``rotation`` or ``scale`` say otherwise (then the loaded shape is moved by it).

    Args:
        scene: the scene to declare them in.
        shape: the shape's id (the prefix of its Mitsuba keys).
        name: prefix of the new parameters (default: ``shape``).
        rotation_axis: optimise one angle about this axis ((1,) ``<name>.rotation``), instead
            of three Euler angles.
        pivot: ``"center"`` or a point: what rotation and scale keep fixed. ``"center"`` is the
            centre of a mesh's bounding box as loaded, and for an analytic shape the point its
            ``to_world`` puts the shape's local origin at (the centre of a sphere, rectangle or
            disk; the base of Mitsuba's cylinder, which runs from z = 0 to 1).
        translation, rotation, scale: the load-time values (rotation in degrees).

    Returns:
        ``[<name>.translation, <name>.rotation, <name>.scale]``.
    """
    name = name or shape
    vertex_key, world_key = f"{shape}.vertex_positions", f"{shape}.to_world"
    keys = scene.parameter_names()
    if vertex_key in keys:
        target = vertex_key
        points = scene.get(vertex_key).double().reshape(-1, 3)
        origin = _pivot(pivot, points)
    elif world_key in keys:
        target = world_key
        m0 = scene.get(world_key).double()
        origin = _pivot(pivot, m0[:3, 3:].T)  # 'center': where to_world puts the shape's origin
    else:
        shapes = sorted({k.rsplit(".", 1)[0] for k in keys if k.endswith((".vertex_positions", ".to_world"))})
        raise KeyError(f"shape {shape!r} has neither {vertex_key!r} nor {world_key!r}; shapes with a pose: {shapes}")
    axis = None if rotation_axis is None else torch.as_tensor(rotation_axis, dtype=torch.float64, device=origin.device)
    if axis is not None and (axis.shape != (3,) or float(axis.norm()) == 0.0):
        raise ValueError(f"rotation_axis must be a non-zero [x, y, z], got {rotation_axis!r}")
    n_angles = 1 if axis is not None else 3
    rot0 = torch.as_tensor(rotation, dtype=torch.float32, device="cpu").flatten()
    rot0 = rot0.expand(n_angles).clone() if rot0.numel() == 1 else rot0
    if rot0.numel() != n_angles:
        raise ValueError(f"rotation must have {n_angles} angle(s) (degrees), got {list(rot0.tolist())}")

    def linear_part(r: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        return s.double().reshape(()) * rotation_matrix(r.double(), axis)

    if target == vertex_key:
        def to_target(t: torch.Tensor, r: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
            a = linear_part(r, s)
            return ((points - origin) @ a.T + origin + t.double()).flatten().float()
    else:
        def to_target(t: torch.Tensor, r: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
            a = linear_part(r, s)
            top = torch.cat([a, (origin - a @ origin + t.double())[:, None]], 1)
            pose = torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64, device=a.device)], 0)
            return (pose @ m0).float()

    return scene.derive(
        target,
        to_target,
        {f"{name}.translation": list(translation), f"{name}.rotation": rot0.tolist(), f"{name}.scale": [float(scale)]},
    )


def load_callable(spec: str, base_dir: Optional[Path] = None) -> Callable[..., Any]:
    """``"package.module:attr"`` or ``"path/to/file.py:attr"`` (relative to ``base_dir``) -> the object."""
    if not isinstance(spec, str) or ":" not in spec:
        raise ValueError(f"function must be 'module:attr' or 'file.py:attr', got {spec!r}")
    where, attr = spec.rsplit(":", 1)
    if where.endswith(".py"):
        path = Path(where)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if not path.is_file():
            raise FileNotFoundError(f"function file not found: {str(path)!r} (from {spec!r})")
        module_spec = importlib.util.spec_from_file_location(f"torchir_user_{path.stem}", path)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    if not hasattr(module, attr):
        raise AttributeError(f"{where!r} has no attribute {attr!r} (from {spec!r})")
    return getattr(module, attr)


def from_function(scene: Scene, target: str, function: Union[str, Callable[..., torch.Tensor]],
                  inputs: Mapping[str, Any], base_dir: Optional[Path] = None) -> list[str]:
    """Declare ``target = function(*inputs)``; ``function`` may be named as in :func:`load_callable`."""
    fn = load_callable(function, base_dir) if isinstance(function, str) else function
    if not callable(fn):
        raise TypeError(f"function {function!r} is not callable")
    return scene.derive(target, fn, dict(inputs))


_KINDS = {"rigid": rigid_transform, "function": from_function}


def declare(scene: Scene, label: str, spec: Mapping[str, Any], base_dir: Optional[Path] = None) -> list[str]:
    """Declare one ``model.derived`` entry ``{type: rigid | function, ...options}``; returns the names."""
    kind, options = split_typed(spec, _KINDS, f"model.derived[{label!r}]", "{type: rigid | function, ...}", not_mapping=TypeError)
    try:
        if kind == "rigid":
            options.setdefault("name", label)
            return rigid_transform(scene, **options)
        return from_function(scene, base_dir=base_dir, **options)
    except TypeError as error:
        if "unexpected keyword" in str(error) or "missing" in str(error):
            raise ValueError(f"model.derived[{label!r}] ({kind}): {error}") from None
        raise
