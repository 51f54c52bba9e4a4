"""A triangle mesh's edges, for the estimators that sample visibility boundaries on them
(:mod:`._shadow_edges`, :mod:`._silhouettes`): each edge with the third vertex of its faces, and
the test that makes an edge a silhouette from a viewpoint."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..welding import mesh_weld, weld_map

CREASE_COSINE = 1e-4  # an edge whose second face leaves the first's plane by more is bent: a crease where shading is flat

__all__ = ["EdgeTable", "mesh_edges", "edges_of", "endpoints", "faces_side", "seen_whole", "has_open_border",
           "back_seen_past_border", "mitsuba_silhouettes_wrong"]


@dataclass(frozen=True)
class EdgeTable:
    """A mesh's edges: end vertices ``a``, ``b`` and the third vertex of each adjacent face
    (``c1``, ``c2``; ``c2 == c1`` for an edge with one face); ``crease``: whether the two faces
    reach an end of the edge through vertices of different normal groups (the shading may jump
    there: a flat-shaded or hard edge), or None where no groups were given."""

    a: np.ndarray
    b: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    crease: np.ndarray | None = None


def mesh_edges(faces: np.ndarray, positions: np.ndarray | None = None, groups: np.ndarray | None = None,
               flat: bool = False) -> EdgeTable:
    """Unique edges of a triangle list ``faces`` (F, 3), each with its adjacent faces' third
    vertices.

    With ``positions`` (V, 3), topology comes from positions, not indices
    (:func:`torchir.welding.weld_map`): vertices at one position are one, so uv seams, poles and
    flat-shaded splits are interior edges, and every index in the table is the first vertex at its
    position. An edge with one face (an open border) has ``c2 == c1``. An edge with more than two
    faces (non-manifold) keeps the two that bound the smallest wedge around it holding all of
    them: it outlines the mesh exactly when those two lie on one side of a plane through it; it is
    dropped when no such wedge is under a half turn (its faces surround it: never an outline).
    Faces that collapse to a line after welding are skipped. ``groups`` (V,), the normal group of
    each of the user's vertices (:class:`torchir.welding.MeshWeld`), fills ``crease``; with
    ``flat`` (the mesh is shaded with its face normals) every edge whose faces are not coplanar is
    a crease too, whether or not they share its vertices (``face_normals``, a mesh built without
    normals: only its uv seams would differ in group).
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    group = np.asarray(groups, np.int64) if groups is not None else np.arange(int(faces.max(initial=-1)) + 1)
    welded = faces
    if positions is not None:
        rep = weld_map(positions).astype(np.int64)
        welded = rep[faces]
        points = np.asarray(positions, np.float64).reshape(-1, 3)
    # per undirected edge: (third vertex, normal group at its smaller end, at its larger end) of each face
    sides: dict[tuple[int, int], list[tuple[int, int, int]]] = {}
    for (a, b, c), (oa, ob, oc) in zip(welded.tolist(), faces.tolist()):
        if a == b or b == c or c == a:
            continue
        for u, v, w, ou, ov in ((a, b, c, oa, ob), (b, c, a, ob, oc), (c, a, b, oc, oa)):
            gu, gv = int(group[ou]), int(group[ov])
            sides.setdefault((min(u, v), max(u, v)), []).append((w, gu, gv) if u < v else (w, gv, gu))
    rows = []
    for (u, v), faces_here in sides.items():
        faces_here = list({w: (w, gu, gv) for w, gu, gv in reversed(faces_here)}.values())[::-1]  # a doubled face is one side
        if len(faces_here) <= 2:
            pair = (faces_here[0], faces_here[-1])
        elif positions is not None:
            bound = _bounding_faces(points[u], points[v], points[[w for w, _, _ in faces_here]])
            if bound is None:
                continue
            pair = (faces_here[bound[0]], faces_here[bound[1]])
        else:
            pair = (faces_here[0], faces_here[1])
        (w1, gu1, gv1), (w2, gu2, gv2) = pair
        rows.append((u, v, w1, w2, int(gu1 != gu2 or gv1 != gv2)))
    table = np.array(rows, np.int64).reshape(-1, 5)
    columns = [np.ascontiguousarray(table[:, k].astype(np.uint32)) for k in range(4)]
    crease = table[:, 4].astype(bool) if groups is not None else None
    if flat and positions is not None and len(table):
        crease = (crease if crease is not None else False) | _bent(points, table)
    return EdgeTable(*columns, crease=crease)


