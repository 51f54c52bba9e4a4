"""``cbox``: the Cornell box with global illumination.

For: the foundation's gradient tests, the adaptive pixel sampler and the overhead benchmark.
Light transport: path tracing with ``prb`` (path replay backpropagation); colour bleeding
between the walls needs indirect light, so ``max_depth=4`` (three bounces after the camera ray;
the fourth and later bounces carry under 3% of the image at these albedos).
Typical unknowns: the wall albedos ``red.reflectance.value``, ``green.reflectance.value``.
Option ``canvas=n`` (n > 0) hangs a 0.6 x 0.6 canvas with an n x n bilinear albedo texture
(``canvas.bsdf.reflectance.data``, uniform random in [0.05, 0.95], seed ``canvas_seed``) on the
back wall: a small textured region (~3% of the image), the adaptive sampler's benchmark scene
(``torchir.bench.adaptive``).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import bitmap, film, resolution_hw

DESCRIPTION = "Cornell box; path tracing (prb, max_depth 4); recover wall albedos"
PARAMETERS = ("red.reflectance.value", "green.reflectance.value")


def build(resolution: int | tuple[int, int] | None = None, max_depth: int = 4, canvas: int = 0, canvas_seed: int = 7) -> dict[str, Any]:
    """Mitsuba dict of the Cornell box at ``resolution`` (default 32x32), optionally with a
    ``canvas`` x ``canvas`` textured canvas on the back wall."""
    h, w = resolution_hw(resolution, 32)
    if canvas < 0:
        raise ValueError(f"canvas must be >= 0 texels per side, got {canvas}")
    scene = mi.cornell_box()
    scene["integrator"] = {"type": "prb", "max_depth": max_depth}
    scene["sensor"]["film"] = film(h, w)
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": 4}
    if canvas:
        texture = np.random.default_rng(canvas_seed).uniform(0.05, 0.95, (canvas, canvas, 3))
        scene["canvas"] = {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([-0.3, 0.5, -0.99]).scale(0.3),
            "bsdf": {"type": "diffuse", "reflectance": bitmap(texture)},
        }
    return scene
