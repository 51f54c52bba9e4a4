"""``ajar_painting``: a painting lit through the narrow gap of a nearly closed door (Veach-Ajar-like).

For: ReSTIR (Wang et al. 2023, Fig. 11 "Painting"): light selection is hard because the brightest
light is almost entirely hidden. The camera looks at the back wall of a room, most of the image
being a diffuse painting with a ``texture x texture`` albedo. The room's right wall has a door
that is nearly closed: it leaves a vertical slit ``door`` units wide (the painting is 2 units
wide). Behind it, in the next room, a bright area light (``gap_light``, 2.6 x 4) faces the
door; every point of the painting sees a thin strip of it through the slit (about 1 % of its
area with the default ``door=0.02``), so almost every light sample towards it is occluded, yet
it gives the painting about 90 % of its light. A dim point light in the room (``fill``) adds the rest.
``door=0`` closes the door (one wall, no slit): with ``fill=0`` no light reaches the room and
the image is exactly 0.
Light transport: direct illumination only (``prb`` with ``max_depth=2``; ReSTIR renders the
same light transport through ``render(..., sampler=ReSTIRSampler(scene))``).
Typical unknown: the painting's albedo ``painting.bsdf.reflectance.data`` of shape (T, T, 3).
"""
from __future__ import annotations

from typing import Any

import mitsuba as mi

from ._common import bitmap, painting_texture, perspective, resolution_hw

DESCRIPTION = "painting lit through a door gap by a hidden bright light + dim fill; direct illumination (prb, max_depth 2); recover the albedo texture"
PARAMETERS = ("painting.bsdf.reflectance.data",)

_WALL_X = 1.5  # the door wall (plane x = 1.5, the room is x < 1.5)
_GAP_Z = 2.5  # the slit spans z in [2.5, 2.5 + door]
_LIGHT_X = 2.0  # the light in the next room (plane x = 2.0, facing -x)
_GAP_RADIANCE = 1300.0  # about irradiance 3.6 (gap light) at the painting for door = 0.02
_FILL_POSITION = (-0.8, 0.9, 2.4)
_FILL_IRRADIANCE = 3.6  # fill = 1: the fill light gives the painting's centre this irradiance


def build(
    resolution: int | tuple[int, int] | None = None,
    texture: int = 8,
    door: float = 0.02,
    fill: float = 0.1,
) -> dict[str, Any]:
    """Mitsuba dict of the scene at ``resolution`` (default 128x128).

    Args:
        texture: side of the painting's albedo texture (8: texels ~15 pixels wide at 128²).
        door: width of the slit between the door and its frame, in scene units (painting:
            2 units); 0 closes the door.
        fill: the fill light's irradiance at the painting's centre relative to the gap light's
            mean irradiance there at ``door=0.02`` (0.1: a tenth); 0 removes the fill light.
    """
    if texture < 1:
        raise ValueError(f"texture must be >= 1, got {texture}")
    if not 0.0 <= door <= 1.0:
        raise ValueError(f"door must be a slit width in [0, 1] scene units, got {door}")
    if fill < 0:
        raise ValueError(f"fill must be >= 0, got {fill}")
    h, w = resolution_hw(resolution, 128)
    T = mi.ScalarTransform4f
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.45, 0.42, 0.38]}}
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 40.0, h, w),
        "painting": {
            "type": "rectangle",
            "to_world": T().translate([0, 0, 0.002]),
            "bsdf": {"type": "diffuse", "reflectance": bitmap(painting_texture(texture))},
        },
        "back_wall": {"type": "rectangle", "to_world": T().scale([3.0, 3.0, 1.0]), "bsdf": grey},
        # the next room's light: a rectangle in the plane x = 2 facing -x, z in [2.7, 5.3], y in [-2, 2]
        "gap_light": {
            "type": "rectangle",
            "to_world": T().translate([_LIGHT_X, 0, 4.0]).rotate([0, 1, 0], -90).scale([1.3, 2.0, 1.0]),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [_GAP_RADIANCE, 0.95 * _GAP_RADIANCE, 0.85 * _GAP_RADIANCE]}},
        },
    }
    # The door wall (plane x = 1.5) spans z in [-1, 6], y in [-3, 3]: every segment from the light
    # to the room crosses it there, so light enters only through the slit.
    pieces = [(-1.0, 6.0)] if door == 0 else [(-1.0, _GAP_Z), (_GAP_Z + door, 6.0)]
    for i, (z0, z1) in enumerate(pieces):
        scene[f"door_wall_{i}"] = {
            "type": "rectangle",
            "to_world": T().translate([_WALL_X, 0, 0.5 * (z0 + z1)]).rotate([0, 1, 0], -90).scale([0.5 * (z1 - z0), 3.0, 1.0]),
            "bsdf": grey,
        }
    if fill > 0:
        d2 = sum(c * c for c in _FILL_POSITION)
        cos = _FILL_POSITION[2] / d2**0.5
        intensity = fill * _FILL_IRRADIANCE * d2 / cos
        scene["fill"] = {
            "type": "point",
            "position": list(_FILL_POSITION),
            "intensity": {"type": "rgb", "value": [0.9 * intensity, 0.95 * intensity, intensity]},
        }
    return scene