def _bent(points: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Whether each edge's second face leaves the plane of its first (by more than
    ``CREASE_COSINE`` of the third vertex's distance): false for coplanar faces and open borders."""
    a, b, c1, c2 = (points[table[:, k]] for k in range(4))
    n1 = np.cross(b - a, c1 - a)
    n1 /= np.maximum(np.linalg.norm(n1, axis=1, keepdims=True), 1e-30)
    to_c2 = c2 - a
    to_c2 /= np.maximum(np.linalg.norm(to_c2, axis=1, keepdims=True), 1e-30)
    return np.abs(np.einsum("ek,ek->e", n1, to_c2)) > CREASE_COSINE


def _bounding_faces(a: np.ndarray, b: np.ndarray, thirds: np.ndarray) -> tuple[int, int] | None:
    """Of faces around the edge ``ab`` with third vertices ``thirds`` (k, 3), the two that bound
    the smallest wedge holding all of them (the ends of the largest angular gap between them), or
    None when every gap is under a half turn."""
    axis = (b - a) / max(np.linalg.norm(b - a), 1e-30)
    d = thirds - a
    d = d - np.outer(d @ axis, axis)
    e1 = d[0] / max(np.linalg.norm(d[0]), 1e-30)
    e2 = np.cross(axis, e1)
    angle = np.arctan2(d @ e2, d @ e1) % (2 * np.pi)
    order = np.argsort(angle)
    sorted_angles = angle[order]
    gaps = np.diff(np.concatenate([sorted_angles, sorted_angles[:1] + 2 * np.pi]))
    widest = int(np.argmax(gaps))
    if gaps[widest] <= np.pi:
        return None
    return int(order[(widest + 1) % len(order)]), int(order[widest])


def edges_of(mesh: mi.Mesh) -> EdgeTable:
    """:func:`mesh_edges` of ``mesh``'s faces with topology from its positions (as first seen:
    :func:`torchir.welding.mesh_weld`), computed once per weld."""
    weld = mesh_weld(mesh)
    if weld.edges is None:  # kept with the weld: both are fixed once the mesh is first seen
        weld.edges = mesh_edges(weld.faces, np.asarray(dr.detach(mesh.vertex_positions_buffer()), np.float32), weld.group,
                                flat=weld.flat)
    return weld.edges


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


def has_open_border(table: EdgeTable) -> bool:
    """Whether the mesh has an edge with one face (after welding): a real open border."""
    return bool(np.any(table.c1 == table.c2))


def back_seen_past_border(mesh: mi.Mesh, viewpoint: np.ndarray, scene: mi.Scene | None = None) -> bool:
    """Whether a face along one of ``mesh``'s open borders (after welding) turns its back to
    ``viewpoint``: where a camera there can see a one-sided material's back side past the border.
    With ``scene``, only borders that ``viewpoint`` sees unoccluded count (at three points along
    each such edge)."""
    weld = mesh_weld(mesh)
    faces = weld.welded_faces.astype(np.int64)
    corners = np.concatenate([faces[:, [0, 1, 2]], faces[:, [1, 2, 0]], faces[:, [2, 0, 1]]])  # (edge a, b, third)
    _, inverse, counts = np.unique(np.sort(corners[:, :2], axis=1), axis=0, return_inverse=True, return_counts=True)
    border = corners[counts[inverse.ravel()] == 1]
    if len(border) == 0:
        return False
    p = np.asarray(dr.detach(mesh.vertex_positions_buffer()), np.float64).reshape(-1, 3)
    a, b, c = p[border[:, 0]], p[border[:, 1]], p[border[:, 2]]
    eye = np.asarray(viewpoint, np.float64).ravel()
    back = np.einsum("fk,fk->f", np.cross(b - a, c - a), (a + b + c) / 3 - eye) > 0
    if scene is None or not back.any():
        return bool(back.any())
    a, b, c = a[back], b[back], c[back]
    points = np.concatenate([a + s * (b - a) + 1e-3 * (c - a) for s in (0.25, 0.5, 0.75)])
    to = mi.Point3f(*points.T.astype(np.float32))
    origin = mi.Point3f(*np.broadcast_to(eye[:, None], (3, len(points))).astype(np.float32))
    d = to - origin
    ray = mi.Ray3f(origin, dr.normalize(d))
    ray.maxt = dr.norm(d) * (1.0 - 1e-3)
    return bool(dr.any(~scene.ray_test(ray)))


def mitsuba_silhouettes_wrong(mesh: mi.Mesh) -> bool:
    """Whether Mitsuba's projective primary term is wrong for ``mesh``: on a flat-shaded or
    hard-edged mesh it misses the creases, where the shading jumps, and past an open border it
    shades a one-sided material's back as its front; right on smooth closed meshes (a UV sphere,
    once welded). Measurements: docs/shape-gradients.md, "Where Mitsuba's primary term is wrong"."""
    table = edges_of(mesh)
    return bool(table.crease.any()) or has_open_border(table)
