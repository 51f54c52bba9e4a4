"""Large Steps: optimise a mesh through the latent ``u = (I + λL) x`` (Nicolet, Jacobson and Jakob
2021, "Large Steps in Inverse Rendering of Geometry").

``L`` is the combinatorial graph Laplacian of the *surface*: exporters repeat a vertex wherever a
corner attribute changes (uv seams, a UV sphere's poles), so vertices are welded by position first
(:func:`torchir.welding.weld_map`), as ``mitsuba.ad.LargeSteps`` does; the unknowns are the welded
vertices. ``I + λL`` is factorised once (``cholespy``, on the device of the tensors it solves);
each step then costs two triangular solves, and its gradient is the same solve (the matrix is
symmetric).
"""
from __future__ import annotations

import atexit
import weakref
from typing import Any

import numpy as np
import torch

from ._mesh import Weld, as_faces, as_vertices, host_positions, scene_mesh, unique_edges, weld, weld_positions

__all__ = ["LargeSteps"]

DEFAULT_LAMBDA = 19.0  # mitsuba.ad.LargeSteps' default; Mitsuba's shape tutorial uses 25


class _Factor:
    """The Cholesky factor of ``I + λL`` on one device, for one dtype (float32 or float64)."""

    def __init__(self, n: int, rows: np.ndarray, cols: np.ndarray, values: np.ndarray, device: torch.device,
                 dtype: torch.dtype) -> None:
        from cholespy import CholeskySolverD, CholeskySolverF, MatrixType

        solver = CholeskySolverD if dtype == torch.float64 else CholeskySolverF
        # cholespy factorises where its index arrays live (CPU or CUDA); the values are float64 for both
        as_device = lambda a, t: torch.as_tensor(a, dtype=t, device=device).contiguous()  # noqa: E731
        self.solver = solver(n, as_device(rows, torch.int32), as_device(cols, torch.int32), as_device(values, torch.float64),
                             MatrixType.COO)
        _LIVE_FACTORS.add(self)

    def solve(self, b: torch.Tensor) -> torch.Tensor:
        b = b.detach().contiguous()
        x = torch.empty_like(b)
        self.solver.solve(b, x)
        return x


_LIVE_FACTORS: "weakref.WeakSet[_Factor]" = weakref.WeakSet()


@atexit.register
def _free_factors() -> None:
    """Free the solvers still alive at exit (held by an autograd graph or a run's module):
    nanobind printed "leaked instance ... CholeskySolverF" after every Large Steps run."""
    for factor in list(_LIVE_FACTORS):
        factor.solver = None


class _Solve(torch.autograd.Function):
    """``x = (I + λL)^{-1} b``; its backward is the same solve of the incoming gradient (the
    matrix is symmetric), through this Function again, so it differentiates to any order."""

    @staticmethod
    def forward(ctx: Any, b: torch.Tensor, factor: _Factor) -> torch.Tensor:
        ctx.factor = factor
        return factor.solve(b)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        return _Solve.apply(grad, ctx.factor), None


