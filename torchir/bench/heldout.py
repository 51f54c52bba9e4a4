"""Held-out scenes: procedural scene families that no sampler setting was tuned against.

Each family is a function ``(resolution=None, seed=0, **options) -> Mitsuba scene dict`` that
draws its layout from ``seed`` (a numpy Generator); every scene renders direct illumination only
(``prb``, ``max_depth`` 2, box filter) and has one differentiable albedo texture, under the key
of :func:`spec`. A run names a scene ``heldout:<family>:<seed>`` (:func:`parse_spec`).

* ``slit_lights``: a painting lit through a narrow slit in a side wall by 100-300 point lights
  hidden behind it, plus a dim fill light: light-bound (almost every light sample is occluded).
* ``holes``: a canvas under a ceiling with a few random rectangular holes, many point lights and
  a few small area lights above it: light-bound.
* ``open``: a canvas lit by one or two large area lights and nothing else (no occluder): not
  light-bound; light reuse cannot gain much here, and must not lose.
* ``fine_texture``: ``holes`` with a 256² albedo with texel-scale detail, at a 96² film by default:
  the texture is finer than the pixels, where fixed camera samples leave texels unseen.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import mitsuba as mi
import numpy as np

from torchir.scenes._common import bitmap, painting_texture, perspective, resolution_hw

__all__ = ["FAMILIES", "PREFIX", "Family", "spec", "parse_spec", "is_spec", "load", "factory", "draw_specs",
           "slit_lights", "holes", "open_canvas", "fine_texture"]

PREFIX = "heldout"
_IRRADIANCE = 3.0  # mean irradiance of a family's main lights over its textured surface
_GREY = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.45, 0.42, 0.38]}}
_DARK = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.1}}


# ------------------------------------------------------------------------------ helpers
def _rng(seed: int, stream: int) -> np.random.Generator:
    """The layout's generator: one stream per family, so equal seeds do not share a layout. Also
    selects torchir's Mitsuba variant (transforms need one), as ``Scene.builtin`` does."""
    from torchir import backend

    backend.variant()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    return np.random.default_rng([int(seed), stream])


def _texture(rng: np.random.Generator, size: int, detail: float = 0.0) -> np.ndarray:
    """A (size, size, 3) albedo in [0.05, 0.9]: the built-in painting pattern turned, mirrored and
    recoloured at random, plus ``detail`` x uniform noise per texel."""
    tex = np.rot90(painting_texture(size), k=int(rng.integers(4)))
    if rng.random() < 0.5:
        tex = tex[:, ::-1]
    tex = tex[..., rng.permutation(3)] * rng.uniform(0.8, 1.15, 3) + rng.uniform(-0.05, 0.05, 3)
    if detail > 0:
        tex = tex + detail * rng.uniform(-1.0, 1.0, tex.shape)
    return np.clip(tex, 0.05, 0.9).astype(np.float32)


def _grid(n: int, half: float, z: float = 0.0) -> np.ndarray:
    """(n², 3) points on a regular grid over [-half, half]² at height ``z`` (cell centres)."""
    c = (np.arange(n) + 0.5) / n * 2 * half - half
    x, y = np.meshgrid(c, c, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), np.full(n * n, z)])


