"""Meshes whose faces do not share the vertices at one position, for visibility-boundary terms.

Exporters split a vertex wherever a corner attribute changes: along uv seams, at a UV sphere's
poles, at every corner of a flat-shaded mesh, on each face of Mitsuba's ``cube``. Shading needs
those copies, but a boundary term needs the surface's topology: an edge whose two faces reach it
through different copies is interior, not an open border. Mitsuba's projective integrators
(``direct_projective``, ``prb_projective``) and torchir's own edge estimators build edges from
vertex *indices*, so on such a mesh they take every seam for a border that is always on the
silhouette and add a boundary term where the surface is smooth.

Here topology comes from *positions*: vertices at bit-identical positions (as exporters write
them) are one. :func:`weld_map` gives each vertex the index of the first vertex at its position;
:class:`WeldedFaces` rebinds a scene's moving meshes to faces that index only those
representatives for the duration of a boundary pass, and binds the user's faces again after it.
Positions are untouched, so the surface is the same and gradients reach the user's vertex buffer
(the boundary part of each welded vertex's derivative lands on its first copy: the derivative of
moving all copies of a vertex together, the only motion that keeps the surface closed, is exact).
During the pass a seam copy's uv is its representative's, and shading normals are those of the
welded surface: recomputed across the seams (as Mitsuba recomputes a moving mesh's normals), or,
for a flat-shaded export (every normal its face's), face normals.
"""
from __future__ import annotations

import hashlib
import weakref
from collections.abc import Iterable, Mapping
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from .backend import jit_array

__all__ = ["weld_map", "mesh_weld", "weld_of", "keep_loaded_welds", "MeshWeld", "WeldedFaces", "moving_meshes", "group_normals"]


def weld_map(positions: np.ndarray) -> np.ndarray:
    """``(V,)`` uint32: for each vertex of ``positions`` (``(V, 3)`` or flat ``(3 V,)``), the
    index of the first vertex at a bit-identical position (``-0.0`` and ``0.0`` are one)."""
    p = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    if p.shape[0] == 0:
        return np.zeros(0, np.uint32)
    p = np.ascontiguousarray(p + np.float32(0.0))  # -0.0 + 0.0 == +0.0 in IEEE arithmetic
    _, first, inverse = np.unique(p.view(np.dtype((np.void, 12))).ravel(), return_index=True, return_inverse=True)
    return first[inverse.ravel()].astype(np.uint32)


class MeshWeld:
    """A mesh's weld, from the positions and normals it was loaded with.

    ``rep`` (V,): the first vertex at each vertex's position; ``faces`` (F, 3) the user's faces
    and ``welded_faces`` the same through ``rep``; ``group`` (V,): the first vertex at the same
    position with the same loaded normal (copies along a uv seam share one, the corners of a
    flat-shaded or hard-edged export do not); ``flat``: the shading normals are the faces'
    (none, or every normal its face's); ``merges``: some group holds several copies."""

    def __init__(self, faces: np.ndarray, positions: np.ndarray, normals: np.ndarray | None) -> None:
        self.faces = np.asarray(faces, np.uint32).reshape(-1, 3)
        self.rep = weld_map(positions)
        self.welded_faces = self.rep[self.faces]
        self.repeats = int(len(self.rep) - len(np.unique(self.rep)))
        has_normals = normals is not None and len(normals) > 0
        self.flat = not has_normals or _normals_are_face_normals(self.faces, positions, normals)
        if has_normals and not self.flat:
            key = np.concatenate([self.rep[:, None].astype(np.int64),
                                  np.round(np.asarray(normals, np.float64).reshape(-1, 3) * 1e3).astype(np.int64)], axis=1)
            _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
            self.group = first[inverse.ravel()].astype(np.uint32)
        else:
            self.group = np.arange(len(self.rep), dtype=np.uint32)
        self.merges = bool(np.any(self.group != np.arange(len(self.group))))
        self.edges: Any = None  # the mesh's edge table, built on first use (integrators._mesh_edges.edges_of)
        self._jit: dict[str, Any] = {}

    def jit(self, name: str) -> Any:
        """A Dr.Jit array of this topology, made once and kept (so every step's kernels read the
        same buffer): ``"welded_faces"`` (3F,); ``"group"`` (V,); ``"corner_k"`` (F,), the
        position offsets ``3 * faces[:, k]``; ``"corner_group_k"`` (F,), ``group[faces[:, k]]``."""
        if name not in self._jit:
            if name == "welded_faces":
                values = self.welded_faces.ravel()
            elif name == "group":
                values = self.group
            elif name.startswith("corner_group_"):
                values = self.group[self.faces[:, int(name[-1])]]
            elif name.startswith("corner_"):
                values = 3 * self.faces[:, int(name[-1])]
            else:
                raise KeyError(name)
            self._jit[name] = jit_array(mi.UInt32, values.astype(np.uint32))
        return self._jit[name]

    @property
    def welded(self) -> bool:
        """Whether no two vertices share a position (faces already share their edges' vertices)."""
        return self.repeats == 0