class LargeSteps:
    """The Large Steps parameterisation of one mesh: ``u = (I + λL) x`` on its welded surface.

    Args:
        mesh: a :class:`torchir.Scene`, or the mesh's vertices ``(V, 3)`` or flat ``(3V,)``.
        shape: with a scene, the mesh's id (``"shape"`` or ``"shape.vertex_positions"``); else
            the faces ``(F, 3)`` (or flat ``(3F,)``) indexing the vertices.
        lambda_: ``λ >= 0``, how far a gradient spreads over the surface (larger for finer meshes).
            The default is ``mitsuba.ad.LargeSteps``' (19); Mitsuba's shape tutorial uses 25.

    Vertices at bit-identical float32 positions (seam copies) are one unknown:
    :meth:`from_differential` gives every copy the same position, and the gradients of the copies
    sum. The factorisation is made on the device of the vertices (a scene: its render device), in
    float32 unless the vertices are float64, and again for another device or dtype when one is
    first solved.

    Shape:
        ``x`` (the file's vertex list): ``(V, 3)`` or flat ``(3V,)`` as Mitsuba's
        ``vertex_positions``; ``u`` (the welded vertices): ``(n, 3)`` or ``(3n,)``, in ``x``'s layout.

    Example:
        >>> v = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> ls = LargeSteps(v, f, lambda_=10.0)
        >>> u = ls.to_differential(v).requires_grad_()
        >>> x = ls.from_differential(u)          # differentiable: (I + λL)^{-1} u
        >>> torch.allclose(x, v, atol=1e-5), ls.welded_count
        (True, 4)
    """

    def __init__(self, mesh: Any, shape: Any, lambda_: float = DEFAULT_LAMBDA) -> None:
        from .. import backend
        from ..scene import Scene

        lambda_ = float(lambda_)
        if not np.isfinite(lambda_) or lambda_ < 0:
            raise ValueError(f"lambda_ must be finite and >= 0, got {lambda_}")
        self.lambda_ = lambda_
        if isinstance(mesh, Scene):
            mi_mesh = scene_mesh(mesh, shape)
            mesh.spread_steps.add(mi_mesh.id())
            loaded = mesh.mesh_weld(mi_mesh)  # the weld the scene made when it loaded (as its boundary terms use)
            self._weld = weld(loaded.rep, loaded.faces.astype(np.int64))
            self.device, self.dtype = torch.device(backend.device()), torch.float32
        else:
            vertices = as_vertices(mesh)
            if vertices.dtype not in (torch.float32, torch.float64):
                raise TypeError(f"vertices must be float32 or float64, got {vertices.dtype}")
            faces = as_faces(shape, vertices.shape[0])
            self._weld = weld_positions(host_positions(vertices), faces)
            self.device, self.dtype = vertices.device, vertices.dtype
        self._rows, self._cols, self._values = _system_matrix(self._weld, lambda_)
        self._factors: dict[tuple[torch.device, torch.dtype], _Factor] = {}
        self._indices: dict[torch.device, tuple[torch.Tensor, ...]] = {}
        self._factor(self.device, self.dtype)  # once per topology, where the mesh lives

    # ---------------------------------------------------------------------------- queries
    @property
    def vertex_count(self) -> int:
        """``V``: the vertices of the file's list (seam copies included)."""
        return len(self._weld.welded_index)

    @property
    def welded_count(self) -> int:
        """``n``: the welded vertices (the unknowns)."""
        return self._weld.count

    @property
    def welded_index(self) -> torch.Tensor:
        """``(V,)`` int64: each file vertex's welded vertex."""
        return self._device_indices(self.device)[2]

    @property
    def welded_faces(self) -> torch.Tensor:
        """``(F, 3)`` int64: the faces on the welded vertices."""
        return torch.as_tensor(self._weld.faces, device=self.device)

    def matrix(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``I + λL`` as a coalesced sparse ``(n, n)`` tensor on the mesh's device."""
        index = torch.as_tensor(np.stack([self._rows, self._cols]), device=self.device)
        values = torch.as_tensor(self._values, dtype=dtype, device=self.device)
        # the entries are unique and sorted by (row, column): coalesced as built
        return torch.sparse_coo_tensor(index, values, (self.welded_count,) * 2, is_coalesced=True, check_invariants=False)

    # ----------------------------------------------------------------------- conversions
    def to_differential(self, x: torch.Tensor) -> torch.Tensor:
        """``u = (I + λL) x`` of the welded vertices (each takes its first copy's position);
        differentiable. ``x`` ``(V, 3)`` or ``(3V,)``; ``u`` ``(n, 3)`` or ``(3n,)`` likewise."""
        points = self._check(x, self.vertex_count, "x")
        rows, cols, _, representative = self._device_indices(points.device)
        welded = points[representative]
        values = torch.as_tensor(self._values, dtype=points.dtype, device=points.device)
        u = torch.zeros_like(welded).index_add_(0, rows, welded[cols] * values[:, None])
        return u.reshape(-1) if x.dim() == 1 else u

    def from_differential(self, u: torch.Tensor) -> torch.Tensor:
        """``x = (I + λL)^{-1} u`` on the file's vertex list (copies share their welded vertex's
        position); differentiable (the backward is the same solve). ``u`` ``(n, 3)`` or ``(3n,)``;
        ``x`` ``(V, 3)`` or ``(3V,)`` likewise."""
        welded = self._check(u, self.welded_count, "u")
        _, _, welded_index, _ = self._device_indices(welded.device)
        x = _Solve.apply(welded, self._factor(welded.device, welded.dtype))[welded_index]
        return x.reshape(-1) if u.dim() == 1 else x

    def __repr__(self) -> str:
        return f"LargeSteps(vertices={self.vertex_count}, welded={self.welded_count}, lambda_={self.lambda_})"

    # --------------------------------------------------------------------------- helpers
    def _check(self, t: torch.Tensor, count: int, name: str) -> torch.Tensor:
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{name} must be float32 or float64, got {t.dtype}")
        if tuple(t.shape) not in ((count, 3), (3 * count,)):
            raise ValueError(f"{name} must be ({count}, 3) or ({3 * count},), got {tuple(t.shape)}")
        return t.reshape(count, 3)

    def _device_indices(self, device: torch.device) -> tuple[torch.Tensor, ...]:
        if device not in self._indices:
            self._indices[device] = tuple(torch.as_tensor(a, device=device) for a in (
                self._rows, self._cols, self._weld.welded_index, self._weld.representative))
        return self._indices[device]

    def _factor(self, device: torch.device, dtype: torch.dtype) -> _Factor:
        key = (torch.device(device), dtype)
        if key not in self._factors:
            self._factors[key] = _Factor(self.welded_count, self._rows, self._cols, self._values, key[0], dtype)
        return self._factors[key]


def _system_matrix(w: Weld, lambda_: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``I + λL`` in COO form (rows, cols int64; values float64), each entry once: ``1 + λ deg(i)``
    on the diagonal and ``-λ`` per edge (both directions)."""
    n = w.count
    edges = unique_edges(w.faces) if w.faces.size else np.zeros((0, 2), np.int64)
    degree = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    diagonal = np.arange(n, dtype=np.int64)
    rows = np.concatenate([diagonal, edges[:, 0], edges[:, 1]])
    cols = np.concatenate([diagonal, edges[:, 1], edges[:, 0]])
    values = np.concatenate([1.0 + lambda_ * degree, np.full(2 * len(edges), -lambda_)])
    order = np.lexsort((cols, rows))
    return rows[order], cols[order], values[order]
