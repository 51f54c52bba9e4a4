"""Sensor rigs: lists of Mitsuba sensor dicts placed around a target, for multi-view recovery.

Mitsuba's shape tutorial (``inverse_rendering/shape_optimization.ipynb``) looks at the object
from 8 cameras on a Fibonacci lattice (:func:`fibonacci`); its volume tutorial from 5 cameras on
a half circle (:func:`orbit` with ``start=-90, arc=180``); :func:`look_at` takes explicit poses.
Each function returns plain Mitsuba dicts (``{"type": "perspective", ...}``): give them to
:meth:`torchir.Scene.from_dict` / ``from_file`` / ``builtin`` as ``sensors=`` (they replace the
scene's own sensors), or ``mi.load_dict`` them yourself. In YAML: ``model.sensors: {type:
fibonacci, count: 8, distance: 5, fov: 45, resolution: 96}`` (:func:`from_spec`).

Every film is an RGB float32 ``hdrfilm`` with the tutorial's ``gaussian`` filter and
``sample_border: true`` by default; ``filter`` takes a plugin name or a dict. :func:`render_pixels
<torchir.functions.render_pixels>` estimates box-filtered pixels: use ``filter="box"`` there.

Example:
    >>> from torchir import rigs
    >>> views = rigs.fibonacci(8, distance=5, fov=45, resolution=16)
    >>> len(views), views[0]["type"], views[0]["film"]["rfilter"]
    (8, 'perspective', {'type': 'gaussian'})
    >>> scene = torchir.Scene.builtin("multiview", resolution=16, sensors=views)
    >>> scene.sensor_count, scene.resolution
    (8, (16, 16))
"""
from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence
from typing import Any, Callable, Union

import mitsuba as mi
import numpy as np

from . import backend
from ._specs import split_typed

__all__ = ["fibonacci", "orbit", "look_at", "from_spec", "RIGS"]

Resolution = Union[int, Sequence[int]]
Vector = Sequence[float]
GOLDEN_RATIO = (1 + 5**0.5) / 2


def fibonacci(
    count: int, distance: float, fov: float, resolution: Resolution, *, target: Vector = (0.0, 0.0, 0.0),
    up: Vector = (0.0, 1.0, 0.0), filter: str | Mapping[str, Any] = "gaussian", sample_border: bool = True,
    fov_axis: str = "x",
) -> list[dict[str, Any]]:
    """``count`` cameras on a Fibonacci lattice of the sphere of radius ``distance`` around
    ``target``, all looking at it, as Mitsuba's shape tutorial builds them: camera ``i`` sits at
    polar angle ``acos(1 - 2 (i + 0.5) / count)`` from +z and azimuth ``2 pi i / golden ratio``
    around it (the tutorial's ``up`` is +y).

    Args:
        count: number of cameras, >= 1.
        distance: distance from ``target``, > 0.
        fov: field of view in degrees along ``fov_axis`` (Mitsuba's default axis, ``x``).
        resolution: film size, ``H`` (square) or ``(H, W)``.
        target, up: the point looked at and the cameras' up direction.
        filter: the film's reconstruction filter, a plugin name or a dict (the tutorial: gaussian).
        sample_border: the film's ``sample_border`` (the tutorial: true).
    """
    count = _count(count)
    origins = []
    for i in range(count):
        theta = 2 * math.pi * i / GOLDEN_RATIO
        phi = math.acos(1 - 2 * (i + 0.5) / count)
        origins.append([math.cos(theta) * math.sin(phi), math.sin(theta) * math.sin(phi), math.cos(phi)])
    centre = _vector("target", target)
    poses = [(centre + _positive("distance", distance) * np.array(o), centre, up) for o in origins]
    return _sensors(poses, fov, resolution, filter, sample_border, fov_axis)


def orbit(
    count: int, distance: float, elevation: float, fov: float, resolution: Resolution, *, start: float = 0.0,
    arc: float = 360.0, target: Vector = (0.0, 0.0, 0.0), up: Vector = (0.0, 1.0, 0.0),
    filter: str | Mapping[str, Any] = "gaussian", sample_border: bool = True, fov_axis: str = "x",
) -> list[dict[str, Any]]:
    """``count`` cameras on a circle around ``up`` through ``target``, all looking at it.

    Camera ``i`` is at azimuth ``start + arc * i / count`` degrees (a right-handed turn about
    ``up``; azimuth 0 is +z seen from ``target``, or +x when ``up`` is along z) and ``elevation``
    degrees above the circle's plane, ``distance`` away. Mitsuba's volume tutorial:
    ``orbit(5, 4, 0, 45, 64, start=-90, arc=180, filter="tent", sample_border=False)``.

    Args:
        count, distance, fov, resolution, target, up, filter, sample_border: as :func:`fibonacci`.
        elevation: degrees above the plane, in (-90, 90).
        start, arc: the first azimuth and the arc the ``count`` cameras split evenly (degrees).
    """
    count = _count(count)
    if not -90.0 < float(elevation) < 90.0:
        raise ValueError(f"elevation must be in (-90, 90) degrees (a camera on the up axis has no up direction), got {elevation}")
    centre, axis = _vector("target", target), _unit("up", up)
    reference = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    front = reference - (reference @ axis) * axis
    front /= np.linalg.norm(front)
    right = np.cross(axis, front)  # a right-handed turn about up takes front to right
    e = math.radians(float(elevation))
    poses = []
    for i in range(count):
        a = math.radians(float(start) + float(arc) * i / count)
        direction = math.cos(e) * (math.cos(a) * front + math.sin(a) * right) + math.sin(e) * axis
        poses.append((centre + _positive("distance", distance) * direction, centre, up))
    return _sensors(poses, fov, resolution, filter, sample_border, fov_axis)


