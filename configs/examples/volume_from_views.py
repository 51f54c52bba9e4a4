"""The scene of ``volume_from_views.yaml``: Mitsuba's volume-optimisation tutorial in small, with a
procedural density instead of a downloaded grid.

``build`` returns the Mitsuba scene dict: a ``cube`` with a ``null`` BSDF around a ``heterogeneous``
medium whose ``sigma_t`` is a ``gridvolume`` (``scale: 40``, constant albedo), lit by a ``constant``
environment, rendered by ``prbvolpath``, seen by ``views`` cameras on a half circle
(:func:`torchir.rigs.orbit`, the tutorial's rig: tent filter, no border sampling). The grid it is
loaded with is the truth (:func:`truth_grid`: a ring and an off-centre ball), so a run's synthetic
targets render it and its parameter error is against it.
"""
from __future__ import annotations

from typing import Any

import numpy as np


def truth_grid(size: int = 16, ring: float = 0.1, ball: float = 0.15) -> np.ndarray:
    """The true density, ``(size, size, size, 1)`` float32 (Mitsuba's (Z, Y, X, C)): a ring in the
    xy plane (radius 0.55, thickness 0.15, peak ``ring``) and a ball at (0.3, -0.3, 0.4) (peak
    ``ball``), in the cube [-1, 1]³ (the medium's ``scale`` multiplies them)."""
    c = (np.arange(size) + 0.5) / size * 2 - 1  # voxel centres in the cube's frame
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    ring_shape = np.exp(-((np.hypot(x, y) - 0.55) ** 2 + z**2) / (2 * 0.15**2))
    ball_shape = np.exp(-((x - 0.3) ** 2 + (y + 0.3) ** 2 + (z - 0.4) ** 2) / (2 * 0.2**2))
    return (ring * ring_shape + ball * ball_shape).astype(np.float32)[..., None]


def truth_albedo(size: int = 16) -> np.ndarray:
    """A per-voxel RGB albedo, ``(size, size, size, 3)`` float32: from (0.9, 0.5, 0.3) at x = -1 to
    (0.3, 0.6, 0.9) at x = 1 (Yan et al. 2025 recover density and albedo per voxel)."""
    x = (np.arange(size) + 0.5) / size
    rgb = (1 - x)[:, None] * np.array([0.9, 0.5, 0.3]) + x[:, None] * np.array([0.3, 0.6, 0.9])  # (X, 3)
    return np.ascontiguousarray(np.broadcast_to(rgb, (size, size, size, 3)), dtype=np.float32)


def build(resolution: int | list[int] | None = None, grid: int = 16, views: int = 5, albedo: float = 0.8,
          max_depth: int = 8, ring: float = 0.1, ball: float = 0.15, albedo_grid: int | None = None) -> dict[str, Any]:
    """The scene dict (``resolution``: film size, default 32²; ``grid``, ``ring``, ``ball``: the
    truth grid's size and peaks, :func:`truth_grid`; ``albedo_grid``: a size, to make the albedo a
    per-voxel RGB grid (:func:`truth_albedo`, key ``object.interior_medium.albedo.data``) instead of
    the constant ``albedo``)."""
    import mitsuba as mi

    from torchir import rigs

    sensors = rigs.orbit(views, distance=4.0, elevation=0.0, fov=45.0, resolution=32 if resolution is None else resolution,
                         start=-90.0, arc=180.0, filter="tent", sample_border=False)
    medium = {
        "type": "heterogeneous",
        "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(truth_grid(grid, ring, ball)),
                    "to_world": mi.ScalarTransform4f().translate(-1.0).scale(2.0)},  # the unit cube onto the cube
        "scale": 40.0,
        "albedo": albedo if albedo_grid is None else {
            "type": "gridvolume", "grid": mi.VolumeGrid(truth_albedo(albedo_grid)),
            "to_world": mi.ScalarTransform4f().translate(-1.0).scale(2.0)},
    }
    return {"type": "scene", "integrator": {"type": "prbvolpath", "max_depth": max_depth},
            **{f"view_{i}": s for i, s in enumerate(sensors)},
            "object": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
            "light": {"type": "constant"}}
