"""``painting``: a textured canvas lit by many lights, most of them useless.

For: ReSTIR (many-light direct illumination) and the target-aware denoiser.
Light transport: direct illumination only (``prb`` with ``max_depth=2``: emitter sampling and
BSDF sampling at the first hit, no indirect bounce). The canvas is diffuse with a
``texture x texture`` albedo. Two bright, narrow spot lights light two regions, a dim point
light fills the rest, and ``hidden_lights`` bright point lights sit behind an occluding wall:
they take emitter samples but contribute nothing, which is what makes light selection hard.
Typical unknown: the albedo texture ``canvas.bsdf.reflectance.data`` of shape (T, T, 3).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import bitmap, painting_texture, perspective, resolution_hw

DESCRIPTION = "textured canvas, 2 spots + dim fill + hidden lights; direct illumination (prb, max_depth 2); recover the albedo texture"
PARAMETERS = ("canvas.bsdf.reflectance.data",)


def build(
    resolution: int | tuple[int, int] | None = None, texture: int = 32, hidden_lights: int = 16
) -> dict[str, Any]:
    """Mitsuba dict of the canvas scene at ``resolution`` (default 32x32)."""
    h, w = resolution_hw(resolution, 32)
    T = mi.ScalarTransform4f
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 40.0, h, w),
        "canvas": {
            "type": "rectangle",
            "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))},
        },
        "spot_left": {
            "type": "spot",
            "to_world": T().look_at(origin=[-1.2, 0.8, 2.0], target=[-0.4, 0.3, 0], up=[0, 1, 0]),
            "intensity": {"type": "rgb", "value": [40.0, 38.0, 34.0]},
            "cutoff_angle": 14.0,
            "beam_width": 10.0,
        },
        "spot_right": {
            "type": "spot",
            "to_world": T().look_at(origin=[1.3, -0.6, 2.0], target=[0.45, -0.35, 0], up=[0, 1, 0]),
            "intensity": {"type": "rgb", "value": [32.0, 36.0, 40.0]},
            "cutoff_angle": 12.0,
            "beam_width": 8.0,
        },
        "fill": {"type": "point", "position": [0.0, 0.2, 2.5], "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
        "wall": {
            "type": "rectangle",
            "to_world": T().translate([0, 0, -0.5]).scale([3.0, 3.0, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        },
    }
    for i in range(hidden_lights):
        angle = 2 * np.pi * i / max(hidden_lights, 1)
        scene[f"hidden_{i:02d}"] = {
            "type": "point",
            "position": [1.5 * np.cos(angle), 1.5 * np.sin(angle), -1.0],
            "intensity": {"type": "rgb", "value": [200.0, 200.0, 200.0]},
        }
    return scene
