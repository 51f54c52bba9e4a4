"""Isotropic remeshing (Botsch and Kobbelt 2004, "A Remeshing Approach to Multiresolution
Modeling": edge splits, collapses, flips, tangential smoothing and projection back onto the
input) through ``gpytoolbox.remesh_botsch``, on the welded surface.

A remesh changes the topology: every per-vertex state is rebuilt on it afterwards (a new
:class:`~torchir.geometry.LargeSteps`, its latent, a fresh optimiser), as Mitsuba's shape tutorial does.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ._mesh import as_faces, as_vertices, host_positions, mean_edge_length, scene_mesh, shape_id, weld_positions

__all__ = ["remesh", "remesh_scene", "replace_mesh"]


def _gpytoolbox() -> Any:
    """gpytoolbox, imported without the DeprecationWarnings its own imports raise (of scipy and
    numpy modules it does not use here)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import gpytoolbox
    return gpytoolbox


def _remesh_arrays(positions: np.ndarray, faces: np.ndarray, edge_length: float | None, iterations: int,
                   project: bool) -> tuple[np.ndarray, np.ndarray]:
    """Weld ``positions`` (V, 3) float64 and ``faces`` (F, 3), then remesh: host arrays out."""
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be a positive int, got {iterations!r}")
    if not np.isfinite(positions).all():
        raise ValueError("vertices have NaN/Inf entries")
    # seam copies would be open borders, which remesh_botsch keeps fixed: remesh the surface
    w = weld_positions(positions, faces)
    v = np.ascontiguousarray(positions[w.representative], dtype=np.float64)
    f = np.ascontiguousarray(w.faces, dtype=np.int32)
    if edge_length is None:
        edge_length = 0.5 * mean_edge_length(v, f)  # Mitsuba's shape tutorial: half the mean edge
    edge_length = float(edge_length)
    if not np.isfinite(edge_length) or edge_length <= 0:
        raise ValueError(f"edge_length must be finite and > 0, got {edge_length}")
    v_new, f_new = _gpytoolbox().remesh_botsch(v, f, i=iterations, h=edge_length, project=bool(project))
    return np.asarray(v_new, np.float64), np.asarray(f_new, np.int64)


def remesh(vertices: Any, faces: Any, *args: Any, edge_length: float | None = None, iterations: int = 5,
           project: bool = True) -> tuple[Any, torch.Tensor]:
    """Remesh a triangle mesh to edges of about ``edge_length``.

    Vertices at bit-identical positions are welded first (a seam would otherwise be a border,
    which the remesher keeps fixed), so the result is one welded surface, without uvs.
    ``remesh(scene, shape, vertices, ...)`` (a :class:`torchir.Scene` first) is
    :func:`remesh_scene`.

    Args:
        vertices: ``(V, 3)`` or ``(3V,)`` floating tensor.
        faces: ``(F, 3)`` or ``(3F,)`` integer indices.
        edge_length: the target edge length; None: half the mean edge length of the input.
        iterations: the remesher's iterations (the tutorial: 5).
        project: project the new vertices onto the input surface (else it smooths it).

    Returns:
        ``(vertices (V', 3), faces (F', 3) int64)``, on the input's device, in its dtype.
    """
    from ..scene import Scene

    if isinstance(vertices, Scene):
        return remesh_scene(vertices, faces, *args, edge_length=edge_length, iterations=iterations, project=project)
    if args:
        raise TypeError("remesh(vertices, faces) takes edge_length, iterations and project by keyword")
    v = as_vertices(vertices)
    f = as_faces(faces, v.shape[0])
    v_new, f_new = _remesh_arrays(host_positions(v), f, edge_length, iterations, project)
    return torch.as_tensor(v_new, dtype=v.dtype, device=v.device), torch.as_tensor(f_new, device=v.device)


