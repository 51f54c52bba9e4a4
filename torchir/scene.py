"""Scene: load a Mitsuba 3 scene, list and read its parameters, bind torch values to it.

Parameter tensors keep Mitsuba's shapes, with vectors as a trailing axis:

=========================================  ====================  ===========================
Mitsuba value                              torch shape           example
=========================================  ====================  ===========================
``TensorXf`` (bitmap texture, grid)        its own shape         ``(H, W, C)`` texture
``Float`` of width n (flat arrays)         ``(n,)``              ``vertex_positions``: (3V,)
``Color3f``/``Point3f``/... of width 1     ``(3,)``              ``red.reflectance.value``
``Color3f``/``Point3f``/... of width n     ``(n, 3)``
=========================================  ====================  ===========================

A ``gridvolume``'s ``data`` (``(Z, Y, X, C)``) also binds at another resolution ``(Z', Y', X', C)``
(:meth:`Scene.is_grid_volume_data`; :func:`torchir.volumes.resample` resizes one), for
coarse-to-fine volume fits.

A render binds the values it is given for its own duration; parameters it is not given keep
the value the scene was loaded with. Binding is exact: the render Functions re-bind their
own values before their backward pass, so interleaved renders differentiate correctly.
"""
from __future__ import annotations

import difflib
import math
import os
import warnings
import weakref
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import drjit as dr
import mitsuba as mi
import torch

from . import backend
from ._scene_loading import (TextureStorage, _check_sensors, _check_texture_storage, _float_bitmaps, _integrator_spec,
                             _override_integrator, _replace_dict_sensors, _replace_parsed_sensors, _resolving_from)
from ._scene_values import _is_flat_float, _is_transform, _is_vector_array, _same_layout, _torch_shape, _unbindable_hint
from .welding import MeshWeld, group_normals, keep_loaded_welds, weld_of

__all__ = ["Scene", "ParameterInfo", "DerivedParameter"]


@dataclass(frozen=True)
class ParameterInfo:
    """What torch needs to know about one Mitsuba parameter."""

    name: str
    type_name: str  # Dr.Jit/Python type of the value, e.g. "TensorXf", "Color3f"
    shape: tuple[int, ...]  # torch-side shape (see the module docstring)
    bindable: bool  # can be given a torch tensor (float arrays and tensors)
    differentiable: bool  # Mitsuba marks it differentiable
    discontinuous: bool  # moving it moves visibility edges (needs a projective integrator)


@dataclass(frozen=True)
class DerivedParameter:
    """A torch-side reparameterisation: ``name`` is optimised, ``target`` (a Mitsuba key) is
    bound to ``to_target(*values of inputs)``, computed in torch before the Dr.Jit boundary.

    Several derived parameters may set one target together (a pose: translation, rotation and
    scale of one shape): they share ``to_target`` and ``inputs``; inputs a render does not give
    take their load-time ``value``. Declare them with :meth:`Scene.derive` or
    :func:`torchir.derived.rigid_transform`."""

    name: str
    target: str
    shape: tuple[int, ...]
    to_target: Callable[..., torch.Tensor]
    value: tuple[float, ...]  # the load-time value (flattened)
    inputs: tuple[str, ...] = ()  # every input of to_target, in call order; () means (name,)

    @property
    def group(self) -> tuple[str, ...]:
        return self.inputs or (self.name,)


# Keys whose change moves visibility edges. (Mitsuba also flags BSDF roughness "discontinuous",
# for its sampling, which prb handles.)
_GEOMETRY_KEYS = frozenset({"vertex_positions", "to_world", "center", "radius"})


def is_geometry_key(name: str) -> bool:
    """Whether Mitsuba key ``name`` moves geometry (``<shape>.vertex_positions``, ``.to_world``, ...)."""
    return name.rsplit(".", 1)[-1] in _GEOMETRY_KEYS


_LIVE: weakref.WeakSet = weakref.WeakSet()
EAGER_WELD_VERTICES = 250_000  # meshes up to this size are welded when the scene loads (larger: when first asked)


