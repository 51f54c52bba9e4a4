"""``glossy_highlight``: a shiny metal sphere whose only visible feature is a point light's highlight.

For: the locally orderless images (LOI) loss and its benchmark ``torchir.bench.loi`` (an analogue
of the "Envlight" scene and Fig. 1 of Mehta et al. 2025, "Locally Orderless Images for
Optimization in Differentiable Rendering"): recover the light's azimuth from where the
highlight sits. The highlight is a few pixels wide and moves across the sphere with the
azimuth, so a pixel-wise loss sees no gradient once rendered and reference highlights stop
overlapping.
Geometry: a unit sphere (``roughconductor``, aluminium, GGX alpha 0.08) and nothing else; a
``point`` light on a circle of radius 4 around it at elevation 0.35 rad; the camera looks at
the sphere from +z, so azimuth 0 puts the highlight just above the centre.
Light transport: direct illumination with Mitsuba's C++ ``direct`` integrator: Mitsuba's
Python ``prb``/``direct_projective`` sample lights detached and give a point light's
``position`` no derivative; the C++ integrators differentiate it (checked against finite
differences in ``tests/core/test_scene_derived.py``). A sphere lit by a point light has no moving
visibility edge (the terminator is smooth), so no projective term is missing.
Differentiable unknown: the derived parameter ``light.azimuth`` (shape (1,), radians), which
the render functions expand to ``light.position`` in torch; ``light.position`` itself works too.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from ._common import perspective, resolution_hw

DESCRIPTION = "glossy metal sphere + point light on a circle; direct illumination (C++ direct, = max_depth 2); recover the light azimuth"
PARAMETERS = ("light.azimuth",)

RADIUS = 4.0  # distance of the light from the sphere's centre
ELEVATION = 0.35  # radians above the equator


def light_position(azimuth: torch.Tensor) -> torch.Tensor:
    """``(3,)`` world position of the light at ``azimuth`` (radians, shape (1,)); differentiable."""
    a = azimuth.reshape(())
    c = RADIUS * math.cos(ELEVATION)
    return torch.stack([c * torch.sin(a), (RADIUS * math.sin(ELEVATION)) + 0 * a, c * torch.cos(a)])


def build(resolution: int | tuple[int, int] | None = None, azimuth: float = 0.0, roughness: float = 0.08, intensity: float = 60.0) -> dict[str, Any]:
    """Mitsuba dict at ``resolution`` (default 32x32), light at ``azimuth`` radians.

    The dict carries the derived parameter under ``"torchir_derived"`` as ``(target,
    to_target, {name: load-time value})``, declared with :meth:`torchir.Scene.derive` by
    :meth:`torchir.Scene.builtin` (which takes it out before Mitsuba sees the dict)."""
    h, w = resolution_hw(resolution, 32)
    position = light_position(torch.tensor([float(azimuth)], dtype=torch.float64, device="cpu")).tolist()
    return {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1},
        "sensor": perspective([0, 0, 5.0], [0, 0, 0], [0, 1, 0], 30.0, h, w),
        "ball": {
            "type": "sphere",
            "center": [0, 0, 0],
            "radius": 1.0,
            "bsdf": {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": roughness},
        },
        "light": {"type": "point", "position": position, "intensity": {"type": "rgb", "value": intensity}},
        "torchir_derived": [
            ("light.position", light_position, {"light.azimuth": [float(azimuth)]}),
        ],
    }
