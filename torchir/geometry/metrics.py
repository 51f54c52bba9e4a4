"""Distances between two surfaces from area-uniform samples of each: the symmetric Chamfer
distance and the Hausdorff distance.

Each mesh is sampled ``samples`` times (uniformly by area); each sample's distance is to the
*nearest sample* of the other mesh (``scipy.spatial.cKDTree``), so a mesh against itself gives a
small positive "sampling floor" (about the squared spacing of the samples), not zero: report it
beside a result.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ._mesh import as_vertices, face_tensor

__all__ = ["sample_surface", "chamfer_distance", "hausdorff_distance", "chamfer_and_hausdorff"]

Mesh = tuple[Any, Any]  # (vertices (V, 3) or (3V,), faces (F, 3) or (3F,))


def _areas(v: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return 0.5 * torch.linalg.vector_norm(torch.linalg.cross(b - a, c - a), dim=1)


def sample_surface(vertices: Any, faces: Any, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` points uniformly distributed by area on a triangle mesh.

    A face is drawn with probability proportional to its area (zero-area faces never), then a
    point uniformly in it: ``(1 - √ξ1) a + √ξ1 (1 - ξ2) b + √ξ1 ξ2 c``.

    Args:
        vertices: ``(V, 3)`` or ``(3V,)`` floating tensor.
        faces: ``(F, 3)`` or ``(3F,)`` integer indices.
        n: the number of points.
        generator: the random numbers' source (drawn on its own device); None: torch's global
            generator of the vertices' device.

    Returns:
        ``(n, 3)`` on the vertices' device, in their dtype.

    Raises:
        ValueError: non-finite vertices, or a mesh of zero total area.

    Example:
        >>> v = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
        >>> f = torch.tensor([[0, 1, 2], [3, 3, 3]])          # the second face has no area
        >>> p = sample_surface(v, f, 1000, torch.Generator(device="cpu").manual_seed(0))
        >>> p.shape, bool((p[:, 2] == 0).all() and (p[:, :2].sum(1) <= 1 + 1e-6).all())
        (torch.Size([1000, 3]), True)
    """
    v = as_vertices(vertices)
    f = face_tensor(faces, v.shape[0], v.device)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError("the mesh has NaN/Inf vertex positions")
    areas = _areas(v.detach().to(torch.float64), f) if len(f) else v.new_zeros(0, dtype=torch.float64)
    cdf = torch.cumsum(areas, 0)
    total = cdf[-1] if len(cdf) else None
    if total is None or not bool(total > 0):
        raise ValueError(f"the mesh has no area ({len(f)} faces, all degenerate): nothing to sample")
    draw_device = generator.device if generator is not None else v.device
    xi = torch.rand(n, 3, generator=generator, dtype=torch.float64, device=draw_device).to(v.device)
    # right=True: a zero-area face repeats the cdf value before it, so no draw lands on it
    face = torch.searchsorted(cdf, xi[:, 0] * total, right=True).clamp_(max=len(f) - 1)
    r1, r2 = xi[:, 1].sqrt()[:, None], xi[:, 2][:, None]
    corners = v.to(torch.float64)[f[face]]  # (n, 3 corners, 3)
    points = (1 - r1) * corners[:, 0] + r1 * (1 - r2) * corners[:, 1] + r1 * r2 * corners[:, 2]
    return points.to(v.dtype)


def _directed(a: Mesh, b: Mesh, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances from ``samples`` points of ``a`` to the nearest of ``samples`` points of ``b``,
    and from those of ``b`` to ``a``'s (host float64: scipy's k-d tree)."""
    from scipy.spatial import cKDTree

    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples must be a positive int, got {samples!r}")
    generator = torch.Generator(device="cpu").manual_seed(int(seed))  # the same points on every device
    points = []
    for name, mesh in (("a", a), ("b", b)):
        if not isinstance(mesh, (tuple, list)) or len(mesh) != 2:
            raise TypeError(f"mesh {name} must be a (vertices, faces) pair, got {type(mesh).__name__}")
        v = as_vertices(mesh[0], f"vertices of mesh {name}")
        p = sample_surface(v.detach().to(device="cpu", dtype=torch.float64), mesh[1], samples, generator)
        points.append(p.cpu().numpy())
    pa, pb = points
    return cKDTree(pb).query(pa)[0], cKDTree(pa).query(pb)[0]


def chamfer_distance(a: Mesh, b: Mesh, samples: int = 20000, squared: bool = True, seed: int = 0) -> float:
    """The symmetric Chamfer distance between two meshes from ``samples`` area-uniform points of each.

    ``squared=True``: ``mean_a min_b |a - b|² + mean_b min_a |b - a|²``; ``squared=False``: the
    same with distances. Two concentric spheres of radii r1, r2 give about ``2 (r1 - r2)²``.
    Each nearest-sample query visits the other mesh's samples within its distance, so meshes far
    apart (compared with the samples' spacing) cost more than close ones.

    Args:
        a, b: ``(vertices, faces)``: vertices ``(V, 3)`` or ``(3V,)``, faces ``(F, 3)`` or ``(3F,)``.
        samples: points drawn on each mesh.
        squared: squared distances (the usual form) or distances.
        seed: the samples' seed (the same points on CPU and CUDA).

    Returns:
        A float.

    Example:
        >>> v = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> f = torch.tensor([[0, 1, 2]])
        >>> round(chamfer_distance((v, f), (v + torch.tensor([0, 0, 0.5]), f)), 3)   # 0.5² + 0.5²
        0.5
    """
    return _chamfer(*_directed(a, b, samples, seed), squared)


def hausdorff_distance(a: Mesh, b: Mesh, samples: int = 20000, seed: int = 0) -> float:
    """The Hausdorff distance between two meshes, ``max(max_a min_b |a - b|, max_b min_a |b - a|)``,
    from ``samples`` area-uniform points of each (arguments as :func:`chamfer_distance`); a float.
    Its sampling error is about the spacing of the samples (not its square)."""
    return _hausdorff(*_directed(a, b, samples, seed))


def chamfer_and_hausdorff(a: Mesh, b: Mesh, samples: int = 20000, seed: int = 0) -> tuple[float, float]:
    """``(chamfer_distance(a, b), hausdorff_distance(a, b))`` (squared Chamfer) from one draw of
    ``samples`` points of each mesh and one nearest-sample query each way: the same values as the
    two calls, at half their cost."""
    da, db = _directed(a, b, samples, seed)
    return _chamfer(da, db, squared=True), _hausdorff(da, db)


def _chamfer(da: np.ndarray, db: np.ndarray, squared: bool) -> float:
    """The Chamfer distance of the two directed nearest-sample distance lists of :func:`_directed`."""
    if squared:
        return float(np.mean(da**2) + np.mean(db**2))
    return float(np.mean(da) + np.mean(db))


def _hausdorff(da: np.ndarray, db: np.ndarray) -> float:
    """The Hausdorff distance of the two directed nearest-sample distance lists of :func:`_directed`."""
    return float(max(da.max(), db.max()))
