"""Pieces shared by the built-in scenes: resolution parsing, films, sensors, textures."""
from __future__ import annotations

from typing import Any

import mitsuba as mi
import numpy as np


def resolution_hw(resolution: int | tuple[int, int] | None, default: int) -> tuple[int, int]:
    """``(H, W)`` from an int (square), a pair, or ``None`` (the scene's default)."""
    if resolution is None:
        return default, default
    if isinstance(resolution, int) and not isinstance(resolution, bool):
        h = w = resolution
    elif isinstance(resolution, (tuple, list)) and len(resolution) == 2:
        h, w = (int(r) for r in resolution)
    else:
        raise ValueError(f"resolution must be an int or (H, W), got {resolution!r}")
    if h < 1 or w < 1:
        raise ValueError(f"resolution must be positive, got {(h, w)}")
    return h, w


def film(h: int, w: int) -> dict[str, Any]:
    """An RGB float film with a box filter: a pixel is the mean radiance over its square."""
    return {
        "type": "hdrfilm",
        "width": w,
        "height": h,
        "rfilter": {"type": "box"},
        "pixel_format": "rgb",
        "component_format": "float32",
        "sample_border": False,
    }


def perspective(origin, target, up, fov: float, h: int, w: int, spp: int = 4) -> dict[str, Any]:
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "smaller",
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": film(h, w),
    }


def bitmap(data: np.ndarray) -> dict[str, Any]:
    """A raw (linear, unfiltered by sRGB) RGB bitmap texture from an (H, W, 3) array."""
    return {
        "type": "bitmap",
        "raw": True,
        "filter_type": "bilinear",
        "data": mi.TensorXf(np.ascontiguousarray(data, dtype=np.float32)),
    }


def painting_texture(size: int) -> np.ndarray:
    """A procedural (size, size, 3) albedo with blobs, stripes and flat regions, in [0.05, 0.9]."""
    y, x = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    r = 0.45 + 0.4 * np.sin(6.0 * x + 1.0) * np.cos(4.0 * y)
    g = 0.45 + 0.4 * np.exp(-((x - 0.3) ** 2 + (y - 0.65) ** 2) / 0.03) - 0.2 * (x > 0.7)
    b = 0.3 + 0.5 * ((np.floor(8 * x) + np.floor(8 * y)) % 2) * (y < 0.4)
    return np.clip(np.stack([r, g, b], -1), 0.05, 0.9).astype(np.float32)


# The unit cube [-1, 1]^3 with 8 shared vertices (index 4x + 2y + z of the corner's 0/1 bits) and
# 12 outward-facing triangles.
_BOX_FACES = ((0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
              (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3))


def welded_box(name: str, to_world: mi.ScalarTransform4f, bsdf: dict[str, Any]) -> mi.Mesh:
    """A closed box whose faces share their 8 corner vertices (flat-shaded, no uv).

    Mitsuba's ``cube`` gives each face its own 4 vertices, so every edge is an open mesh border
    to the projective integrators' silhouette sampling, which then overstates the boundary
    gradient; a welded box's agrees with finite differences (measured on ``occluded_lights``:
    docs/rendering.md, "Measurements behind the design")."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    return triangle_mesh(name, transform_points(to_world, corners), np.array(_BOX_FACES, dtype=np.uint32), bsdf)


def transform_points(to_world: mi.ScalarTransform4f, points: np.ndarray) -> np.ndarray:
    """``points`` (N, 3) through the affine transform ``to_world``, in float64."""
    m = np.array(to_world.matrix, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]


def triangle_mesh(name: str, vertices: np.ndarray, faces: np.ndarray, bsdf: dict[str, Any], smooth: bool = False) -> mi.Mesh:
    """A Mitsuba mesh from ``vertices`` (V, 3) and ``faces`` (F, 3); ``smooth``: per-vertex
    normals (area-weighted from the faces), else flat shading."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(vertices), len(faces), props, has_vertex_normals=smooth)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, dtype=np.uint32).ravel())
    params.update()
    if smooth:
        mesh.recompute_vertex_normals()
    return mesh


def sphere_grid(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """``(directions (V, 3), faces (F, 3))``: a closed latitude-longitude unit sphere with shared
    poles, ``rings`` latitude bands and ``segments`` longitudes (outward-facing triangles)."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    d = np.concatenate([[[0, 0, 1]], d, [[0, 0, -1]]])
    faces = []
    ring = lambda i, j: 1 + i * segments + j % segments  # noqa: E731
    last = len(d) - 1
    for j in range(segments):
        faces.append((0, ring(0, j), ring(0, j + 1)))
        faces.append((last, ring(rings - 2, j + 1), ring(rings - 2, j)))
        for i in range(rings - 2):
            faces.append((ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)))
            faces.append((ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)))
    return d, np.array(faces, dtype=np.uint32)