def _point_irradiance(points: np.ndarray, lights: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Irradiance at ``points`` (P, 3) on an upward-facing surface from unit point lights (L, 3):
    (P, L), zero where ``visible`` (P, L) is False or a light is below the surface."""
    d = lights[None, :, :] - points[:, None, :]
    dist = np.linalg.norm(d, axis=-1)
    return np.where(visible, np.maximum(d[..., 2], 0.0) / dist**3, 0.0)


def _rect_axes(to_world: mi.ScalarTransform4f) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, half-axis x, half-axis y) of a ``rectangle`` shape's ``to_world``."""
    m = np.array(to_world.matrix, dtype=np.float64)
    return m[:3, 3], m[:3, 0], m[:3, 1]


def _segments_hit_rect(p: np.ndarray, q: np.ndarray, rect: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Whether the open segments ``p -> q`` (broadcast (..., 3)) cross the rectangle ``rect``."""
    c, ex, ey = rect
    n = np.cross(ex, ey)
    dq = q - p
    denom = dq @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c - p) @ n) / denom
        h = p + t[..., None] * dq - c
        u, v = (h @ ex) / (ex @ ex), (h @ ey) / (ey @ ey)
    return (np.abs(denom) > 1e-12) & (t > 1e-6) & (t < 1 - 1e-6) & (np.abs(u) <= 1) & (np.abs(v) <= 1)


def _scene(sensor: dict[str, Any]) -> dict[str, Any]:
    return {"type": "scene", "integrator": {"type": "prb", "max_depth": 2}, "sensor": sensor}


def _rgb(value: float, tint: np.ndarray) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(value * t) for t in tint]}


# ------------------------------------------------------------------------------ families
def slit_lights(resolution: int | tuple[int, int] | None = None, seed: int = 0, *, lights: int | None = None,
                texture: int | None = None, fill: float = 0.1) -> dict[str, Any]:
    """A painting (``[-1, 1]²`` at z = 0, camera 3 units above) lit through a slit in a side wall.

    The wall (on a random side, 1.3-1.8 units from the centre) has one slit 0.01-0.05 units wide,
    running along or across it at a random place; 100-300 point lights of random (log-normal)
    intensity lie behind it, so each lights only thin strips of the painting. Their mean
    irradiance over the painting is 3; a point light in the room adds ``fill`` times that at the
    painting's centre. Texture: 8-16 texels a side (``texture``), key ``painting.bsdf.reflectance.data``.
    """
    rng = _rng(seed, 1)
    n = int(rng.integers(100, 301)) if lights is None else lights
    size = int(rng.integers(8, 17)) if texture is None else texture
    if n < 1 or size < 1 or fill < 0:
        raise ValueError("lights and texture must be >= 1, fill >= 0")
    wall_x, width, along = rng.uniform(1.3, 1.8), rng.uniform(0.01, 0.05), bool(rng.integers(2))
    start = rng.uniform(0.5, 2.0) if along else rng.uniform(-1.0, 1.0 - width)  # gap in z (along y) or in y
    side = int(rng.integers(4))
    pos = np.column_stack([rng.uniform(wall_x + 0.2, wall_x + 2.5, n), rng.uniform(-2.5, 2.5, n), rng.uniform(0.3, 5.0, n)])
    power = rng.lognormal(0.0, 0.5, n)
    # calibrate in the wall's frame (x = wall_x), before turning everything to its side
    pts = _grid(24, 1.0, 0.002)
    t = (wall_x - pts[:, None, 0]) / (pos[None, :, 0] - pts[:, None, 0])  # where each segment crosses the wall
    ax = 2 if along else 1
    cross = pts[:, None, ax] + t * (pos[None, :, ax] - pts[:, None, ax])
    visible = (cross >= start) & (cross <= start + width)
    mean = float((_point_irradiance(pts, pos, visible) * power).sum(1).mean())
    power *= _IRRADIANCE / mean if mean > 0 else 1.0

    h, w = resolution_hw(resolution, 128)
    T = mi.ScalarTransform4f
    turn = T().rotate([0, 0, 1], 90.0 * side)
    scene = _scene(perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 40.0, h, w))
    scene["painting"] = {"type": "rectangle", "to_world": T().translate([0, 0, 0.002]),
                         "bsdf": {"type": "diffuse", "reflectance": bitmap(_texture(rng, size))}}
    scene["back_wall"] = {"type": "rectangle", "to_world": T().scale([3.0, 3.0, 1.0]), "bsdf": _GREY}
    # the wall spans y in [-3, 3], z in [-1, 6] (every segment from a light to the painting crosses it there)
    lo, hi = (-1.0, 6.0) if along else (-3.0, 3.0)
    for i, (a, b) in enumerate([(lo, start), (start + width, hi)]):
        (y0, y1), (z0, z1) = ((-3.0, 3.0), (a, b)) if along else ((a, b), (-1.0, 6.0))
        scene[f"wall_{i}"] = {
            "type": "rectangle", "bsdf": _GREY,
            "to_world": turn.translate([wall_x, 0.5 * (y0 + y1), 0.5 * (z0 + z1)]).rotate([0, 1, 0], -90).scale([0.5 * (z1 - z0), 0.5 * (y1 - y0), 1.0]),
        }
    world = pos @ np.array(turn.matrix, dtype=np.float64)[:3, :3].T
    tints = rng.uniform(0.85, 1.0, (n, 3))
    for k in range(n):
        scene[f"light_{k:03d}"] = {"type": "point", "position": [float(v) for v in world[k]], "intensity": _rgb(power[k], tints[k])}
    if fill > 0:
        at = np.array([*rng.uniform(-0.8, 0.8, 2), rng.uniform(1.5, 2.5)])
        d2 = float(at @ at)
        scene["fill"] = {"type": "point", "position": [float(v) for v in at],
                         "intensity": _rgb(fill * _IRRADIANCE * d2 / (at[2] / d2**0.5), np.array([0.9, 0.95, 1.0]))}
    return scene


def _ceiling(holes: list[tuple[float, float, float, float]], half: float) -> list[tuple[float, float, float, float]]:
    """Rectangles ``(x0, x1, y0, y1)`` covering ``[-half, half]²`` minus the ``holes`` (same form):
    the grid of every hole edge, its solid cells merged along y per column of cells."""
    xs = sorted({-half, half, *(v for hole in holes for v in hole[:2])})
    ys = sorted({-half, half, *(v for hole in holes for v in hole[2:])})
    out = []
    for x0, x1 in zip(xs, xs[1:]):
        xc, run = 0.5 * (x0 + x1), None
        for y0, y1 in zip(ys, ys[1:]):
            yc = 0.5 * (y0 + y1)
            solid = not any(a < xc < b and c < yc < d for a, b, c, d in holes)
            if solid:
                run = (run[0], y1) if run else (y0, y1)
            elif run:
                out.append((x0, x1, *run))
                run = None
        if run:
            out.append((x0, x1, *run))
    return out


def _holes(rng: np.random.Generator, resolution, texture: int, detail: float, lights: int | None, area_lights: int | None,
           holes: int | None, default_resolution: int) -> dict[str, Any]:
    n_point = int(rng.integers(64, 257)) if lights is None else lights
    n_area = int(rng.integers(2, 7)) if area_lights is None else area_lights
    n_holes = int(rng.integers(2, 7)) if holes is None else holes
    if n_point < 0 or n_area < 0 or n_point + n_area < 1 or n_holes < 1 or texture < 1:
        raise ValueError("need at least one light and one hole; texture >= 1")
    height = rng.uniform(1.6, 2.4)
    sizes, centres = rng.uniform(0.15, 0.6, (n_holes, 2)), rng.uniform(-1.5, 1.5, (n_holes, 2))
    cut = [(cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2) for (cx, cy), (sx, sy) in zip(centres, sizes)]
    points = np.column_stack([rng.uniform(-3.0, 3.0, (n_point, 2)), height + rng.uniform(0.2, 1.2, n_point)])
    above = centres[rng.integers(n_holes, size=n_area)] + rng.uniform(-0.4, 0.4, (n_area, 2))  # each over a hole
    areas = np.column_stack([above, height + rng.uniform(0.3, 1.2, n_area)])
    area_half = rng.uniform(0.05, 0.15, (n_area, 2))
    power, radiance = rng.uniform(0.3, 1.7, n_point), rng.uniform(0.5, 1.5, n_area)
    # calibrate: 70 % of the mean irradiance from the point lights, 30 % from the area lights (all
    # from those the canvas sees through the holes when only one kind is seen there)
    pts = _grid(24, 1.0)
    def seen(lights: np.ndarray) -> np.ndarray:  # through a hole: the segment's crossing of the ceiling
        c = pts[:, None, :2] + (height / lights[None, :, 2:3]) * (lights[None, :, :2] - pts[:, None, :2])
        return np.any([(a < c[..., 0]) & (c[..., 0] < b) & (lo < c[..., 1]) & (c[..., 1] < hi) for a, b, lo, hi in cut], axis=0)
    d = areas[None] - pts[:, None]
    cos = d[..., 2] / np.linalg.norm(d, axis=-1)  # area lights face down: cos at the light = cos at the canvas
    e_point = float((_point_irradiance(pts, points, seen(points)) * power).sum(1).mean())
    e_area = float((_point_irradiance(pts, areas, seen(areas)) * cos * radiance * 4 * area_half.prod(1)).sum(1).mean())
    share = 0.7 if e_point > 0 and e_area > 0 else float(e_point > 0)
    power *= share * _IRRADIANCE / e_point if e_point > 0 else 1.0
    radiance *= (1 - share) * _IRRADIANCE / e_area if e_area > 0 else 1.0

    h, w = resolution_hw(resolution, default_resolution)
    T = mi.ScalarTransform4f
    eye = height - 0.3  # below the ceiling, looking straight down at the canvas
    scene = _scene(perspective([0, 0, eye], [0, 0, 0], [0, 1, 0], float(2 * np.degrees(np.arctan(1.0 / eye))), h, w))
    scene["canvas"] = {"type": "rectangle", "to_world": T().scale([1.1, 1.1, 1.0]),
                       "bsdf": {"type": "diffuse", "reflectance": bitmap(_texture(rng, texture, detail))}}
    for i, (x0, x1, y0, y1) in enumerate(_ceiling(cut, 3.5)):  # 1e-3 overlaps: no cracks
        scene[f"ceiling_{i:02d}"] = {"type": "rectangle", "bsdf": _DARK, "to_world": T().translate(
            [0.5 * (x0 + x1), 0.5 * (y0 + y1), height]).scale([0.5 * (x1 - x0) + 1e-3, 0.5 * (y1 - y0) + 1e-3, 1.0])}
    tints = rng.uniform(0.85, 1.0, (n_point + n_area, 3))
    for k in range(n_point):
        scene[f"light_{k:03d}"] = {"type": "point", "position": [float(v) for v in points[k]], "intensity": _rgb(power[k], tints[k])}
    for k in range(n_area):
        scene[f"area_{k:02d}"] = {
            "type": "rectangle", "to_world": T().translate([float(v) for v in areas[k]]).rotate([1, 0, 0], 180).scale([*area_half[k], 1.0]),
            "emitter": {"type": "area", "radiance": _rgb(radiance[k], tints[n_point + k])},
        }
    return scene


def holes(resolution: int | tuple[int, int] | None = None, seed: int = 0, *, texture: int | None = None,
          lights: int | None = None, area_lights: int | None = None, holes: int | None = None) -> dict[str, Any]:
    """A canvas (``[-1.1, 1.1]²`` at z = 0, seen from just under the ceiling) lit through a ceiling
    at height 1.6-2.4 with 2-6 rectangular holes (0.15-0.6 a side, anywhere over [-1.5, 1.5]²) by
    64-256 point lights (anywhere over [-3, 3]²) and 2-6 small downward area lights (each over a
    hole) above it; mean irradiance 3, 70 % from the point lights and 30 % from the area lights
    (where the canvas sees both kinds). Texture: 8-16 texels a side, key ``canvas.bsdf.reflectance.data``."""
    rng = _rng(seed, 2)
    size = int(rng.integers(8, 17)) if texture is None else texture
    return _holes(rng, resolution, size, 0.0, lights, area_lights, holes, 128)


def fine_texture(resolution: int | tuple[int, int] | None = None, seed: int = 0, *, texture: int = 256, detail: float = 0.25,
                 lights: int | None = None, area_lights: int | None = None, holes: int | None = None) -> dict[str, Any]:
    """``holes``' kind of layout (its own draws) with a ``texture``² albedo (default 256²) whose texels
    carry ``detail`` x uniform noise each, at a 96² film by default: several texels per pixel, so
    a pixel's value depends on where in it the camera samples fall. Key ``canvas.bsdf.reflectance.data``."""
    return _holes(_rng(seed, 4), resolution, texture, detail, lights, area_lights, holes, 96)


def open_canvas(resolution: int | tuple[int, int] | None = None, seed: int = 0, *, lights: int | None = None,
                texture: int | None = None) -> dict[str, Any]:
    """A canvas (``[-1, 1]²`` at z = 0, camera 3 units above) lit by one or two large area lights
    (0.5-1 half-sides, 2.6-3.5 units away, 35-60 degrees up, facing the canvas's centre, two at
    least 120 degrees apart) and nothing else: no shape between canvas and lights (layouts where
    one light would shadow the other are redrawn). Mean irradiance 3. Texture: 8-16 texels a
    side, key ``canvas.bsdf.reflectance.data``."""
    rng = _rng(seed, 3)
    n = int(rng.integers(1, 3)) if lights is None else lights
    size = int(rng.integers(8, 17)) if texture is None else texture
    if n not in (1, 2) or size < 1:
        raise ValueError("lights must be 1 or 2, texture >= 1")
    T = mi.ScalarTransform4f
    pts = _grid(12, 1.0)
    for _ in range(1000):
        azimuth = rng.uniform(0, 2 * np.pi) + np.concatenate([[0.0], rng.uniform(np.radians(120), np.radians(240), n - 1)])
        up, dist, half = rng.uniform(np.radians(35), np.radians(60), n), rng.uniform(2.6, 3.5, n), rng.uniform(0.5, 1.0, (n, 2))
        centres = dist[:, None] * np.column_stack([np.cos(up) * np.cos(azimuth), np.cos(up) * np.sin(azimuth), np.sin(up)])
        shapes = [T().look_at(origin=[float(v) for v in c], target=[0, 0, 0], up=[0, 0, 1]).scale([*hf, 1.0]) for c, hf in zip(centres, half)]
        rects = [_rect_axes(s) for s in shapes]
        g = _grid(8, 0.95)
        samples = [c + g[:, :1] * ex + g[:, 1:2] * ey for c, ex, ey in rects]
        if n == 1 or not any(_segments_hit_rect(pts[:, None], samples[j][None], rects[1 - j]).any() for j in range(2)):
            break
    else:
        raise RuntimeError(f"open_canvas: no layout without a shadow between the lights for seed {seed}")
    # irradiance of unit radiance: sum over 8² patches of each light of cos_l cos_p dA / d²
    e = np.zeros(n)
    for j, ((c, ex, ey), s) in enumerate(zip(rects, samples)):
        normal = np.cross(ex, ey) / np.linalg.norm(np.cross(ex, ey))
        d = s[None] - pts[:, None]
        dist2 = (d**2).sum(-1)
        cos_l = np.maximum(-(d @ normal), 0.0) / np.sqrt(dist2)
        cos_p = np.maximum(d[..., 2], 0.0) / np.sqrt(dist2)
        e[j] = float((cos_l * cos_p / dist2).sum(1).mean()) * 4 * np.linalg.norm(ex) * np.linalg.norm(ey) / len(s)
    weight = rng.uniform(0.5, 1.5, n)
    radiance = weight * _IRRADIANCE / float((weight * e).sum())

    h, w = resolution_hw(resolution, 128)
    scene = _scene(perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 40.0, h, w))
    scene["canvas"] = {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": bitmap(_texture(rng, size))}}
    tints = rng.uniform(0.8, 1.0, (n, 3))
    for j in range(n):
        scene[f"area_{j}"] = {"type": "rectangle", "to_world": shapes[j], "emitter": {"type": "area", "radiance": _rgb(radiance[j], tints[j])}}
    return scene


# ------------------------------------------------------------------------------ registry
@dataclass(frozen=True)
class Family:
    build: Callable[..., dict[str, Any]]  # (resolution=None, seed=0, **options) -> Mitsuba scene dict
    key: str  # the albedo texture a benchmark recovers
    light_bound: bool  # whether light selection, not camera sampling, limits a render's error


FAMILIES: dict[str, Family] = {
    "slit_lights": Family(slit_lights, "painting.bsdf.reflectance.data", True),
    "holes": Family(holes, "canvas.bsdf.reflectance.data", True),
    "open": Family(open_canvas, "canvas.bsdf.reflectance.data", False),
    "fine_texture": Family(fine_texture, "canvas.bsdf.reflectance.data", True),
}


def spec(name: str) -> tuple[Callable[..., dict[str, Any]], str]:
    """``(build, texture key)`` of family ``name`` (``KeyError`` naming the families)."""
    if name not in FAMILIES:
        raise KeyError(f"unknown held-out family {name!r}; families: {', '.join(FAMILIES)}")
    return FAMILIES[name].build, FAMILIES[name].key


def is_spec(text: str) -> bool:
    """Whether ``text`` names a held-out scene (``heldout:...``), well formed or not."""
    return text.strip().startswith(PREFIX + ":")


def parse_spec(text: str) -> tuple[str, int]:
    """``"heldout:<family>:<seed>"`` -> ``(family, seed)`` (``ValueError`` saying what is wrong)."""
    parts = [p.strip() for p in text.strip().split(":")]
    if len(parts) != 3 or parts[0] != PREFIX:
        raise ValueError(f"a held-out scene is {PREFIX}:<family>:<seed>, got {text!r}")
    if parts[1] not in FAMILIES:
        raise ValueError(f"unknown held-out family {parts[1]!r} in {text!r}; families: {', '.join(FAMILIES)}")
    if not parts[2].isdigit():
        raise ValueError(f"the seed of {text!r} must be an integer >= 0, got {parts[2]!r}")
    return parts[1], int(parts[2])


def load(text: str, resolution: int | tuple[int, int] | None = None):
    """``(torchir.Scene, texture key)`` of the held-out scene ``text``."""
    import torchir

    family, seed = parse_spec(text)
    build, key = spec(family)
    return torchir.Scene.from_dict(build(resolution=resolution, seed=seed)), key


def factory(text: str) -> tuple[str, dict[str, Any]]:
    """``("package.module:function", scene_options)`` of ``text``, as the trainer's ``scene=`` takes it."""
    family, seed = parse_spec(text)
    return f"{__name__}:{FAMILIES[family].build.__name__}", {"seed": seed}


def draw_specs(per_family: int, clock: int | None = None) -> list[str]:
    """``per_family`` fresh specs of every family, seeds drawn from ``clock`` (default: the time in ns)."""
    rng = np.random.default_rng(time.time_ns() if clock is None else clock)
    return [f"{PREFIX}:{name}:{int(s)}" for name in FAMILIES for s in rng.choice(1_000_000, per_family, replace=False)]