def _normals_are_face_normals(faces: np.ndarray, positions: np.ndarray, normals: np.ndarray) -> bool:
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    face_n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-30)
    return bool(np.all(np.einsum("fk,fck->fc", face_n, n[faces]) > 1 - 1e-4))


def group_normals(mesh: mi.Mesh, weld: MeshWeld) -> mi.Float:
    """Vertex normals of ``mesh`` at its current positions, each the angle-weighted mean of the
    face normals around its normal group (``weld.group``; Mitsuba's weighting), flat ``(3 V,)``;
    differentiable where the positions are. Mitsuba recomputes a moving mesh's normals over its index topology, which
    turns every uv seam into a shading crease; these are smooth across seams and keep the
    exporter's hard edges."""
    # explicit gathers: through dr.unravel, Dr.Jit 1.5's reverse mode dropped the positions'
    # other uses (d/dt of sum(P) + sum(unravel(P).x) came out 15 where it is 20)
    positions = mesh.vertex_positions_buffer()

    def corner(k: int) -> mi.Vector3f:
        index = weld.jit(f"corner_{k}")
        return mi.Vector3f(*(dr.gather(mi.Float, positions, index + axis) for axis in range(3)))

    v = [corner(0), corner(1), corner(2)]
    n = dr.normalize(dr.cross(v[1] - v[0], v[2] - v[0]))
    total = [dr.zeros(mi.Float, len(weld.group)) for _ in range(3)]
    for k in range(3):  # weighted by the face's angle at the corner, as Mitsuba weighs them
        angle = dr.safe_acos(dr.dot(dr.normalize(v[(k + 1) % 3] - v[k]), dr.normalize(v[(k + 2) % 3] - v[k])))
        group = weld.jit(f"corner_group_{k}")
        for axis in range(3):
            dr.scatter_add(total[axis], n[axis] * angle, group)
    group = weld.jit("group")
    summed = mi.Vector3f(*(dr.gather(mi.Float, t, group) for t in total))
    return dr.ravel(dr.normalize(summed))


_WELDS: dict[tuple[int, bytes], tuple[bytes, MeshWeld]] = {}  # meshes outside a torchir.Scene
_OWNERS: weakref.WeakSet = weakref.WeakSet()  # torchir.Scenes: mesh_weld asks their own first


def keep_loaded_welds(owner: Any) -> None:
    """Register ``owner`` (a :class:`torchir.Scene`): while it lives, :func:`mesh_weld` takes the
    weld of one of its meshes from ``owner.mesh_weld(mesh)`` (None: not its mesh)."""
    _OWNERS.add(owner)
_WELDS_LIMIT = 64


def _digest(*arrays: np.ndarray | None) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
    return h.digest()


