"""A triangle mesh's edges, for the estimators that sample visibility boundaries on them
(:mod:`._shadow_edges`, :mod:`._silhouettes`): each edge with the third vertex of its faces, and
the test that makes an edge a silhouette from a viewpoint."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["EdgeTable", "mesh_edges", "edges_of", "endpoints", "faces_side", "seen_whole"]


@dataclass(frozen=True)
class EdgeTable:
    """A mesh's edges: end vertices ``a``, ``b`` and the third vertex of each adjacent face
    (``c1``, ``c2``; ``c2 == c1`` for an edge with one face)."""

    a: np.ndarray
    b: np.ndarray
    c1: np.ndarray
    c2: np.ndarray


def mesh_edges(faces: np.ndarray) -> EdgeTable:
    """Unique edges of a triangle list ``faces`` (F, 3), each with its adjacent faces' third
    vertices (the first two faces of a non-manifold edge)."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    third: dict[tuple[int, int], list[int]] = {}
    for a, b, c in faces.tolist():
        for u, v, w in ((a, b, c), (b, c, a), (c, a, b)):
            third.setdefault((min(u, v), max(u, v)), []).append(w)
    keys = list(third)
    a = np.array([k[0] for k in keys], np.uint32)
    b = np.array([k[1] for k in keys], np.uint32)
    c1 = np.array([third[k][0] for k in keys], np.uint32)
    c2 = np.array([third[k][1] if len(third[k]) > 1 else third[k][0] for k in keys], np.uint32)
    return EdgeTable(a, b, c1, c2)


def edges_of(mesh: mi.Mesh) -> EdgeTable:
    """:func:`mesh_edges` of ``mesh``'s faces, cached by their content."""
    return _edges_of_faces(np.asarray(mesh.faces_buffer(), np.uint32).tobytes())


@functools.lru_cache(maxsize=64)
def _edges_of_faces(faces_bytes: bytes) -> EdgeTable:
    return mesh_edges(np.frombuffer(faces_bytes, np.uint32))


def endpoints(mesh: mi.Mesh, table: EdgeTable, edge: mi.UInt32 | None = None):
    """World positions ``(a, b, c1, c2)`` of the edges' ends and third vertices (all edges, or
    those indexed by ``edge``); differentiable where the vertices are."""
    def vertex(index):
        index = mi.UInt32(index)
        return mesh.vertex_position(index if edge is None else dr.gather(mi.UInt32, index, edge))
    return vertex(table.a), vertex(table.b), vertex(table.c1), vertex(table.c2)


def faces_side(normal, point, third1, third2):
    """``(side, silhouette)`` of an edge through ``point`` against the plane of normal
    ``normal`` that holds it and a viewpoint: ``side`` the sign on which the first face lies,
    ``silhouette`` whether both faces lie on that side (the edge outlines the mesh from there)."""
    side = dr.sign(dr.dot(normal, third1 - point))
    return side, side == dr.sign(dr.dot(normal, third2 - point))


def seen_whole(sensor: mi.Sensor, meshes: list) -> bool:
    """``meshes`` are triangle meshes, none an emitter, seen by a pinhole perspective sensor
    whose film has no crop window: what both edge estimators need."""
    if not meshes or not all(isinstance(m, mi.Mesh) and not m.is_emitter() for m in meshes):
        return False
    film = sensor.film()
    if tuple(film.crop_size()) != tuple(film.size()) or tuple(film.crop_offset()) != (0, 0):
        return False
    return str(sensor).startswith("PerspectiveCamera")
