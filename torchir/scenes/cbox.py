"""``cbox``: the Cornell box with global illumination.

For: the foundation's gradient tests, the adaptive pixel sampler and the overhead benchmark.
Light transport: path tracing with ``prb`` (path replay backpropagation); colour bleeding
between the walls needs indirect light, so ``max_depth=4`` (three bounces after the camera ray;
the fourth and later bounces carry under 3% of the image at these albedos).
Typical unknowns: the wall albedos ``red.reflectance.value``, ``green.reflectance.value``.
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi

from ._common import film, resolution_hw

DESCRIPTION = "Cornell box; path tracing (prb, max_depth 4); recover wall albedos"
PARAMETERS = ("red.reflectance.value", "green.reflectance.value")


def build(resolution: int | tuple[int, int] | None = None, max_depth: int = 4) -> dict[str, Any]:
    """Mitsuba dict of the Cornell box at ``resolution`` (default 32x32)."""
    h, w = resolution_hw(resolution, 32)
    scene = mi.cornell_box()
    scene["integrator"] = {"type": "prb", "max_depth": max_depth}
    scene["sensor"]["film"] = film(h, w)
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": 4}
    return scene
