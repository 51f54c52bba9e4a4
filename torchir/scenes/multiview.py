"""``multiview``: a textured sphere seen by several cameras around it.

For: multi-view optimisation (views as batches, DDP scale-out, global pixel sampling).
Light transport: direct illumination only (``prb``, ``max_depth=2``) from a directional
"sun" and a dim constant environment. All sensors share one film size.
Typical unknown: the sphere's albedo texture ``object.bsdf.reflectance.data`` (T, T, 3).
"""
from __future__ import annotations

import math
from typing import Any


from ._common import bitmap, painting_texture, perspective, resolution_hw

DESCRIPTION = "textured sphere seen by 4 sensors; direct illumination (prb, max_depth 2); recover the texture from all views"
PARAMETERS = ("object.bsdf.reflectance.data",)


def build(resolution: int | tuple[int, int] | None = None, views: int = 4, texture: int = 32) -> dict[str, Any]:
    """Mitsuba dict of the multi-view scene: ``views`` sensors evenly spaced in azimuth."""
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    h, w = resolution_hw(resolution, 32)
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "object": {
            "type": "sphere",
            "radius": 0.8,
            "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))},
        },
        "sun": {"type": "directional", "direction": [-0.4, -0.6, -0.7], "irradiance": {"type": "rgb", "value": 3.0}},
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": 0.15}},
    }
    for v in range(views):
        a = 2 * math.pi * v / views
        origin = [3.0 * math.sin(a), 0.8, 3.0 * math.cos(a)]
        scene[f"sensor{v}"] = perspective(origin, [0, 0, 0], [0, 1, 0], 38.0, h, w)
    return scene
