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
