"""Shared checks and helpers of :mod:`torchir.geometry`: vertex and face layouts, the weld by
position, a mesh's unique edges, and a scene's mesh by its id."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..welding import weld_map

__all__: list[str] = []


def as_vertices(vertices: Any, name: str = "vertices") -> torch.Tensor:
    """``vertices`` as a ``(V, 3)`` floating tensor (a view of a flat ``(3 V,)`` one), device and dtype kept."""
    if not isinstance(vertices, torch.Tensor):
        vertices = torch.as_tensor(np.asarray(vertices), device="cpu")
    if not vertices.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got dtype {vertices.dtype}")
    if vertices.dim() == 1 and vertices.numel() % 3 == 0:
        return vertices.reshape(-1, 3)
    if vertices.dim() == 2 and vertices.shape[1] == 3:
        return vertices
    raise ValueError(f"{name} must be (V, 3) or flat (3V,), got shape {tuple(vertices.shape)}")


def as_faces(faces: Any, vertex_count: int, name: str = "faces") -> np.ndarray:
    """``faces`` as a host ``(F, 3)`` int64 array, checked against ``vertex_count``."""
    if isinstance(faces, torch.Tensor):
        if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
            raise TypeError(f"{name} must hold integer vertex indices, got dtype {faces.dtype}")
        faces = faces.detach().to(torch.int64).cpu().numpy()  # torch's uint32 (Mitsuba's faces) as well
    faces = np.asarray(faces)
    if faces.dtype.kind not in "iu":
        raise TypeError(f"{name} must hold integer vertex indices, got dtype {faces.dtype}")
    if faces.ndim == 1 and faces.size % 3 == 0:
        faces = faces.reshape(-1, 3)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name} must be (F, 3) or flat (3F,), got shape {faces.shape}")
    faces = faces.astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= vertex_count):
        raise ValueError(f"{name} index vertices in [{faces.min()}, {faces.max()}], but there are {vertex_count} vertices")
    return faces


def face_tensor(faces: Any, vertex_count: int, device: torch.device, name: str = "faces") -> torch.Tensor:
    """``faces`` as an ``(F, 3)`` int64 tensor on ``device``, checked against ``vertex_count``
    (a tensor there already is checked there: two scalar reads, no copy of the faces)."""
    if not isinstance(faces, torch.Tensor) or faces.device != torch.device(device):
        return torch.as_tensor(as_faces(faces, vertex_count, name), device=device)
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise TypeError(f"{name} must hold integer vertex indices, got dtype {faces.dtype}")
    if not ((faces.dim() == 2 and faces.shape[1] == 3) or (faces.dim() == 1 and faces.numel() % 3 == 0)):
        raise ValueError(f"{name} must be (F, 3) or flat (3F,), got shape {tuple(faces.shape)}")
    faces = faces.detach().to(torch.int64).reshape(-1, 3)
    if faces.numel() and (bool(faces.min() < 0) or bool(faces.max() >= vertex_count)):
        raise ValueError(f"{name} index vertices in [{int(faces.min())}, {int(faces.max())}], but there are {vertex_count} vertices")
    return faces


def host_positions(vertices: torch.Tensor) -> np.ndarray:
    """A float64 host copy of ``(V, 3)`` vertices (construction time only: welds, remeshing, metrics)."""
    return vertices.detach().to(torch.float64).cpu().numpy()


@dataclass(frozen=True)
class Weld:
    """The surface behind a vertex list whose seams repeat positions.

    ``welded_index`` (V,): each file vertex's welded vertex; ``representative`` (n,): the first
    file vertex of each welded vertex (in order of first appearance); ``faces`` (F, 3): the faces
    through ``welded_index``."""

    welded_index: np.ndarray
    representative: np.ndarray
    faces: np.ndarray

    @property
    def count(self) -> int:
        return len(self.representative)


def weld(first: np.ndarray, faces: np.ndarray) -> Weld:
    """The :class:`Weld` of a vertex list whose ``first`` (V,) gives each vertex the first vertex
    at its position (:func:`torchir.welding.weld_map`)."""
    representative, welded_index = np.unique(first, return_inverse=True)
    welded_index = welded_index.reshape(-1).astype(np.int64)
    return Weld(welded_index, representative.astype(np.int64), welded_index[faces] if faces.size else faces)


def weld_positions(positions: np.ndarray, faces: np.ndarray) -> Weld:
    """The :class:`Weld` of ``positions`` (V, 3): vertices at bit-identical float32 positions are one."""
    return weld(weld_map(positions), faces)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """``(E, 2)`` int64: each undirected edge of ``faces`` once (lower index first), self-loops of
    degenerate faces left out."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    edges = np.sort(edges, axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    return np.unique(edges, axis=0) if len(edges) else edges.reshape(0, 2)


def mean_edge_length(positions: np.ndarray, faces: np.ndarray) -> float:
    """The mean length of the unique edges of a mesh (positions (V, 3), faces (F, 3))."""
    edges = unique_edges(faces)
    if not len(edges):
        raise ValueError("the mesh has no edges")
    return float(np.linalg.norm(positions[edges[:, 0]] - positions[edges[:, 1]], axis=1).mean())


def shape_id(shape: str) -> str:
    """A mesh's id from ``"shape"`` or its key ``"shape.vertex_positions"``."""
    if not isinstance(shape, str) or not shape:
        raise TypeError(f"a shape is named by its id (a string such as 'shape'), got {shape!r}")
    return shape.removesuffix(".vertex_positions")


def scene_mesh(scene: Any, shape: str) -> Any:
    """The ``mitsuba.Mesh`` of ``scene`` (a :class:`torchir.Scene`) whose id is ``shape``."""
    import mitsuba as mi

    name = shape_id(shape)
    meshes = {s.id(): s for s in scene.mi_scene.shapes() if isinstance(s, mi.Mesh)}
    if name not in meshes:
        raise KeyError(f"the scene has no mesh {name!r}; its meshes: {sorted(meshes)}")
    return meshes[name]
