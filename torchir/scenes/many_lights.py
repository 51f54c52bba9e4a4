"""``many_lights``: a textured canvas lit by hundreds of point lights through a few ceiling holes.

For: ReSTIR (Wang et al. 2023, many-light direct illumination; a benchmark scene of
``torchir.bench.restir``): light selection is hard because almost every light sample is
occluded. The camera looks straight down at a diffuse canvas with a ``texture x texture``
albedo. ``lights`` point lights of random intensity are scattered above an occluding ceiling (a
12 x 12 grid of 0.5 x 0.5 tiles at height 2, above the camera, out of its view) from which
``holes`` tiles are missing; a canvas point sees a light only through a hole, about 10 % of the
lights with the defaults, and every light reaches only part of the canvas, so the canvas is lit
by a soft patchwork of light.
Light transport: direct illumination only (``prb`` with ``max_depth=2``; ReSTIR renders the
same light transport through ``render(..., sampler=ReSTIRSampler(scene))``).
Typical unknown: the albedo texture ``canvas.bsdf.reflectance.data`` of shape (T, T, 3).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import bitmap, painting_texture, perspective, resolution_hw

DESCRIPTION = "textured canvas under hundreds of point lights seen through a few ceiling holes; direct illumination (prb, max_depth 2); recover the albedo texture"
PARAMETERS = ("canvas.bsdf.reflectance.data",)

_GRID, _TILE, _CEILING = 12, 0.5, 2.0  # ceiling: _GRID x _GRID tiles of side _TILE at z = _CEILING


def hole_tiles(holes: int, seed: int = 3) -> list[tuple[int, int]]:
    """The ``(row, column)`` of the missing ceiling tiles: random, in the central 8 x 8 tiles."""
    rng = np.random.default_rng(seed)
    centre = [(i, j) for i in range(2, _GRID - 2) for j in range(2, _GRID - 2)]
    picks = rng.choice(len(centre), size=min(holes, len(centre)), replace=False)
    return sorted(centre[k] for k in picks)


def build(
    resolution: int | tuple[int, int] | None = None,
    texture: int = 8,
    lights: int = 256,
    holes: int = 6,
    seed: int = 3,
) -> dict[str, Any]:
    """Mitsuba dict of the scene at ``resolution`` (default 128x128).

    Args:
        texture: side of the canvas's albedo texture (8: texels 16 pixels wide at 128²).
        lights: number of point lights (ids ``light_000`` ...), at heights 2.3-3.0 over
            [-2.5, 2.5]^2, intensities uniform in [0.5, 1.5] times a common scale.
        holes: missing ceiling tiles (0: the canvas is dark).
        seed: the random layout of the lights and the holes.
    """
    if texture < 1 or lights < 1 or holes < 0:
        raise ValueError("texture and lights must be >= 1, holes >= 0")
    h, w = resolution_hw(resolution, 128)
    T = mi.ScalarTransform4f
    dark = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.1}}
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        # straight down from z = 1.6 (below the ceiling): the view covers the canvas's [-1, 1]^2
        "sensor": perspective([0, 0, 1.6], [0, 0, 0], [0, 1, 0], 64.0, h, w),
        "canvas": {
            "type": "rectangle",
            "to_world": T().scale([1.1, 1.1, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))},
        },
    }
    # The ceiling: each row of tiles merged into runs of solid tiles (one rectangle per run,
    # 1e-3 larger on every side so that neighbouring rectangles overlap: no cracks).
    missing = set(hole_tiles(holes, seed))
    half = _GRID * _TILE / 2
    runs = 0
    for i in range(_GRID):
        j = 0
        while j < _GRID:
            if (i, j) in missing:
                j += 1
                continue
            k = j
            while k < _GRID and (i, k) not in missing:
                k += 1
            x0, x1 = -half + j * _TILE, -half + k * _TILE
            y0 = -half + i * _TILE
            scene[f"ceiling_{runs:02d}"] = {
                "type": "rectangle",
                "to_world": T().translate([0.5 * (x0 + x1), y0 + 0.5 * _TILE, _CEILING]).scale([0.5 * (x1 - x0) + 1e-3, 0.5 * _TILE + 1e-3, 1.0]),
                "bsdf": dark,
            }
            runs += 1
            j = k
    rng = np.random.default_rng(seed + 1000)
    pos = np.column_stack([rng.uniform(-2.5, 2.5, (lights, 2)), rng.uniform(2.3, 3.0, lights)])
    power = rng.uniform(0.5, 1.5, lights) * (6.0 / holes if holes else 1.0) * (256.0 / lights)
    for n in range(lights):
        scene[f"light_{n:03d}"] = {
            "type": "point",
            "position": [float(v) for v in pos[n]],
            "intensity": {"type": "rgb", "value": float(power[n])},
        }
    return scene
