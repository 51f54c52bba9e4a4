"""``occluded_lights``: a blocker's shadow on a textured floor, one small and one hidden large light.

For: ReSTIR (Wang et al. 2023, Figs. 9-10 "Tree"): an object seen only through its cast shadow, lit
by one small area light and one large area light that is mostly hidden. The camera looks
straight down at a diffuse floor with a ``texture x texture`` albedo. A small bright square
light (``small_light``) low on the left casts the sharp shadow of ``blocker``, a thin box
mesh (8 shared vertices, so ``blocker.vertex_positions`` exists and the projective boundary
terms see a closed mesh; rotate it with :func:`torchir.derived.rigid_transform`) hanging outside
the camera's view, across the floor. ``blocker="crown"`` makes it a lumpy, finely tessellated
closed mesh of about the box's size (a tree's crown, as the paper's "Tree": thousands of edges,
of which only the few on its outline as seen from a light cast a shadow edge).
A large ceiling panel (``large_light``, 4 x 4) sits above an occluding plate (``shade``) with a
single ``hole`` x ``hole`` opening: each floor point sees about 2 % of the panel, so almost
every light sample towards it is occluded, though it gives the floor about half its light.
Light transport: direct illumination only (``prb`` with ``max_depth=2``; ReSTIR renders the
same light transport through ``render(..., sampler=ReSTIRSampler(scene))``).
Typical unknowns: the floor albedo ``floor.bsdf.reflectance.data`` of shape (T, T, 3); the
blocker's pose (``blocker.vertex_positions`` through a rigid transform).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import (bitmap, painting_texture, perspective, resolution_hw, sphere_grid, transform_points, triangle_mesh,
                      welded_box)

DESCRIPTION = "blocker shadow on a textured floor, small light + mostly hidden large light; direct illumination (prb, max_depth 2); recover the floor texture (or the blocker's rotation)"
PARAMETERS = ("floor.bsdf.reflectance.data",)

BLOCKER_CENTER = (-1.35, 0.05, 1.1)  # the pivot for rigid transforms of the blocker


def build(
    resolution: int | tuple[int, int] | None = None,
    texture: int = 8,
    angle: float = 30.0,
    hole: float = 0.4,
    large: float = 1.0,
    blocker: str = "box",
    rings: int = 24,
) -> dict[str, Any]:
    """Mitsuba dict of the scene at ``resolution`` (default 128x128).

    Args:
        texture: side of the floor's albedo texture.
        angle: the blocker's rotation about the vertical (z) axis, in degrees.
        hole: side of the square opening in the shade under the large light (0: fully hidden).
        large: radiance scale of the large light (1: about half the floor's light).
        blocker: ``"box"`` (12 edges) or ``"crown"`` (a lumpy sphere of ``rings`` latitude bands
            and ``2 * rings`` longitudes: 6 rings (rings - 1) edges, 3312 by default).
    """
    if texture < 1:
        raise ValueError(f"texture must be >= 1, got {texture}")
    if not 0.0 <= hole <= 2.0:
        raise ValueError(f"hole must be in [0, 2], got {hole}")
    if large < 0:
        raise ValueError(f"large must be >= 0, got {large}")
    if blocker not in ("box", "crown"):
        raise ValueError(f"blocker must be 'box' or 'crown', got {blocker!r}")
    if rings < 3:
        raise ValueError(f"rings must be >= 3, got {rings}")
    h, w = resolution_hw(resolution, 128)
    T = mi.ScalarTransform4f
    dark = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.2}}
    placement = T().translate(list(BLOCKER_CENTER)).rotate([0, 0, 1], angle).scale([0.38, 0.06, 0.26])
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        # straight down from z = 2.4: the view covers the floor's [-1.15, 1.15]^2
        "sensor": perspective([0, 0, 2.4], [0, 0, 0], [0, 1, 0], 51.2, h, w),
        "floor": {
            "type": "rectangle",
            "to_world": T().scale([1.25, 1.25, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))},
        },
        # a welded box (shared vertices): Mitsuba's cube doubled its projective boundary gradient
        "blocker": welded_box("blocker", placement, dark) if blocker == "box" else _crown("blocker", placement, dark, rings),
        # small light: 0.16 x 0.16, low on the left, facing the floor's centre
        "small_light": {
            "type": "rectangle",
            "to_world": T().look_at(origin=[-2.6, 0.2, 2.3], target=[0.0, 0.0, 0.0], up=[0, 0, 1]).scale(0.08),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [2000.0, 1880.0, 1670.0]}},
        },
        # large light: a 4 x 4 ceiling panel at z = 4 facing down (rectangle normals are +z)
        "large_light": {
            "type": "rectangle",
            "to_world": T().translate([0, 0, 4.0]).rotate([1, 0, 0], 180).scale(2.0),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [120.0 * large, 124.0 * large, 134.0 * large]}},
        },
    }
    # The shade: a plate at z = 3 covering [-6, 6]^2 but for a hole x hole opening at (0.3, 0.3),
    # built from four rectangles around the opening (one plate when hole = 0).
    lo, hi, big = 0.3 - hole / 2, 0.3 + hole / 2, 6.0
    if hole == 0:
        rects = [(-big, big, -big, big)]
    else:
        rects = [(-big, lo, -big, big), (hi, big, -big, big), (lo, hi, -big, lo), (lo, hi, hi, big)]
    for i, (x0, x1, y0, y1) in enumerate(rects):
        scene[f"shade_{i}"] = {
            "type": "rectangle",
            "to_world": T().translate([0.5 * (x0 + x1), 0.5 * (y0 + y1), 3.0]).scale([0.5 * (x1 - x0), 0.5 * (y1 - y0), 1.0]),
            "bsdf": dark,
        }
    return scene


def _crown(name: str, to_world: mi.ScalarTransform4f, bsdf: dict[str, Any], rings: int) -> mi.Mesh:
    """A closed lumpy sphere (12 fixed smooth bumps) through ``to_world``, flat-shaded."""
    d, faces = sphere_grid(rings, 2 * rings)
    bumps = np.random.default_rng(3).normal(size=(12, 3))
    bumps /= np.linalg.norm(bumps, axis=1, keepdims=True)
    radius = 1.0 + 0.25 * np.exp((d @ bumps.T - 1.0) / 0.08).sum(1)
    return triangle_mesh(name, transform_points(to_world, d * radius[:, None]), faces, bsdf)