def look_at(
    views: Sequence[Mapping[str, Vector]], fov: float, resolution: Resolution, *,
    filter: str | Mapping[str, Any] = "gaussian", sample_border: bool = True, fov_axis: str = "x",
) -> list[dict[str, Any]]:
    """One camera per ``{origin, target, up}`` of ``views`` (``target`` defaults to the origin of
    the world, ``up`` to +y); the other arguments as :func:`fibonacci`."""
    if isinstance(views, Mapping) or not isinstance(views, Sequence) or not views:
        raise ValueError(f"look_at views must be a non-empty list of {{origin, target, up}}, got {views!r}")
    poses = []
    for k, view in enumerate(views):
        if not isinstance(view, Mapping) or "origin" not in view or set(view) - {"origin", "target", "up"}:
            raise ValueError(f"look_at views[{k}] must be a mapping {{origin, target, up}} (origin required), got {view!r}")
        poses.append((_vector(f"views[{k}].origin", view["origin"]), _vector(f"views[{k}].target", view.get("target", (0.0, 0.0, 0.0))),
                      view.get("up", (0.0, 1.0, 0.0))))
    return _sensors(poses, fov, resolution, filter, sample_border, fov_axis)


RIGS: dict[str, Callable[..., list[dict[str, Any]]]] = {"fibonacci": fibonacci, "orbit": orbit, "look_at": look_at}


def from_spec(spec: Mapping[str, Any], resolution: Resolution | None = None, where: str = "model.sensors") -> list[dict[str, Any]]:
    """The sensors of a ``{type: fibonacci | orbit | look_at, **arguments}`` mapping (YAML's
    ``model.sensors``); ``resolution`` is used when the spec gives none, and must agree with it
    when it does. Unknown types, unknown or missing arguments: a ``ValueError`` naming them."""
    kind, options = split_typed(spec, RIGS, where, f"{{type: {' | '.join(RIGS)}, ...}}")
    if resolution is not None:
        if "resolution" in options and _hw(options["resolution"]) != _hw(resolution):
            raise ValueError(f"model.resolution ({resolution}) and {where}.resolution ({options['resolution']}) differ: give one")
        options["resolution"] = resolution
    signature = inspect.signature(RIGS[kind])
    unknown = set(options) - set(signature.parameters)
    if unknown:
        raise ValueError(f"{where} ({kind}) has unknown key(s) {sorted(unknown)}; allowed: {sorted(signature.parameters)}")
    missing = [n for n, p in signature.parameters.items() if p.default is p.empty and n not in options]
    if missing:
        hint = " (or set model.resolution)" if "resolution" in missing else ""
        raise ValueError(f"{where} ({kind}) needs {missing}{hint}")
    return RIGS[kind](**options)


# ------------------------------------------------------------------------------- helpers
def _sensors(poses, fov: float, resolution: Resolution, filter, sample_border: bool, fov_axis: str) -> list[dict[str, Any]]:
    """Perspective sensor dicts of ``(origin, target, up)`` poses sharing one film."""
    backend.variant()  # mi.ScalarTransform4f needs a variant
    if not (isinstance(fov, (int, float)) and 0 < fov < 180):
        raise ValueError(f"fov must be in (0, 180) degrees, got {fov!r}")
    h, w = _hw(resolution)
    rfilter = {"type": filter} if isinstance(filter, str) else dict(filter)
    if not isinstance(rfilter.get("type"), str):
        raise ValueError(f"filter must be a plugin name ('gaussian', 'box', 'tent') or {{type: name, ...}}, got {filter!r}")
    out = []
    for origin, target, up in poses:
        origin, target, up = _vector("origin", origin), _vector("target", target), _unit("up", up)
        forward = target - origin
        if np.linalg.norm(forward) < 1e-9:
            raise ValueError(f"a camera at {origin.tolist()} looks at itself: origin and target coincide")
        if np.linalg.norm(np.cross(forward / np.linalg.norm(forward), up)) < 1e-6:
            raise ValueError(f"the camera at {origin.tolist()} looks along its up direction {up.tolist()}: give another up")
        out.append({
            "type": "perspective",
            "fov": float(fov),
            "fov_axis": fov_axis,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=target.tolist(), up=up.tolist()),
            "sampler": {"type": "independent", "sample_count": 4},  # torchir's renders pass their own spp
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": rfilter, "pixel_format": "rgb",
                     "component_format": "float32", "sample_border": bool(sample_border)},
        })
    return out


def _count(count: object) -> int:
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be an int >= 1, got {count!r}")
    return count


def _positive(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def _vector(name: str, value: object) -> np.ndarray:
    out = np.asarray(value, dtype=np.float64)
    if out.shape != (3,) or not np.isfinite(out).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return out


def _unit(name: str, value: object) -> np.ndarray:
    out = _vector(name, value)
    norm = np.linalg.norm(out)
    if norm < 1e-12:
        raise ValueError(f"{name} must be a non-zero direction, got {value!r}")
    return out / norm


def _hw(resolution: object) -> tuple[int, int]:
    if isinstance(resolution, int) and not isinstance(resolution, bool):
        h = w = resolution
    elif isinstance(resolution, Sequence) and not isinstance(resolution, str) and len(resolution) == 2 \
            and all(isinstance(r, int) and not isinstance(r, bool) for r in resolution):
        h, w = resolution
    else:
        raise ValueError(f"resolution must be an int or [H, W], got {resolution!r}")
    if h < 1 or w < 1:
        raise ValueError(f"resolution must be positive, got {resolution!r}")
    return int(h), int(w)