def _loaded_state(mesh: mi.Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``mesh``'s faces, positions and vertex normals (None without) as they are now."""
    faces = np.asarray(mesh.faces_buffer(), np.uint32)
    positions = np.asarray(dr.detach(mesh.vertex_positions_buffer()), np.float32)
    normals = np.asarray(dr.detach(mesh.vertex_normals_buffer()), np.float32) if mesh.has_vertex_normals() else None
    return faces, positions, normals


def weld_of(mesh: mi.Mesh) -> MeshWeld:
    """A fresh :class:`MeshWeld` of ``mesh`` as it is now (its positions and normals)."""
    return MeshWeld(*_loaded_state(mesh))


def mesh_weld(mesh: mi.Mesh) -> MeshWeld:
    """``mesh``'s :class:`MeshWeld`, from the positions and normals it was loaded with.

    A mesh of a live :class:`torchir.Scene` gets the weld the scene made when it loaded
    (``Scene.mesh_weld``): exact for as long as the scene lives, however far its vertices moved
    since. Another mesh (loaded with Mitsuba alone) is welded when first seen and the weld kept
    while its faces, positions and normals are those it was welded with; a mesh that differs is
    welded afresh (keyed by identity alone, a later mesh at a freed one's address was given the
    freed one's weld)."""
    for owner in list(_OWNERS):
        weld = owner.mesh_weld(mesh)
        if weld is not None:
            return weld
    faces, positions, normals = _loaded_state(mesh)
    key, state = (id(mesh), _digest(faces)), _digest(positions, normals)
    kept = _WELDS.get(key)
    if kept is None or kept[0] != state:
        if kept is None and len(_WELDS) >= _WELDS_LIMIT:
            _WELDS.pop(next(iter(_WELDS)))
        kept = _WELDS[key] = (state, MeshWeld(faces, positions, normals))
    return kept[1]


def moving_meshes(scene: mi.Scene, params: Mapping[str, Any] | None) -> list[mi.Mesh]:
    """The meshes of ``scene`` whose ``<id>.vertex_positions`` in ``params`` are grad-enabled."""
    names = {name[: -len(".vertex_positions")] for name, value in (params or {}).items()
             if name.endswith(".vertex_positions") and dr.grad_enabled(value)}
    return [shape for shape in scene.shapes() if isinstance(shape, mi.Mesh) and shape.id() in names] if names else []


class WeldedFaces:
    """Context manager: inside it, each of ``meshes`` that repeats positions has welded faces
    (and, where its copies' normals differ, face normals); on exit the user's faces and normals
    are bound again. ``params`` is the scene's :func:`mitsuba.traverse`. With nothing to weld it
    does nothing.

    Welded faces list the same triangles in the same order (each corner moved to the first copy
    at its position), so the acceleration structure built for either serves both: Mitsuba
    computes a hit from the face index and its current faces. It is rebuilt, going in and back,
    only where the pass inside needs what Mitsuba derives with it: ``indirect`` (the pass samples
    indirect silhouettes, whose edge distribution Mitsuba rebuilds only when positions change)
    or a flat-shaded mesh (its vertex normals are dropped); else faces and normals are swapped
    alone, both ways, and the structure keeps the user's faces (``docs/geometry.md``, the shape step).

    Example:
        >>> with WeldedFaces(mi.traverse(scene), moving_meshes):  # doctest: +SKIP
        ...     boundary_integrator.render_backward(scene, params, grad_in, sensor)
    """

    def __init__(self, params: Any, meshes: Iterable[mi.Mesh], indirect: bool = True) -> None:
        self.params = params
        self.indirect = indirect
        self.todo = []
        for mesh in meshes:
            if not isinstance(mesh, mi.Mesh):
                continue
            weld = mesh_weld(mesh)
            if not weld.welded:
                self.todo.append((mesh, weld))
        self._saved: list[tuple[str, Any]] = []

    def __bool__(self) -> bool:
        return bool(self.todo)

    def __enter__(self) -> "WeldedFaces":
        if not self.todo:
            return self
        for mesh, weld in self.todo:
            name = mesh.id()
            self._swap(f"{name}.faces", weld.jit("welded_faces"))
            if mesh.has_vertex_normals():  # flat: face normals; smooth: its group normals, below
                self._swap(f"{name}.vertex_normals", dr.zeros(mi.Float, 0) if weld.flat else self.params[f"{name}.vertex_normals"])
        self._update_faces(rebuild=self._rebuilds)
        smooth = [(mesh, weld) for mesh, weld in self.todo if mesh.has_vertex_normals() and not weld.flat]
        self._set_normals({f"{mesh.id()}.vertex_normals": group_normals(mesh, weld) for mesh, weld in smooth})
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self._saved:
            return
        saved, self._saved = self._saved, []
        for key, value in reversed(saved):
            self.params[key] = value
            self.params.set_dirty(key)
        self._update_faces(rebuild=self._rebuilds)  # as going in: a structure built for the welded faces must not outlive them
        self._set_normals({key: value for key, value in saved if key.endswith(".vertex_normals")})

    @property
    def _rebuilds(self) -> bool:
        """Whether the swaps rebuild the acceleration structure (both ways alike)."""
        return self.indirect or any(weld.flat for _, weld in self.todo)

    def _update_faces(self, rebuild: bool) -> None:
        # A change of faces alone rebuilds Mitsuba's directed edges (its primary silhouettes);
        # ``rebuild`` marks the positions too: Mitsuba then rebuilds its indirect edge-sampling
        # distribution (after a change of faces alone its indirect silhouettes were drawn from
        # the old topology's: twice the gradient of a welded box), the acceleration structure
        # and the normals.
        if rebuild:
            for mesh, _ in self.todo:
                self.params.set_dirty(f"{mesh.id()}.vertex_positions")
        self.params.update()

    def _set_normals(self, normals: dict[str, Any]) -> None:
        """Bind ``normals`` over the ones Mitsuba recomputed (a second update: normals alone)."""
        for key, value in normals.items():
            self.params[key] = value
            self.params.set_dirty(key)
        if normals:
            self.params.update()

    def _swap(self, key: str, value: Any) -> None:
        current = self.params[key]
        self._saved.append((key, type(current)(current)))  # a new reference: assignment replaces in place
        self.params[key] = value
        self.params.set_dirty(key)
