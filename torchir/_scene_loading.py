"""Helpers of scene loading: texture storage, the file resolver's folder, float bitmaps, and the
override of a scene file's integrator."""
from __future__ import annotations

import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import mitsuba as mi

__all__: list[str] = []

TextureStorage = Literal["float", "file"]


def _check_texture_storage(texture_storage: str) -> None:
    if texture_storage not in ("float", "file"):
        raise ValueError(f"texture_storage must be 'float' or 'file', got {texture_storage!r}")


@contextlib.contextmanager
def _resolving_from(folder: Path):
    """Mitsuba's file resolver looks in ``folder`` first for the duration."""
    saved = mi.FileResolver(mi.file_resolver())
    mi.file_resolver().prepend(str(folder.resolve()))
    try:
        yield
    finally:
        mi.Thread.thread().set_file_resolver(saved)


def _float_bitmaps(node: Any) -> Any:
    """A copy of a scene dict in which every file-backed ``bitmap`` texture without a ``format``
    stores float32 (``format: "variant"``)."""
    if not isinstance(node, Mapping):
        return node
    out = {k: _float_bitmaps(v) for k, v in node.items()}
    if out.get("type") == "bitmap" and "filename" in out and "format" not in out:
        out["format"] = "variant"
    return out


def _integrator_spec(spec: Mapping[str, Any]) -> dict[str, Any]:
    """A validated ``{type: name, **properties}`` integrator override."""
    if not isinstance(spec, Mapping) or not isinstance(spec.get("type"), str):
        raise ValueError(f"an integrator override is {{type: name, ...properties}}, e.g. {{type: prb, max_depth: 3}}; got {spec!r}")
    return dict(spec)


def _override_integrator(state: Any, spec: dict[str, Any], path: Path) -> None:
    """Replace the parsed scene's integrator node by ``spec`` (plugin name and properties)."""
    nodes = [n for n in state.nodes if n.type == mi.ObjectType.Integrator]
    if not nodes:
        raise ValueError(f"{str(path)!r} has no <integrator> to override: add one to the file")
    props = nodes[0].props
    props.set_plugin_name(spec["type"])
    for key in list(props.keys()):
        props.remove_property(key)
    for key, value in spec.items():
        if key != "type":
            props[key] = value


RIG_KEY = "torchir_sensor_{}"  # the scene-dict / root-property names of the sensors given as ``sensors=``


def _check_sensors(sensors: Any) -> list[Any]:
    """``sensors=`` of the scene loaders as a non-empty list of sensor dicts or ``mi.Sensor`` objects."""
    if isinstance(sensors, (Mapping, mi.Object)) or not isinstance(sensors, (list, tuple)) or not sensors:
        raise TypeError(f"sensors must be a non-empty list of Mitsuba sensor dicts or mi.Sensor objects "
                        f"(e.g. torchir.rigs.fibonacci(...)), got {type(sensors).__name__}")
    for k, sensor in enumerate(sensors):
        if isinstance(sensor, mi.Sensor):
            continue
        kind = sensor.get("type") if isinstance(sensor, Mapping) else None
        if not isinstance(kind, str) or mi.PluginManager.instance().plugin_type(kind) != mi.ObjectType.Sensor:
            raise TypeError(f"sensors[{k}] is not a Mitsuba sensor dict ({{'type': 'perspective', ...}}) or an mi.Sensor: got {sensor!r:.200}")
    return list(sensors)


def _is_sensor_entry(value: Any) -> bool:
    if isinstance(value, mi.Sensor):
        return True
    kind = value.get("type") if isinstance(value, Mapping) else None
    return isinstance(kind, str) and mi.PluginManager.instance().plugin_type(kind) == mi.ObjectType.Sensor


def _replace_dict_sensors(scene_dict: Mapping[str, Any], sensors: list[Any]) -> dict[str, Any]:
    """A copy of ``scene_dict`` whose top-level sensors are ``sensors`` (in their order)."""
    out = {k: v for k, v in scene_dict.items() if not _is_sensor_entry(v)}
    for k, sensor in enumerate(sensors):
        key = RIG_KEY.format(k)
        if key in out:
            raise ValueError(f"the scene dict has an entry {key!r}, the name torchir gives the sensors of sensors=: rename it")
        out[key] = sensor
    return out


def _replace_parsed_sensors(state: Any, sensors: list[Any]) -> None:
    """Replace the sensors of a parsed scene file (``mi.parser`` state) by ``sensors``."""
    root = state.root.props
    for key in list(root.keys()):
        if root.type(key) == mi.Properties.Type.ResolvedReference and state.nodes[root[key].index()].type == mi.ObjectType.Sensor:
            del root[key]
    for k, sensor in enumerate(sensors):
        root[RIG_KEY.format(k)] = sensor if isinstance(sensor, mi.Sensor) else mi.load_dict(dict(sensor))
