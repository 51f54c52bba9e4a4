"""``oxalis_lite``: a textured canvas under two bright spot lights and many useless lights.

For: ReSTIR: a small version of the "Oxalis" scene of Wang et al. 2023 (Fig. 1), a benchmark
scene of ``torchir.bench.restir``; two spot lights, as the paper's text says (its Fig. 1
caption says "several").
Light transport: direct illumination only (``prb`` with ``max_depth=2``; ReSTIR renders the
same light transport through ``render(..., sampler=ReSTIRSampler(scene))``). A diffuse canvas
with a ``texture x texture`` albedo is lit by two bright, narrow spot lights and
``dim_lights`` dim point lights; a leaf-shaped occluder casts a shadow, and
``hidden_lights`` bright point lights sit behind the canvas and an occluding wall: they take
light samples but contribute nothing, which is what makes light selection hard.
``emitter_pdf="power"`` sets every emitter's ``sampling_weight`` to its power (our reading of
the paper's light-candidate pdf proportional to emitted radiance), so the hidden lights take
most samples; ``"uniform"`` samples every emitter equally.
Typical unknown: the albedo texture ``canvas.bsdf.reflectance.data`` of shape (T, T, 3).
"""
from __future__ import annotations

import math
from typing import Any

import mitsuba as mi
import numpy as np

from ._common import bitmap, painting_texture, perspective, resolution_hw

DESCRIPTION = "textured canvas, 2 bright spots + many dim and hidden lights, a leaf shadow; direct illumination (prb, max_depth 2); recover the albedo texture"
PARAMETERS = ("canvas.bsdf.reflectance.data",)


def _lum(rgb) -> float:
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]


def build(
    resolution: int | tuple[int, int] | None = None,
    texture: int = 32,
    dim_lights: int = 8,
    hidden_lights: int = 16,
    emitter_pdf: str = "uniform",
    views: int = 1,
) -> dict[str, Any]:
    """Mitsuba dict of the scene at ``resolution`` (default 64x64).

    Args:
        texture: side of the albedo texture.
        dim_lights: dim point lights in front of the canvas (total intensity about 1).
        hidden_lights: bright point lights behind the canvas (no contribution).
        emitter_pdf: ``"uniform"`` or ``"power"`` emitter selection (``sampling_weight``).
        views: cameras; more than 1 puts them on a 70-degree arc 3 units from the canvas
            (``view00``, ``view01``, ...; multi-view ReSTIR, DDP).
    """
    if emitter_pdf not in ("uniform", "power"):
        raise ValueError(f"emitter_pdf must be 'uniform' or 'power', got {emitter_pdf!r}")
    if texture < 1 or dim_lights < 0 or hidden_lights < 0:
        raise ValueError("texture must be >= 1 and the light counts >= 0")
    if isinstance(views, bool) or not isinstance(views, int) or views < 1:
        raise ValueError(f"views must be an int >= 1, got {views!r}")
    h, w = resolution_hw(resolution, 64)
    T = mi.ScalarTransform4f
    spots = {
        "spot_left": ([-1.2, 0.8, 2.0], [-0.4, 0.3, 0], [40.0, 38.0, 34.0], 12.0),
        "spot_right": ([1.3, -0.6, 2.0], [0.45, -0.35, 0], [32.0, 36.0, 40.0], 12.0),
    }
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 40.0, h, w),
        "canvas": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))}},
        "leaf": {
            "type": "rectangle",
            "to_world": T().translate([-0.75, 0.55, 0.9]).rotate([0, 0, 1], 30).scale([0.12, 0.25, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1, 0.3, 0.1]}},
        },
        "wall": {
            "type": "rectangle",
            "to_world": T().translate([0, 0, -0.5]).scale([3.0, 3.0, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        },
    }
    for name, (origin, target, intensity, cutoff) in spots.items():
        scene[name] = {
            "type": "spot",
            "to_world": T().look_at(origin=origin, target=target, up=[0, 1, 0]),
            "intensity": {"type": "rgb", "value": intensity},
            "cutoff_angle": cutoff,
            "beam_width": cutoff * 0.7,
        }
        if emitter_pdf == "power":
            scene[name]["sampling_weight"] = 2 * math.pi * (1 - math.cos(math.radians(cutoff))) * _lum(intensity)
    lights = []
    for i in range(dim_lights):
        a = 2 * np.pi * (i + 0.5) / max(dim_lights, 1)
        lights.append((f"dim_{i:02d}", [1.8 * np.cos(a), 1.8 * np.sin(a), 2.2], [1.0 / max(dim_lights, 1)] * 3))
    for i in range(hidden_lights):
        a = 2 * np.pi * i / max(hidden_lights, 1)
        lights.append((f"hidden_{i:02d}", [1.5 * np.cos(a), 1.5 * np.sin(a), -1.0], [200.0] * 3))
    for name, position, intensity in lights:
        scene[name] = {"type": "point", "position": [float(v) for v in position], "intensity": {"type": "rgb", "value": intensity}}
        if emitter_pdf == "power":
            scene[name]["sampling_weight"] = 4 * math.pi * _lum(intensity)
    if views > 1:
        del scene["sensor"]
        for v in range(views):
            a = math.radians(-35 + 70 * v / (views - 1))
            origin = [3.0 * math.sin(a), 0.4 * math.cos(3 * a), 3.0 * math.cos(a)]
            scene[f"view{v:02d}"] = perspective(origin, [0, 0, 0], [0, 1, 0], 40.0, h, w)
    return scene
