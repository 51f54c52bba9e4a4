"""What a run's config names, built: its scene (built-in, XML file or Python factory), loss,
denoiser and sampler, its parameters' settings; and the sampler state's checkpoint form."""
from __future__ import annotations

from typing import Any, Optional, Union

import torch
from torch import nn

from .. import Scene
from .parameters import ParameterConfig

__all__: list[str] = []


def _load_scene(scene: str, resolution, scene_options: dict[str, Any], integrator: Optional[dict[str, Any]],
                sensors: Optional[dict[str, Any]] = None) -> Scene:
    """The run's scene; ``sensors`` (``model.sensors``, a :func:`torchir.rigs.from_spec` mapping)
    replaces its sensors, with ``resolution`` (``model.resolution``) as the rig's film size."""
    rig = None
    if sensors is not None:
        from ..rigs import from_spec

        rig = from_spec(sensors, resolution)
    if scene.endswith(".xml"):
        if resolution is not None and rig is None:
            raise ValueError("resolution applies to built-in scenes and to model.sensors; set the film size in the XML file instead")
        return Scene.from_file(scene, override_integrator=integrator, **_rig(rig), **scene_options)
    if ":" in scene:  # a Python factory, as Mitsuba's tutorials build scenes: "file.py:fn" or "module:fn"
        return _scene_from_factory(scene, resolution, scene_options, integrator, rig)
    return Scene.builtin(scene, resolution=resolution, override_integrator=integrator, **_rig(rig), **scene_options)


def _rig(rig: Optional[list[Any]]) -> dict[str, Any]:
    """The loaders' ``sensors=`` argument, only where a rig replaces the scene's sensors."""
    return {} if rig is None else {"sensors": rig}


def _scene_from_factory(spec: str, resolution, scene_options: dict[str, Any], integrator: Optional[dict[str, Any]],
                        sensors: Optional[list[Any]] = None) -> Scene:
    """``factory(**scene_options)`` (plus ``resolution=`` when given) -> a Mitsuba scene dict."""
    from ..derived import load_callable

    factory = load_callable(spec)
    if not callable(factory):
        raise TypeError(f"model.scene {spec!r} is not callable")
    kwargs = dict(scene_options)
    if resolution is not None:
        kwargs["resolution"] = resolution
    try:
        scene_dict = factory(**kwargs)
    except TypeError as error:
        raise TypeError(f"model.scene {spec!r} could not be called with {sorted(kwargs)} (scene_options"
                        f"{' and resolution' if resolution is not None else ''}): {error}") from None
    if not isinstance(scene_dict, dict) or scene_dict.get("type") != "scene":
        raise ValueError(f"model.scene {spec!r} must return a Mitsuba scene dict ({{'type': 'scene', ...}}), "
                         f"got {type(scene_dict).__name__}")
    return Scene.from_dict(scene_dict, override_integrator=integrator, sensors=sensors)


def _as_config(key: str, config: Any) -> ParameterConfig:
    if isinstance(config, ParameterConfig):
        return config
    if config is None:
        return ParameterConfig()
    if isinstance(config, dict):
        unknown = set(config) - set(ParameterConfig.__dataclass_fields__)
        if unknown:
            raise ValueError(f"parameters[{key!r}] has unknown field(s) {sorted(unknown)}; allowed: {sorted(ParameterConfig.__dataclass_fields__)}")
        return ParameterConfig(**config)
    raise TypeError(f"parameters[{key!r}] must be a mapping of ParameterConfig fields, got {type(config).__name__}")


def _to_checkpoint(state: Any) -> Any:
    """Sampler state with numpy arrays and scalars as torch tensors and Python numbers, so that
    ``torch.load(weights_only=True)`` (Lightning's default on resume) accepts the checkpoint."""
    import numpy as np

    if isinstance(state, np.ndarray):
        return {"__ndarray__": torch.from_numpy(np.ascontiguousarray(state).copy())}
    if isinstance(state, np.generic):
        return state.item()
    if isinstance(state, dict):
        return {k: _to_checkpoint(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_to_checkpoint(v) for v in state)
    return state


def _from_checkpoint(state: Any) -> Any:
    if isinstance(state, dict):
        if set(state) == {"__ndarray__"}:
            return state["__ndarray__"].cpu().numpy()
        return {k: _from_checkpoint(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_from_checkpoint(v) for v in state)
    return state


def _registered(section: str, spec: Any, registry: dict[str, type], *args: Any) -> Any:
    """Build ``registry[spec["type"]](*args, **options)`` from a ``{type: name, **options}`` mapping."""
    spec = dict(spec)
    name = spec.pop("type", None)
    if name not in registry:
        raise ValueError(f"model.{section}.type must be one of {sorted(registry)}, got {name!r}")
    try:
        return registry[name](*args, **spec)
    except TypeError as error:
        raise ValueError(f"model.{section} ({name}): {error}") from error


def _resolve_loss(loss: Union[str, nn.Module, dict[str, Any]]) -> nn.Module:
    from ..modules import LOSSES

    if isinstance(loss, nn.Module):
        return loss
    if isinstance(loss, str) and loss in LOSSES:
        return LOSSES[loss]()
    if isinstance(loss, dict):
        return _registered("loss", loss, LOSSES)
    raise ValueError(f"model.loss must be one of {sorted(LOSSES)}, {{type: name, ...options}} or an nn.Module class path, got {loss!r}")


def _resolve_denoiser(denoiser: Optional[Union[nn.Module, dict[str, Any]]]) -> Optional[nn.Module]:
    from ..modules import DENOISERS

    if denoiser is None or isinstance(denoiser, nn.Module):
        return denoiser
    if isinstance(denoiser, dict):
        if denoiser.get("type") in (None, "none"):
            return None
        return _registered("denoiser", denoiser, DENOISERS)
    raise ValueError(f"model.denoiser must be {{type: name, ...options}} or an nn.Module class path, got {denoiser!r}")


def _resolve_sampler(sampler: Optional[dict[str, Any]], scene: Scene) -> Any:
    from ..samplers import SAMPLERS

    if sampler is None:
        return None
    if not isinstance(sampler, dict):
        raise ValueError(f"model.sampler must be a mapping {{type: name, ...options}}, got {sampler!r}")
    if sampler.get("type") == "none":
        return None
    return _registered("sampler", sampler, SAMPLERS, scene)
