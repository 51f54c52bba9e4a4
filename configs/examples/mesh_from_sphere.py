"""The scene of ``mesh_from_sphere.yaml``: an icosphere to be deformed into an ellipsoid seen by
four cameras under a constant environment (Mitsuba's shape-optimisation tutorial, in small).

``build`` returns the Mitsuba scene dict (the start mesh is built here, in memory, from
``gpytoolbox.icosphere``); ``python configs/examples/mesh_from_sphere.py`` writes the target,
``mesh_from_sphere_target.ply`` beside this file, from the same code (the run's ``truth``; its
vertex list is the sphere's, deformed, so synthetic targets render from it).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

TARGET = Path(__file__).with_name("mesh_from_sphere_target.ply")
AXES = (1.3, 0.8, 1.0)  # the ellipsoid's semi-axes
CAMERAS = (([4.0, 0, 0], [0, 0, 1]), ([0, 4.0, 0], [0, 0, 1]), ([0, 0, 4.0], [0, 1, 0]), ([-2.3, -2.3, 2.3], [0, 0, 1]))


def meshes(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(sphere vertices (V, 3), target vertices (V, 3), faces (F, 3))``: a unit icosphere and the
    ellipsoid ``AXES`` on the same vertex list."""
    import gpytoolbox

    v, f = gpytoolbox.icosphere(subdivisions)
    v = np.asarray(v, np.float64)
    return v, v * np.asarray(AXES), np.asarray(f, np.int64)


def build(resolution: int | list[int] | None = None, subdivisions: int = 2, albedo: float = 0.2) -> dict[str, Any]:
    """The scene dict: the sphere ``shape`` (diffuse, smooth-shaded: ``direct_projective`` refuses a
    flat-shaded mesh, whose creases it does not sample), ``view_0`` .. ``view_3`` and a constant
    environment, rendered by ``direct_projective`` (the silhouettes carry the shape)."""
    import mitsuba as mi

    from torchir.scenes._common import perspective, resolution_hw

    h, w = resolution_hw(resolution, 64)
    v, _, f = meshes(subdivisions)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}})
    mesh = mi.Mesh("shape", len(v), len(f), props, has_vertex_normals=True, has_vertex_texcoords=False)
    buffers = mi.traverse(mesh)
    buffers["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    buffers["faces"] = mi.UInt32(f.astype(np.uint32).ravel())
    buffers.update()  # bounding box and vertex normals
    mesh.set_id("shape")
    sensors = {f"view_{i}": perspective(origin, [0, 0, 0], up, 45.0, h, w) for i, (origin, up) in enumerate(CAMERAS)}
    for sensor in sensors.values():
        sensor["film"]["sample_border"] = True  # a moving shape may cross the film's border (Mitsuba's advice)
    return {"type": "scene", "integrator": {"type": "direct_projective", "sppi": 0}, **sensors, "shape": mesh,
            "light": {"type": "constant"}}


if __name__ == "__main__":
    from torchir.geometry import write_mesh

    _, target, faces = meshes()
    print(write_mesh(TARGET, target, faces, binary=False))
