"""``glossy_ball``: a glossy sphere on a floor, lit by one movable point light.

For: the locally orderless images (LOI) loss: the light's position moves the highlight in
image space, the case where pixel-wise losses give no useful gradient.
Light transport: direct illumination only (``prb``, ``max_depth=2``): the highlight and the
shadow are first-hit effects. A dim constant environment keeps the unlit side visible.
The light is placed by the ``azimuth`` option. Differentiable unknowns: ``ball.bsdf.alpha``
(roughness, shape (1,)) and ``ball.bsdf.diffuse_reflectance.value`` (3,). Mitsuba 3.9 gives no
derivative for a point light's ``position`` under ``prb`` (it samples the light detached), so
torchir rejects ``light.position`` with requires_grad here; to recover a light, use the
``glossy_highlight`` scene (C++ ``direct`` integrator, derived parameter ``light.azimuth``).
"""
from __future__ import annotations

import math
from typing import Any

import mitsuba as mi

from ._common import perspective, resolution_hw

DESCRIPTION = "glossy sphere + point light placed by azimuth; direct illumination (prb, max_depth 2); recover roughness/colour"
PARAMETERS = ("ball.bsdf.alpha", "ball.bsdf.diffuse_reflectance.value")


def light_position(azimuth_deg: float, elevation_deg: float = 45.0, distance: float = 3.0) -> list[float]:
    """World position of the light at the given azimuth/elevation around the ball's centre."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return [distance * math.cos(e) * math.sin(a), distance * math.sin(e), distance * math.cos(e) * math.cos(a)]


def build(resolution: int | tuple[int, int] | None = None, azimuth: float = 30.0, roughness: float = 0.08) -> dict[str, Any]:
    """Mitsuba dict of the glossy ball at ``resolution`` (default 32x32), light at ``azimuth``."""
    h, w = resolution_hw(resolution, 32)
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0, 1.2, 4.0], [0, 0.1, 0], [0, 1, 0], 35.0, h, w),
        "ball": {
            "type": "sphere",
            "center": [0, 0.5, 0],
            "radius": 0.5,
            "bsdf": {
                "type": "roughplastic",
                "distribution": "ggx",
                "alpha": roughness,
                "diffuse_reflectance": {"type": "rgb", "value": [0.15, 0.2, 0.5]},
            },
        },
        "floor": {
            "type": "rectangle",
            "to_world": T().rotate([1, 0, 0], -90).scale(3.0),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}},
        },
        "light": {"type": "point", "position": light_position(azimuth), "intensity": {"type": "rgb", "value": 20.0}},
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": 0.05}},
    }