def live_scenes() -> list[Scene]:
    """The torchir scenes alive in this process (the frozen passes guard their buffers:
    :mod:`torchir._frozen`)."""
    return list(_LIVE)


class Scene:
    """A Mitsuba 3 scene that torch code renders and differentiates.

    Build one with :meth:`builtin`, :meth:`from_file` or :meth:`from_dict`. Each takes
    ``sensors=``: a list of Mitsuba sensor dicts (e.g. a :mod:`torchir.rigs` rig) or ``mi.Sensor``
    objects that *replace* the scene's own sensors, in their order (sensor ``i`` is
    ``sensors[i]``; an ``mi.Sensor`` given is the scene's own object, so ``render(...,
    sensor=that_object)`` works).

    Example:
        >>> scene = Scene.builtin("cbox", resolution=32)
        >>> scene.resolution, scene.sensor_count
        ((32, 32), 1)
        >>> scene.get("red.reflectance.value").shape
        torch.Size([3])
    """

    def __init__(self, mi_scene: mi.Scene, *, name: str | None = None, description: str = "") -> None:
        if not isinstance(mi_scene, mi.Scene):
            raise TypeError(f"expected a mitsuba Scene, got {type(mi_scene).__name__}")
        self.mi_scene = mi_scene
        self.name = name
        self.description = description
        self.params = mi.traverse(mi_scene)
        self._info: dict[str, ParameterInfo] = {}
        self._base: dict[str, Any] = {}  # load-time values of the parameters a render overrode
        self._loaded_normals: dict[str, Any] = {}  # a moved mesh's load-time normals, by its positions' name
        self._overridden: set[str] = set()
        self._owner: object | None = None  # the render op whose grad-enabled values are bound
        self._warned: set[str] = set()
        self._verdicts: dict[Hashable, Any] = {}  # checks on this scene's contents, kept as long as it lives
        # ids of the meshes whose vertex steps a Large Steps parametrization spreads over the surface
        # (torchir.geometry.LargeSteps adds them); render's shading-band warning advises accordingly
        self.spread_steps: set[str] = set()
        self.derived: dict[str, DerivedParameter] = {}  # reparameterisations declared by the scene
        self.is_builtin = False  # made by Scene.builtin (not from a user's file or dict)
        # each mesh's weld from the positions and normals it was loaded with, made when first asked
        # for; holding the meshes keeps their Python objects (and so their ids) for the scene's life
        self._meshes = {id(s): s for s in mi_scene.shapes() if isinstance(s, mi.Mesh)}
        self._loaded_welds: dict[int, MeshWeld] = {}
        for mesh_id, mesh in self._meshes.items():
            if int(mesh.vertex_count()) <= EAGER_WELD_VERTICES:
                self._loaded_welds[mesh_id] = weld_of(mesh)
        keep_loaded_welds(self)
        _LIVE.add(self)

    def mesh_weld(self, mesh: mi.Mesh) -> MeshWeld | None:
        """The :class:`~torchir.welding.MeshWeld` of ``mesh`` from the positions and normals it was
        loaded with, or None when ``mesh`` is not one of this scene's (see
        :func:`torchir.welding.mesh_weld`). Meshes over ``EAGER_WELD_VERTICES`` vertices are
        welded when first asked for, as they are then."""
        mesh_id = id(mesh)
        if self._meshes.get(mesh_id) is not mesh:
            return None
        weld = self._loaded_welds.get(mesh_id)
        if weld is None:
            weld = self._loaded_welds[mesh_id] = weld_of(mesh)
        return weld

    # ----------------------------------------------------------------------------- loading
    @classmethod
    def builtin(
        cls, name: str, resolution: int | tuple[int, int] | None = None, override_integrator: Mapping[str, Any] | None = None,
        sensors: Sequence[Mapping[str, Any] | mi.Sensor] | None = None, **options: Any,
    ) -> Scene:
        """A built-in procedural scene (see :func:`torchir.scenes.available`).

        Args:
            name: scene name, e.g. ``"cbox"``.
            resolution: ``H`` (square) or ``(H, W)``; each scene has a small default.
            override_integrator: ``{type: ..., **properties}`` replacing the scene's integrator.
            sensors: sensor dicts or ``mi.Sensor`` objects replacing the scene's sensors
                (``resolution`` then sizes only what the builder sizes besides its sensors).
            options: scene-specific options (documented on each scene's builder).
        """
        from . import scenes

        entry = scenes.get(name)
        backend.variant()
        scene_dict = entry.build(resolution=resolution, **options)
        if sensors is not None:
            scene_dict = _replace_dict_sensors(scene_dict, _check_sensors(sensors))
        if override_integrator is not None:
            scene_dict["integrator"] = _integrator_spec(override_integrator)
        derived = scene_dict.pop("torchir_derived", ())  # [(target, to_target, {name: value})]
        scene = cls(mi.load_dict(scene_dict, optimize=False), name=name, description=entry.description)
        scene.is_builtin = True
        for target, to_target, inputs in derived:
            scene.derive(target, to_target, inputs)
        return scene

    @classmethod
    def from_file(
        cls, path: str | os.PathLike, optimize: bool = False, texture_storage: TextureStorage = "float",
        override_integrator: Mapping[str, Any] | None = None, sensors: Sequence[Mapping[str, Any] | mi.Sensor] | None = None,
        **scene_args: Any,
    ) -> Scene:
        """Load a Mitsuba 3 XML scene file.

        Args:
            path: the ``.xml`` file.
            optimize: let Mitsuba merge shapes (off by default so every shape keeps its own,
                addressable parameters).
            texture_storage: ``"float"`` (default): every bitmap texture without an explicit
                ``format`` is stored as float32 linear values, so 8-bit PNG/JPEG and 16-bit
                textures can be optimised (converted once, at load). ``"file"``: Mitsuba's
                default (8-bit files stay ``TensorXu8``, 4x smaller, but cannot be bound).
            sensors: sensor dicts or ``mi.Sensor`` objects replacing the file's sensors.
            scene_args: ``$name`` substitutions of the XML file.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"scene file not found: {str(path)!r} (resolved to {path.resolve()})")
        _check_texture_storage(texture_storage)
        variant = backend.variant()
        sensors = None if sensors is None else _check_sensors(sensors)
        parser = mi.parser
        config = parser.ParserConfig(variant)
        config.merge_meshes = config.merge_equivalent = optimize
        with _resolving_from(path.parent):  # meshes and textures beside the file, as mi.load_file does
            state = parser.parse_file(config, str(path), **{k: str(v) for k, v in scene_args.items()})
            parser.transform_all(config, state)
            if texture_storage == "float":
                for node in state.nodes:
                    if node.props.plugin_name() == "bitmap" and "format" not in node.props:
                        node.props["format"] = "variant"
            if override_integrator is not None:
                _override_integrator(state, _integrator_spec(override_integrator), path)
            if sensors is not None:
                _replace_parsed_sensors(state, sensors)
            mi_scene = parser.instantiate(config, state)
        return cls(mi_scene, name=path.stem)

    @classmethod
    def from_dict(
        cls, scene_dict: Mapping[str, Any], optimize: bool = False, texture_storage: TextureStorage = "float",
        override_integrator: Mapping[str, Any] | None = None, sensors: Sequence[Mapping[str, Any] | mi.Sensor] | None = None,
    ) -> Scene:
        """Load a Mitsuba 3 scene dictionary (``{"type": "scene", ...}``); ``texture_storage`` and
        ``override_integrator`` as in :meth:`from_file`; ``sensors`` (dicts or ``mi.Sensor``
        objects) replace the dict's top-level sensors."""
        if not isinstance(scene_dict, Mapping) or scene_dict.get("type") != "scene":
            raise ValueError("expected a Mitsuba scene dict with 'type': 'scene'")
        _check_texture_storage(texture_storage)
        backend.variant()
        if texture_storage == "float":
            scene_dict = _float_bitmaps(scene_dict)
        scene_dict = dict(scene_dict)
        if sensors is not None:
            scene_dict = _replace_dict_sensors(scene_dict, _check_sensors(sensors))
        if override_integrator is not None:  # the dict's "integrator" entry (Mitsuba's convention)
            scene_dict["integrator"] = _integrator_spec(override_integrator)
        return cls(mi.load_dict(scene_dict, optimize=optimize))

    # --------------------------------------------------------------------------- queries
    @property
    def resolution(self) -> tuple[int, int]:
        """``(H, W)`` of sensor 0."""
        return self.sensor_resolution(0)

    def sensor_resolution(self, sensor: int = 0) -> tuple[int, int]:
        """``(H, W)`` of the film crop of sensor ``sensor``."""
        w, h = self.sensor(sensor).film().crop_size()
        return int(h), int(w)

    @property
    def sensor_count(self) -> int:
        return len(self.mi_scene.sensors())

    def sensor(self, index: int) -> mi.Sensor:
        """Sensor ``index``, with a clear error when out of range."""
        if isinstance(index, bool) or not isinstance(index, int):
            raise TypeError(f"sensor must be an int index, got {type(index).__name__}")
        if not 0 <= index < self.sensor_count:
            raise IndexError(f"sensor {index} out of range: the scene has {self.sensor_count} sensor(s)")
        return self.mi_scene.sensors()[index]

    def sensor_index(self, sensor: int | mi.Sensor) -> int:
        """The index of ``sensor``: an int index (range-checked) or one of this scene's own
        ``mi.Sensor`` objects. A sensor object the scene was not loaded with is an error that
        says how to add it (``sensors=`` of the loaders)."""
        if not isinstance(sensor, mi.Sensor):
            if isinstance(sensor, bool) or not isinstance(sensor, int):
                raise TypeError(f"sensor must be an int index or one of the scene's mi.Sensor objects, got {type(sensor).__name__}")
            self.sensor(sensor)
            return sensor
        for index, own in enumerate(self.mi_scene.sensors()):
            if own is sensor:
                return index
        raise ValueError(
            f"this mi.Sensor is not one of the scene's {self.sensor_count} sensor(s): a torchir render uses the "
            f"scene's own sensors. Load the scene with it, e.g. Scene.from_dict(d, sensors=sensors) (also "
            f"Scene.from_file(path, sensors=...) and Scene.builtin(name, sensors=...)), then pass it or its index"
        )

    @property
    def integrator(self) -> mi.Integrator:
        return self.mi_scene.integrator()

    def parameter_names(self, differentiable_only: bool = False) -> list[str]:
        """Mitsuba keys of the scene's parameters (``differentiable_only``: those Mitsuba
        marks differentiable and torch can bind)."""
        names = list(self.params.keys()) + list(self.derived)
        if differentiable_only:
            names = [n for n in names if self.info(n).differentiable and self.info(n).bindable]
        return names

    def info(self, name: str) -> ParameterInfo:
        """Type, torch shape and flags of parameter ``name``."""
        self._require_name(name)
        if name in self.derived:
            return ParameterInfo(name, "derived", self.derived[name].shape, True, True, False)
        if name not in self._info:
            value = self._base.get(name, self.params[name])
            shape, bindable = _torch_shape(value)
            flags = self.params.flags(name)
            self._info[name] = ParameterInfo(
                name=name,
                type_name=type(value).__name__,
                shape=shape,
                bindable=bindable,
                differentiable=not flags & int(mi.ParamFlags.NonDifferentiable),
                discontinuous=bool(flags & int(mi.ParamFlags.Discontinuous)),
            )
        return self._info[name]

    def is_grid_volume_data(self, name: str) -> bool:
        """Whether Mitsuba key ``name`` is the ``data`` of a ``gridvolume`` (a ``(Z, Y, X, C)``
        TensorXf): such a value binds at any positive resolution ``(Z', Y', X', C)`` with the
        loaded channel count ``C`` (Mitsuba then renders the grid at that size; ``info(name).shape``
        stays the loaded one). Every other key binds at its loaded shape only."""
        if name in self.derived or not name.endswith(".data") or name not in self.params:
            return False
        node = self.params.properties[name][2]
        return isinstance(node, mi.Volume) and node.class_name() == "GridVolume"

    def get(self, name: str) -> torch.Tensor:
        """A torch copy of parameter ``name`` as loaded (shape as in the module docstring), on the
        render device (:func:`torchir.backend.device`)."""
        info = self.info(name)
        if name in self.derived:
            return torch.tensor(self.derived[name].value, dtype=torch.float32, device=backend.device()).reshape(info.shape)
        value = self._base.get(name, self.params[name])
        if _is_transform(value):
            import numpy as np

            out = torch.from_numpy(np.array(value.matrix, dtype=np.float32).reshape(4, 4))
        elif dr.is_tensor_v(value) or _is_flat_float(value):
            out = value.torch()
        elif _is_vector_array(value):
            out = dr.ravel(value).torch()
        else:
            import numpy as np

            out = torch.as_tensor(np.array(value), device="cpu")
        return out.detach().to(device=backend.device(), copy=True).reshape(info.shape)

    def __repr__(self) -> str:
        h, w = self.resolution
        return f"Scene(name={self.name!r}, resolution=({h}, {w}), sensors={self.sensor_count})"

    # -------------------------------------------------------------- validation (public API)
    def _require_name(self, name: str) -> None:
        if not isinstance(name, str):
            raise TypeError(f"parameter names are strings, got {type(name).__name__}")
        if name not in self.params and name not in self.derived:
            close = difflib.get_close_matches(name, list(self.params.keys()), n=3, cutoff=0.5)
            hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise KeyError(
                f"unknown scene parameter {name!r}.{hint} "
                f"(scene.parameter_names() lists all {len(self.params)} keys)"
            )

    def check_values(self, values: Mapping[str, torch.Tensor]) -> None:
        """Validate torch values for :meth:`bind`: names, dtype, device, shape, finiteness."""
        if not isinstance(values, Mapping):
            raise TypeError(f"params must be a dict {{name: tensor}}, got {type(values).__name__}")
        expected_device = torch.device(backend.device())
        for name, tensor in values.items():
            info = self.info(name)
            if not isinstance(tensor, torch.Tensor):
                raise TypeError(f"params[{name!r}] must be a torch.Tensor, got {type(tensor).__name__}")
            if not info.bindable:
                raise TypeError(
                    f"parameter {name!r} has type {info.type_name}, which torchir cannot bind from a tensor: "
                    f"{_unbindable_hint(name, info.type_name)}"
                )
            if tensor.dtype != torch.float32:
                raise TypeError(
                    f"params[{name!r}] has dtype {tensor.dtype}; the renderer computes in float32: "
                    f"pass tensor.float()"
                )
            if tensor.device.type != expected_device.type:
                raise ValueError(
                    f"params[{name!r}] is on {tensor.device}, but variant {backend.variant()!r} "
                    f"renders on {expected_device.type}: move it with .to({expected_device.type!r})"
                )
            if not _same_layout(tuple(tensor.shape), info.shape):
                if self.is_grid_volume_data(name):
                    _check_grid_shape(name, tuple(tensor.shape), info.shape)
                else:
                    hint = " (Mitsuba's (H, W, C) layout, not (C, H, W))" if len(info.shape) == 3 else ""
                    raise ValueError(
                        f"params[{name!r}] has shape {tuple(tensor.shape)}, expected {info.shape}{hint}"
                    )
            if tensor.requires_grad and not info.differentiable and self._detaches(name):
                raise ValueError(
                    f"parameter {name!r} is marked non-differentiable by Mitsuba (its integrators "
                    f"produce no derivative for it, e.g. point-light positions under prb): detach it, "
                    f"or optimise a differentiable parameterisation instead"
                )
            if not bool(torch.isfinite(tensor.detach()).all()):
                bad = int((~torch.isfinite(tensor.detach())).sum())
                raise ValueError(f"params[{name!r}] has {bad} NaN/Inf entries")
            if tensor.requires_grad and info.discontinuous and is_geometry_key(name):
                self._warn_discontinuous(name)

    def _detaches(self, name: str) -> bool:
        """Whether the integrator really gives parameter ``name`` (flagged non-differentiable by
        Mitsuba) no derivative: Mitsuba's Python path-replay integrators (prb, direct_projective,
        ...) detach it; the C++ integrators (direct, path) record it in their AD graph."""
        from mitsuba.python.ad.integrators.common import ADIntegrator

        return isinstance(self.integrator, ADIntegrator)

    def derive(self, target: str, to_target: Callable[..., torch.Tensor], inputs: Mapping[str, Any]) -> list[str]:
        """Declare torch-side parameters that together set the Mitsuba key ``target``.

        Args:
            target: the Mitsuba key they set (e.g. ``"bunny.vertex_positions"``).
            to_target: ``to_target(*values)`` -> the target's value (any shape with as many
                entries as the target), differentiable in torch; called with the inputs in order.
            inputs: ``{new name: load-time value}``; a value's shape is the parameter's shape.

        Returns:
            The new names, usable in ``render(..., params)`` and in ``model.parameters``. A render
            that gives some of them takes the load-time value for the others.

        Example:
            >>> ball = Scene.builtin("glossy_ball", resolution=16)   # a point light at "light.position"
            >>> ball.derive("light.position", lambda h: torch.cat([h.new_zeros(1), h, h.new_ones(1)]),
            ...             {"light.height": [2.0]})
            ['light.height']
        """
        self._require_name(target)
        if target in self.derived:
            raise ValueError(f"{target!r} is itself a derived parameter: derive from a Mitsuba key")
        info = self.info(target)
        if not info.bindable:
            raise TypeError(f"cannot derive {target!r} ({info.type_name}): {_unbindable_hint(target, info.type_name)}")
        taken = [d.name for d in self.derived.values() if d.target == target]
        if taken:
            raise ValueError(f"{target!r} is already set by the derived parameter(s) {taken}")
        if not inputs:
            raise ValueError("derive() needs at least one input")
        for name in inputs:
            if not isinstance(name, str) or not name:
                raise TypeError(f"derived parameter names are non-empty strings, got {name!r}")
            if name in self.params or name in self.derived:
                raise ValueError(f"derived parameter name {name!r} is already a parameter of the scene: choose another")
        device = backend.device()  # to_target meets the inputs there, as in expand_derived
        values = {n: torch.as_tensor(v, dtype=torch.float32, device=device).detach().clone() for n, v in inputs.items()}
        with torch.no_grad():
            result = torch.as_tensor(to_target(*values.values()), device=device)
        if result.numel() != math.prod(info.shape):
            raise ValueError(
                f"to_target gives {result.numel()} values for {target!r}, which has shape {info.shape} "
                f"({math.prod(info.shape)} values)"
            )
        if not bool(torch.isfinite(result).all()):
            raise ValueError(f"to_target gives NaN/Inf for {target!r} at the inputs' load-time values")
        loaded = self.get(target)
        if not torch.allclose(result.float().reshape(loaded.shape), loaded, rtol=1e-4, atol=1e-5):
            self.warn_once(
                f"derive:{target}",
                f"the load-time values of {list(values)} do not reproduce the loaded {target!r}: renders that "
                f"give them differ from the scene as loaded even where they are unchanged",
            )
        group = tuple(values)
        for name, value in values.items():
            self.derived[name] = DerivedParameter(
                name, target, tuple(value.shape), to_target, tuple(value.flatten().tolist()), inputs=group
            )
        return list(group)

    def expand_derived(self, values: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """``values`` with every derived parameter replaced by its Mitsuba target (in torch,
        differentiably); the targets are validated like any bound value."""
        if not any(name in self.derived for name in values):
            return dict(values)
        out = {n: t for n, t in values.items() if n not in self.derived}
        targets = {}
        for name in sorted(values.keys() & self.derived.keys()):
            d = self.derived[name]
            if d.target in values:
                raise ValueError(f"params gives both {name!r} and the parameter it sets, {d.target!r}: pass one")
            if d.target in targets:
                continue  # set already, by another input of the same group
            args = [values[n] if n in values else self.get(n) for n in d.group]
            targets[d.target] = d.to_target(*args).to(torch.float32).reshape(self.info(d.target).shape)
        self.check_values(targets)
        return {**out, **targets}

    def _warn_discontinuous(self, name: str) -> None:
        integrator = type(self.integrator).__name__
        if "Projective" not in integrator:
            self.warn_once(
                name,
                f"{name!r} moves visibility edges, but the scene's integrator ({integrator}) "
                f"differentiates only the interior term: gradients miss the boundary term. Use a "
                f"projective integrator (prb_projective, direct_projective) for shape/pose parameters.",
            )

    def verdict(self, key: Hashable, judge: Callable[[], Any]) -> Any:
        """``judge()``, computed on the first call with ``key`` and kept with this scene (a
        check of its contents that a fit does not change, e.g. whether a mesh's silhouettes are
        differentiable). Kept here, not by the objects' addresses: a freed scene's mesh left its
        address to a later scene's, which was then given the freed one's verdict."""
        if key not in self._verdicts:
            self._verdicts[key] = judge()
        return self._verdicts[key]

    def warn_once(self, key: str, message: str) -> None:
        """A ``UserWarning`` about this scene, issued once per ``key``."""
        if key not in self._warned:
            self._warned.add(key)
            warnings.warn(message, stacklevel=4)

    # ------------------------------------------------------------- binding (used by functions/)
    def to_drjit(self, name: str, tensor: Any) -> Any:
        """Convert a Dr.Jit tensor (from ``dr.wrap``) to parameter ``name``'s Mitsuba type.

        Differentiable: gradients flow back to ``tensor``.
        """
        value = self._base.get(name, self.params[name])
        if _is_transform(value):
            return type(value)(dr.unravel(mi.Matrix4f, tensor.array, order="C"))
        if dr.is_tensor_v(value):
            if tuple(tensor.shape) == tuple(value.shape):
                return tensor
            if len(tensor.shape) == 4 and self.is_grid_volume_data(name):  # a grid of another resolution
                return type(value)(tensor.array, tuple(tensor.shape))
            return type(value)(tensor.array, value.shape)
        if _is_flat_float(value):
            return tensor.array
        return dr.unravel(type(value), tensor.array)

    def bind(self, values: Mapping[str, Any], grad_names: frozenset[str] = frozenset(), owner: object = None) -> dict[str, Any]:
        """Make the scene exactly "loaded scene + ``values``" and update it.

        Parameters bound by an earlier call but absent from ``values`` go back to their loaded
        values. Each name in ``grad_names`` gets a fresh grad-enabled Dr.Jit variable (a fresh
        one, because Mitsuba does not refresh a scene for a variable that merely had its
        gradient re-enabled); those variables are returned, and ``owner`` is remembered as the
        op whose AD edges are live in the scene until :meth:`release` is called.

        Args:
            values: ``{name: Dr.Jit value}`` in the parameters' Mitsuba types (detached).
            grad_names: the names to differentiate.
            owner: an opaque token (the render op) for :meth:`owns_live_binding`.
        """
        for other in list(_SCENES_WITH_LIVE_GRADS):
            other.drop_live_grads()  # this scene's kernels would trace the others' grad-enabled data
        params = self.params
        moved = [name[: -len(".vertex_positions")] for name in values if name.endswith(".vertex_positions")]
        welds = self._welds(moved)  # before Mitsuba's first update recomputes the loaded normals
        restored = []  # meshes back at their loaded positions: their loaded normals too, after the update
        for name in self._overridden - values.keys():
            params[name] = self._base.pop(name)
            params.set_dirty(name)
            if name.endswith(".vertex_positions") and name in self._loaded_normals:
                restored.append(name[: -len(".vertex_positions")])
        fresh: dict[str, Any] = {}
        for name, value in values.items():
            if name not in self._base:
                # A new Python object: SceneParameters assigns into the existing one in place.
                self._base[name] = type(params[name])(params[name])
                normals = f"{name[: -len('.vertex_positions')]}.vertex_normals"
                if name.endswith(".vertex_positions") and normals in params and dr.width(params[normals]) > 0:
                    self._loaded_normals[name] = type(params[normals])(params[normals])
            value = type(value)(dr.detach(value))
            if name in grad_names:
                dr.enable_grad(value)
                fresh[name] = value
            params[name] = value
            params.set_dirty(name)
        params.update()
        normals = {f"{mesh.id()}.vertex_normals": group_normals(mesh, weld) for mesh, weld in welds}  # smooth across
        # uv seams, as the loaded mesh was (see torchir.welding.group_normals); a restored mesh: as loaded
        normals.update({f"{mesh}.vertex_normals": self._loaded_normals.pop(f"{mesh}.vertex_positions") for mesh in restored})
        for name, value in normals.items():
            params[name] = type(value)(value)
            params.set_dirty(name)
        if normals:
            params.update()
        self._overridden = set(values)
        self._owner = owner if fresh else None
        if fresh:
            _SCENES_WITH_LIVE_GRADS.add(self)
        return fresh

    def _welds(self, mesh_ids: list[str]) -> list:
        """``(mesh, MeshWeld)`` of the smooth-shaded meshes among ``mesh_ids`` whose normals
        Mitsuba would recompute with seams (their uv-seam copies share a normal group)."""
        if not mesh_ids:
            return []
        out = []
        for shape in self.mi_scene.shapes():
            if isinstance(shape, mi.Mesh) and shape.id() in mesh_ids and shape.has_vertex_normals():
                weld = self.mesh_weld(shape)  # its own mesh: the weld it was loaded with
                if weld.merges and f"{shape.id()}.vertex_normals" in self.params:
                    out.append((shape, weld))
        return out

    @property
    def bound_names(self) -> frozenset[str]:
        """Names of the parameters currently bound to non-loaded values."""
        return frozenset(self._overridden)

    def owns_live_binding(self, owner: object) -> bool:
        """Whether ``owner``'s grad-enabled values are bound with unused AD edges."""
        return owner is not None and self._owner is owner

    def release(self, owner: object) -> None:
        """Mark ``owner``'s AD edges as consumed (a backward traversal clears them)."""
        if self._owner is owner:
            self._owner = None

    def drop_live_grads(self) -> None:
        """Disable gradients, in place, on every grad-enabled value bound in the scene.

        Mitsuba's symbolic calls trace every registered shape of the process, not only this
        scene's: a mesh left with grad-enabled positions makes a later ``prbvolpath`` adjoint of
        *another* scene fail to compile and abort the process. A render op whose binding is
        dropped re-binds at its backward (see :meth:`owns_live_binding`). No ``params.update()``
        is needed: the values stay, only their AD edges go. Only the bound values themselves:
        Mitsuba takes a value changed in place (normals derived from the positions) for the
        user's own, and would stop recomputing it from the positions at the next update.
        """
        self._owner = None
        _SCENES_WITH_LIVE_GRADS.discard(self)
        for name in self._overridden & set(self.params.keys()):
            value = self.params[name]
            if dr.is_diff_v(value) and dr.grad_enabled(value):
                dr.disable_grad(value)


# Scenes whose bound values are grad-enabled (see Scene.drop_live_grads); weak, so a scene that
# goes away leaves the set by itself.
_SCENES_WITH_LIVE_GRADS: "weakref.WeakSet[Scene]" = weakref.WeakSet()


def _check_grid_shape(name: str, got: tuple[int, ...], loaded: tuple[int, ...]) -> None:
    """Refuse a grid-volume value that is not ``(Z, Y, X, C)`` with positive sizes and the loaded ``C``."""
    channels = loaded[-1]
    if len(got) != 4 or got[-1] != channels or min(got) < 1:
        raise ValueError(
            f"params[{name!r}] has shape {got}, expected (Z, Y, X, {channels}): a gridvolume's data binds at any "
            f"positive resolution (Z, Y, X) with the {channels} channel(s) it was loaded with (loaded as {loaded}, "
            f"Mitsuba's (Z, Y, X, C) layout)"
        )
