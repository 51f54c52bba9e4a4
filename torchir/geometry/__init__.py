"""Mesh reconstruction on the torch side: the Large Steps parameterisation, uniform Adam,
Botsch-Kobbelt remeshing, surface distances and mesh files.

See ``docs/geometry.md`` for a reconstruction loop.
"""
from .largesteps import LargeSteps
from .meshio import read_mesh, write_mesh
from .metrics import chamfer_and_hausdorff, chamfer_distance, hausdorff_distance, sample_surface
from .optim import AdamUniform
from .remesh import remesh, remesh_scene, replace_mesh

__all__ = ["LargeSteps", "AdamUniform", "remesh", "remesh_scene", "replace_mesh", "chamfer_distance", "hausdorff_distance",
           "chamfer_and_hausdorff", "sample_surface",            "read_mesh", "write_mesh"]
