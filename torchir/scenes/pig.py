"""``pig``: a smooth diffuse blob above a floor, lit by one area light (Wang et al. 2023, Fig. 8 "Pig").

For: shape derivatives of the camera-ray term (the derivative image w.r.t. the blob's vertical
displacement), and the primary-vertex forms compared in ``torchir.bench.restir_antithetic``.
The ``pig`` is a closed, smooth-shaded mesh (an ellipsoid body with a snout and four stubby
legs blended in, one connected surface whose shading is continuous, so the camera-ray term has
no boundaries of its own) floating just above a grey floor; one square area light above and
to the side lights it and casts its shadow on the floor. A box filter, as the paper's.
Light transport: direct illumination only (``prb`` with ``max_depth=2``; ReSTIR renders the
same light transport through ``render(..., sampler=ReSTIRSampler(scene))``).
Typical unknown: the blob's vertical position (``pig.vertex_positions`` through
:func:`torchir.derived.rigid_transform`, translation only).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import perspective, resolution_hw, sphere_grid, triangle_mesh

DESCRIPTION = "smooth diffuse blob above a floor, one area light, box filter; direct illumination (prb, max_depth 2); recover its vertical position"
PARAMETERS = ("pig.vertex_positions",)

CENTER = (0.0, 0.0, 0.75)  # the blob's centre (the pivot of rigid transforms)
LIGHT_ORIGIN, LIGHT_TARGET = (-1.6, -1.0, 3.0), (0.0, 0.0, 0.6)  # the main light's centre and where it faces


def blob_vertices(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3), faces (F, 3))`` of the blob around the origin: a latitude-longitude
    sphere (poles shared) displaced smoothly into a body, a snout and four legs."""
    d, faces = sphere_grid(rings, segments)

    def bump(center, width):
        c = np.asarray(center, dtype=np.float64)
        c /= np.linalg.norm(c)
        return np.exp((d @ c - 1.0) / width)

    radius = 1.0 + 0.35 * bump([1, 0, 0.1], 0.02)  # snout
    for sx in (-1, 1):
        for sy in (-1, 1):
            radius += 0.3 * bump([0.55 * sx, 0.45 * sy, -0.7], 0.015)  # legs
    return d * radius[:, None] * np.array([0.75, 0.45, 0.42]), faces


def blob_mesh(name: str, rings: int, segments: int, center, bsdf: dict[str, Any]) -> mi.Mesh:
    """The blob as a smooth-shaded Mitsuba mesh centred at ``center``."""
    v, f = blob_vertices(rings, segments)
    return triangle_mesh(name, v + np.asarray(center), f, bsdf, smooth=True)


def build(resolution: int | tuple[int, int] | None = None, rings: int = 24, segments: int = 48, light_size: float = 1.0,
          dome_lights: int = 0, blind: float = 0.0) -> dict[str, Any]:
    """Mitsuba dict of the scene at ``resolution`` (default 64x64).

    Args:
        rings, segments: the blob's tessellation (latitude rings, longitude segments).
        light_size: side of the square light (its power stays the same).
        dome_lights: that many more small square lights (side 0.1) on a dome around the blob, of
            random colours and powers spanning 100x, together as powerful as the main light:
            light selection becomes the hard part, with nothing occluding the blob.
        blind: slat period of a venetian blind a quarter of the way from the light to the blob
            (slats across the light's beam, 70 % closed; 0: none): each point of the blob sees
            the light through stripes, so visibility becomes the hard part.
    """
    if dome_lights < 0:
        raise ValueError(f"dome_lights must be >= 0, got {dome_lights}")
    if not light_size > 0:
        raise ValueError(f"light_size must be > 0, got {light_size}")
    if rings < 3 or segments < 3:
        raise ValueError(f"rings and segments must be >= 3, got {rings}, {segments}")
    if not 0.0 <= blind <= 1.0:
        raise ValueError(f"blind must be in [0, 1], got {blind}")
    h, w = resolution_hw(resolution, 64)
    T = mi.ScalarTransform4f
    pink = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.45, 0.45]}}
    scene = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0.4, -3.2, 1.9], [0.0, 0.0, 0.55], [0, 0, 1], 38.0, h, w),
        "floor": {
            "type": "rectangle",
            "to_world": T().scale([3.0, 3.0, 1.0]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}},
        },
        "pig": blob_mesh("pig", rings, segments, CENTER, pink),
        # a square light (side light_size) at z = 3, up and to the left, facing the blob
        "light": {
            "type": "rectangle",
            "to_world": T().look_at(origin=list(LIGHT_ORIGIN), target=list(LIGHT_TARGET), up=[0, 0, 1]).scale(0.5 * light_size),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 25.0 / light_size**2}},
        },
    }
    if blind > 0:
        scene.update(_blind(blind))
    rng = np.random.default_rng(7)
    powers = np.exp(rng.uniform(0.0, np.log(100.0), dome_lights))
    powers *= 25.0 / powers.sum() if dome_lights else 1.0  # radiance x area: together as the main light
    for i in range(dome_lights):
        azimuth, elevation = rng.uniform(0, 2 * np.pi), rng.uniform(0.25, 1.2)
        origin = [2.6 * np.cos(elevation) * np.cos(azimuth), 2.6 * np.cos(elevation) * np.sin(azimuth), 0.75 + 2.6 * np.sin(elevation)]
        colour = rng.uniform(0.5, 1.0, 3)
        scene[f"dome_{i}"] = {
            "type": "rectangle",
            "to_world": T().look_at(origin=origin, target=list(CENTER), up=[0, 0, 1]).scale(0.05),
            # main light: radiance 25 over area light_size^2, so radiance x area = 25
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (powers[i] / 0.01 * colour / colour.mean()).tolist()}},
        }
    return scene


def _blind(period: float, closed: float = 0.7, half_width: float = 1.3) -> dict[str, Any]:
    """Slats (dark rectangles, ``closed`` of each ``period``) across the main light's beam, in
    the plane a quarter of the way from the light's centre to its target."""
    T = mi.ScalarTransform4f
    light, target = np.array(LIGHT_ORIGIN), np.array(LIGHT_TARGET)
    middle = light + 0.25 * (target - light)
    frame = T().look_at(origin=middle.tolist(), target=(middle + target - light).tolist(), up=[0, 0, 1])
    dark = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.1}}
    count = int(2 * half_width / period) + 1
    return {f"slat_{i}": {"type": "rectangle", "bsdf": dark,
                          "to_world": frame @ T().translate([-half_width + (i + 0.5) * period, 0, 0])
                          @ T().scale([0.5 * period * closed, half_width, 1])}
            for i in range(count)}