def remesh_scene(scene: Any, shape: str, vertices: Any = None, edge_length: float | None = None, iterations: int = 5,
                 project: bool = True) -> tuple[Any, torch.Tensor]:
    """A new :class:`torchir.Scene` in which the mesh ``shape`` is remeshed (:func:`remesh`).

    The new scene holds the old one's integrator, sensors, emitters and other shapes (the same
    objects: use the new scene from then on), and a new mesh of the same id with the old one's
    BSDF and media; it has vertex normals (smooth shading, recomputed by Mitsuba) if the old one
    had. Derived parameters of other keys carry over.

    Args:
        scene: the :class:`torchir.Scene`.
        shape: the mesh's id (``"shape"`` or ``"shape.vertex_positions"``).
        vertices: its current vertices (``(V, 3)`` or ``(3V,)``, e.g. ``ls.from_differential(u)``);
            None: the scene's loaded ones.
        edge_length, iterations, project: as in :func:`remesh`.

    Returns:
        ``(new scene, its vertex positions (3V',))``: ``float32``, flat as ``"<shape>.vertex_positions"``,
        on the render device; its faces are ``new_scene.get("<shape>.faces")``.
    """
    from .. import backend

    old, name = _editable_mesh(scene, shape, "remesh_scene")
    if vertices is None:
        vertices = scene.get(f"{name}.vertex_positions")
    v = as_vertices(vertices)
    if v.shape[0] != old.vertex_count():
        raise ValueError(f"vertices has {v.shape[0]} vertices, mesh {name!r} has {old.vertex_count()}")
    faces = np.asarray(old.faces_buffer(), np.int64).reshape(-1, 3)
    v_new, f_new = _remesh_arrays(host_positions(v), faces, edge_length, iterations, project)
    new = replace_mesh(scene, name, v_new, f_new)
    positions = torch.as_tensor(v_new.astype(np.float32).ravel(), device=torch.device(backend.device()))
    return new, positions


def _editable_mesh(scene: Any, shape: str, caller: str) -> tuple[Any, str]:
    """``(mesh, id)`` of the mesh ``shape`` of the torchir ``scene`` that ``caller`` may replace
    (a ``TypeError`` for anything but a Scene, a ``ValueError`` for an area light)."""
    from ..scene import Scene

    if not isinstance(scene, Scene):
        raise TypeError(f"{caller} takes a torchir.Scene, got {type(scene).__name__}")
    old = scene_mesh(scene, shape)
    name = shape_id(shape)
    if old.emitter() is not None:
        raise ValueError(f"mesh {name!r} is an area light: remeshing emitters is not supported")
    return old, name


def replace_mesh(scene: Any, shape: str, vertices: Any, faces: Any) -> Any:
    """A new :class:`torchir.Scene` in which the mesh ``shape`` has the given vertices and faces
    (any topology): what :func:`remesh_scene` builds around a remesher's output, and what a
    resumed run rebuilds from a checkpoint's topology.

    The new scene holds the old one's integrator, sensors, emitters and other shapes (the same
    objects) and a new mesh of the same id with the old one's BSDF and media, with vertex normals
    (recomputed by Mitsuba) if the old one had them, without uvs. Derived parameters of other keys
    carry over.

    Args:
        scene: the :class:`torchir.Scene`.
        shape: the mesh's id (``"shape"`` or ``"shape.vertex_positions"``).
        vertices: ``(V', 3)`` or ``(3V',)`` positions (tensor or array).
        faces: ``(F', 3)`` or ``(3F',)`` indices into ``vertices``.

    Returns:
        The new scene; its ``"<shape>.vertex_positions"`` are ``vertices`` in float32.
    """
    import mitsuba as mi

    from ..scene import Scene

    old, name = _editable_mesh(scene, shape, "replace_mesh")
    v_new = host_positions(as_vertices(vertices))
    f_new = as_faces(faces, v_new.shape[0])
    if not np.isfinite(v_new).all():
        raise ValueError("vertices have NaN/Inf entries")

    props = mi.Properties()
    for key, value in (("bsdf", old.bsdf()), ("interior", old.interior_medium()), ("exterior", old.exterior_medium())):
        if value is not None:
            props[key] = value
    mesh = mi.Mesh(name, len(v_new), len(f_new), props, has_vertex_normals=old.has_vertex_normals(), has_vertex_texcoords=False)
    mesh.set_id(name)  # the constructor's name is not the id the scene's keys use
    buffers = mi.traverse(mesh)
    buffers["vertex_positions"] = mi.Float(v_new.astype(np.float32).ravel())
    buffers["faces"] = mi.UInt32(f_new.astype(np.uint32).ravel())
    buffers.update()  # bounding box and (smooth meshes) vertex normals

    mi_scene = scene.mi_scene
    entries: dict[str, Any] = {"type": "scene", "integrator": mi_scene.integrator()}
    objects = [*mi_scene.sensors(), *(e for e in mi_scene.emitters() if e.get_shape() is None),
               *(s for s in mi_scene.shapes() if s is not old and not s.is_sensor()), mesh]
    for i, obj in enumerate(objects):
        key = obj.id() or f"_object_{i}"
        entries[key if key not in entries else f"{key}_{i}"] = obj
    new = Scene(mi.load_dict(entries, optimize=False), name=scene.name, description=scene.description)
    new.is_builtin = scene.is_builtin
    target = f"{name}.vertex_positions"
    for derived in {d.group: d for d in scene.derived.values() if d.target != target}.values():
        loaded = {n: np.reshape(scene.derived[n].value, scene.derived[n].shape) for n in derived.group}
        new.derive(derived.target, derived.to_target, loaded)
    return new
