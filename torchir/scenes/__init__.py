"""Built-in procedural scenes: no downloads, tiny by default, one module each.

Every scene documents what it is for and which integrator and depth its light transport needs
(model only what a scene requires: direct illumination where that suffices), and uses a box
reconstruction filter so pixel-subset renders define the same pixels as full renders.

Example:
    >>> import torchir
    >>> sorted(torchir.scenes.available())
    ['ajar_painting', 'cbox', 'glossy_ball', 'glossy_highlight', 'many_lights', 'multiview', 'occluded_lights', 'oxalis_lite', 'painting', 'pig', 'textured_wall']
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from . import (
    ajar_painting,
    cbox,
    glossy_ball,
    glossy_highlight,
    many_lights,
    multiview,
    occluded_lights,
    oxalis_lite,
    painting,
    pig,
    textured_wall,
)

__all__ = ["available", "get", "BuiltinScene"]


@dataclass(frozen=True)
class BuiltinScene:
    name: str
    description: str  # one line: what it is for, integrator and depth
    build: Callable[..., dict[str, Any]]  # (resolution=None, **options) -> Mitsuba scene dict
    parameters: tuple[str, ...]  # the keys its typical optimisation recovers


_REGISTRY = {
    entry.name: entry
    for entry in (
        BuiltinScene("cbox", cbox.DESCRIPTION, cbox.build, cbox.PARAMETERS),
        BuiltinScene("painting", painting.DESCRIPTION, painting.build, painting.PARAMETERS),
        BuiltinScene("glossy_ball", glossy_ball.DESCRIPTION, glossy_ball.build, glossy_ball.PARAMETERS),
        BuiltinScene("multiview", multiview.DESCRIPTION, multiview.build, multiview.PARAMETERS),
        BuiltinScene("textured_wall", textured_wall.DESCRIPTION, textured_wall.build, textured_wall.PARAMETERS),
        BuiltinScene("glossy_highlight", glossy_highlight.DESCRIPTION, glossy_highlight.build, glossy_highlight.PARAMETERS),
        BuiltinScene("oxalis_lite", oxalis_lite.DESCRIPTION, oxalis_lite.build, oxalis_lite.PARAMETERS),
        BuiltinScene("ajar_painting", ajar_painting.DESCRIPTION, ajar_painting.build, ajar_painting.PARAMETERS),
        BuiltinScene("occluded_lights", occluded_lights.DESCRIPTION, occluded_lights.build, occluded_lights.PARAMETERS),
        BuiltinScene("many_lights", many_lights.DESCRIPTION, many_lights.build, many_lights.PARAMETERS),
        BuiltinScene("pig", pig.DESCRIPTION, pig.build, pig.PARAMETERS),
    )
}


def available() -> dict[str, str]:
    """``{name: one-line description}`` of the built-in scenes."""
    return {name: entry.description for name, entry in _REGISTRY.items()}


def get(name: str) -> BuiltinScene:
    """The registry entry of built-in scene ``name`` (``KeyError`` naming the choices)."""
    if name not in _REGISTRY:
        import difflib

        close = difflib.get_close_matches(name, list(_REGISTRY), n=1)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        raise KeyError(f"unknown built-in scene {name!r}.{hint} Available: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]
