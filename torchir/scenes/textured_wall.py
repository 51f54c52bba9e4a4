"""``textured_wall``: the back wall of an empty Cornell box, textured, lit mostly by bounced light.

For: the benchmark of the target-aware denoiser (Gu et al. 2024, "Target-Aware Image Denoising
for Inverse Monte Carlo Rendering"). The camera sees only the back wall, whose BSDF carries a
``texture x texture`` map (smooth ramps, a disc, a rectangle, stripes).
``lighting="indirect"`` (default) moves the area light down 0.25 and turns it to face the
ceiling, so the wall receives no direct light: with ``prb`` and ``max_depth=5`` (the wall sees
the light after one bounce off the ceiling and walls, and the second bounce still adds ~20 %),
a few-spp render has heavy-tailed noise (relative std per pixel about 2 at 4 spp), the regime
where an L1 loss on raw renders is biased. ``lighting="direct"`` keeps the light at the ceiling.
``material="albedo"``: diffuse wall, unknown albedo ``back.bsdf.reflectance.data`` (T, T, 3).
``material="roughness"``: a metallic ``principled`` wall (base colour 0.8) that mirrors the room
more or less sharply, unknown roughness ``back.bsdf.roughness.data`` (T, T, 1) in [0.05, 0.65]:
invisible to albedo/normal/depth G-buffers (changing it changes the image by ~40 %).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np

from ._common import bitmap, film, resolution_hw

DESCRIPTION = "Cornell-box back wall with a texture, lit by bounced light; path tracing (prb, max_depth 5); recover the texture"
PARAMETERS = ("back.bsdf.reflectance.data",)


def wall_texture(size: int, channels: int = 3) -> np.ndarray:
    """Ground truth ``(size, size, channels)`` in [0.05, 0.95]: ramps, a disc, a rectangle, stripes."""
    y, x = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    r = 0.2 + 0.6 * x
    g = 0.2 + 0.6 * y
    b = 0.5 + 0.3 * np.sin(5 * x + 2 * y)
    disc = (x - 0.3) ** 2 + (y - 0.3) ** 2 < 0.15**2
    rect = (x > 0.55) & (x < 0.85) & (y > 0.2) & (y < 0.45)
    stripes = (y > 0.65) & (np.floor(x * 10) % 2 == 0)
    rgb = np.stack([r, g, b], -1)
    rgb[disc] = [0.9, 0.15, 0.1]
    rgb[rect] = [0.1, 0.2, 0.85]
    rgb[stripes] = 0.9
    rgb = np.clip(rgb, 0.05, 0.95).astype(np.float32)
    return rgb if channels == 3 else rgb.mean(-1, keepdims=True).astype(np.float32)


def build(
    resolution: int | tuple[int, int] | None = None,
    texture: int = 32,
    lighting: str = "indirect",
    material: str = "albedo",
    max_depth: int = 5,
) -> dict[str, Any]:
    """Mitsuba dict of the textured wall at ``resolution`` (default 64x64)."""
    if lighting not in ("indirect", "direct"):
        raise ValueError(f"lighting must be 'indirect' or 'direct', got {lighting!r}")
    if material not in ("albedo", "roughness"):
        raise ValueError(f"material must be 'albedo' or 'roughness', got {material!r}")
    h, w = resolution_hw(resolution, 64)
    T = mi.ScalarTransform4f
    scene = mi.cornell_box()
    for key in ("small-box", "large-box"):
        del scene[key]
    scene["integrator"] = {"type": "prb", "max_depth": max_depth}
    scene["sensor"]["fov"] = 22.5  # the back wall fills the frame
    scene["sensor"]["film"] = film(h, w)
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": 4}
    if lighting == "indirect":
        scene["light"]["to_world"] = T().translate([0, 0.74, 0.01]).rotate([1, 0, 0], -90).scale([0.23, 0.19, 1])
    if material == "albedo":
        scene["back"]["bsdf"] = {"type": "diffuse", "reflectance": bitmap(wall_texture(texture))}
    else:
        rough = bitmap(np.repeat(wall_texture(texture, 1), 3, -1))
        rough["data"] = mi.TensorXf(np.ascontiguousarray(0.05 + 0.6 * wall_texture(texture, 1)))  # (T, T, 1)
        scene["back"]["bsdf"] = {  # a glossy metal: roughness decides how sharply it mirrors the room
            "type": "principled",
            "base_color": {"type": "rgb", "value": [0.8, 0.8, 0.8]},
            "metallic": 1.0,
            "roughness": rough,
        }
    return scene
