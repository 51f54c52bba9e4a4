"""What changed in a scene between two ReSTIR steps, from its parameters (cheap host reads).

- :class:`EmitterWatch`: which lights are on and where they are: temporal reuse must pause for
  a step when a light comes on or moves (its samples lie outside the old reservoirs' support).
- :class:`GeometryWatch`: a fingerprint of the geometry: a frozen (``dr.freeze``) pass replays
  the acceleration structure it was recorded with, so it must not outlive a geometry change.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["EmitterWatch", "GeometryWatch", "ValueReader", "as_tuples"]


class ValueReader:
    """:func:`_fingerprint` of scene values, read from the device only when their Dr.Jit
    variables changed since the last read under the same key.

    A Dr.Jit variable never changes its value (a write makes a new one), so the same variable
    indices mean the same values. The reader keeps the last value it read per key alive, so its
    indices cannot be given to new variables meanwhile. On a GPU every read is a copy and a sync:
    a light or shape that stays put is now read once, not at every step (``device_audit``).
    """

    def __init__(self) -> None:
        self._last: dict[str, tuple[object, tuple, tuple]] = {}  # key: (value kept alive, indices, fingerprint)

    def __call__(self, key: str, value) -> tuple:
        indices = _variable_indices(value)
        last = self._last.get(key)
        if indices and last is not None and last[1] == indices:
            return last[2]
        fingerprint = _fingerprint(value)
        if indices:
            self._last[key] = (value, indices, fingerprint)
        return fingerprint


def _variable_indices(value) -> tuple:
    """The Dr.Jit variable indices behind ``value`` (a transform, array or tensor); ``()`` when
    there are none to go by (Python numbers, a variable not yet created)."""
    if "Transform" in type(value).__name__:
        value = value.matrix
    if dr.is_tensor_v(value):
        value = value.array
    if not dr.is_jit_v(value):
        return ()
    if dr.depth_v(value) == 1:
        return (value.index,) if value.index else ()
    parts = [_variable_indices(entry) for entry in value]
    return () if any(not p for p in parts) else tuple(i for p in parts for i in p)


class EmitterWatch:
    """Which lights are on, and where they are, as the scene's parameters say.

    Temporal reuse tests a neighbour's support (whether ``p̂`` of the chosen sample is positive
    there, which decides the count ``Z`` of the unbiased 1/Z weight) in the *current* scene, not
    the previous step's, which is exact only while the support stays put. A light that comes on
    (all its emission values were zero) or moves makes the old reservoirs unable to hold its
    samples, so Z would count them and darken the image (measurements: docs/restir.md, "Speed";
    docs/restir-measurements.md, "Scene watches"). :meth:`same_support` says when the
    previous step's reservoirs must not be reused. A light dimmed, brightened or switched off
    keeps or shrinks the support: reuse goes on.
    """

    _EMISSION = ("radiance.value", "intensity.value", "irradiance.value", "scale", ".data")
    _PLACEMENT = ("position", "to_world", "vertex_positions", "direction")

    def __init__(self) -> None:
        self._scene: mi.Scene | None = None  # held, not its address: a freed scene's address is reused
        self._keys: list[tuple[list[str], list[str]]] = []  # (emission, placement) keys per light
        self._params = None
        self._read = ValueReader()

    def _bind(self, scene: mi.Scene) -> None:
        self._scene, self._params = scene, mi.traverse(scene)
        keys = list(self._params.keys())
        self._keys = []
        for em in scene.emitters():
            shape = em.get_shape()
            if shape is not None:
                own, place = f"{shape.id()}.emitter.", [k for k in keys if k in (f"{shape.id()}.to_world", f"{shape.id()}.vertex_positions")]
            else:
                own = f"{em.id()}."
                place = [k for k in keys if k.startswith(own) and k[len(own):] in self._PLACEMENT]
            emission = [k for k in keys if k.startswith(own) and k.endswith(self._EMISSION) and "sampling_weight" not in k]
            self._keys.append((emission, place))

    def __call__(self, scene: mi.Scene) -> tuple:
        """``(lights on, placements)``: one entry per emitter."""
        if self._scene is not scene:
            self._bind(scene)
        on, where = [], []
        for emission, place in self._keys:
            on.append(all(_has_nonzero(self._read(k, self._params[k])) for k in emission))
            where.append(tuple(self._read(k, self._params[k]) for k in place))
        return tuple(on), tuple(where)

    @staticmethod
    def same_support(before: tuple | None, now: tuple) -> bool:
        """False when a light came on or moved since ``before`` (None: unknown, assume so)."""
        if before is None:
            return False
        (on0, at0), (on1, at1) = before, now
        if len(on0) != len(on1):
            return False
        return not any(b and not a for a, b in zip(on0, on1)) and at0 == at1


class GeometryWatch:
    """A fingerprint of the scene's geometry: the Dr.Jit variable of each mesh's vertex
    positions (a new one whenever they are written) and each shape's transform."""

    def __init__(self) -> None:
        self._scene: mi.Scene | None = None  # held, not its address: a freed scene's address is reused
        self._params = None
        self._keys: list[str] = []
        self._read = ValueReader()

    def __call__(self, scene: mi.Scene) -> tuple:
        if self._scene is not scene:
            self._scene, self._params = scene, mi.traverse(scene)
            shapes = {sh.id() for sh in scene.shapes()}
            self._keys = [k for k in self._params.keys()
                          if k.split(".", 1)[0] in shapes and k.endswith((".vertex_positions", ".to_world"))]
        out = []
        for key in self._keys:
            v = self._params[key]
            index = getattr(v, "index", 0)
            out.append(index if index else self._read(key, v))
        return tuple(out)


def as_tuples(value):
    """Lists (e.g. from a JSON or YAML round trip) back to the tuples the state compares."""
    if isinstance(value, (list, tuple)):
        return tuple(as_tuples(v) for v in value)
    return value


def _fingerprint(v) -> tuple:
    """The value of a scene parameter as a tuple of floats (large arrays: size, sum and sum of
    squares). Width-1 literals (a light's colour, a point light's position) are read without
    numpy or a host sync: this runs for every light whose variables changed (:class:`ValueReader`),
    so it must stay cheap (measurements: docs/restir-measurements.md, "Scene watches")."""
    if isinstance(v, (int, float)):
        return (float(v),)
    if "Transform" in type(v).__name__:  # (points have a .matrix too)
        return tuple(np.asarray(v.matrix, dtype=np.float64).ravel().tolist())
    if not dr.is_tensor_v(v) and dr.width(v) == 1:
        depth = dr.depth_v(v)
        if depth == 2:
            return tuple(float(c[0]) for c in v)
        if depth == 1:
            return (float(v[0]),)
    vals = np.asarray(v, dtype=np.float64).ravel()
    return tuple(vals.tolist()) if vals.size <= 16 else (vals.size, float(vals.sum()), float((vals * vals).sum()))


def _has_nonzero(values: tuple) -> bool:
    """Whether a :func:`_fingerprint` says some value is nonzero."""
    if len(values) == 3 and isinstance(values[0], int):  # a large array: (size, sum, sum of squares)
        return values[2] != 0
    return any(x != 0 for x in values)
