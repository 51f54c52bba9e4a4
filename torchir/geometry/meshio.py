"""Mesh files: PLY written without Mitsuba (binary little-endian or ASCII, positions and
triangles, as Mitsuba's ``ply`` plugin reads them), PLY and OBJ read through Mitsuba's own loaders
(so a mesh reads as the renderer sees it: an OBJ's corners with different uvs or normals are
separate vertices)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ._mesh import as_faces, as_vertices

__all__ = ["write_mesh", "read_mesh"]

_FACE = np.dtype([("count", "u1"), ("index", "<i4", (3,))])  # packed, 13 bytes: as PLY stores a list


def write_mesh(path: str | os.PathLike, vertices: Any, faces: Any, binary: bool = True) -> Path:
    """Write a triangle mesh as PLY (float32 ``x y z`` per vertex, ``uchar int`` index lists).

    Args:
        path: the ``.ply`` file (its folder is created).
        vertices: ``(V, 3)`` or ``(3V,)``.
        faces: ``(F, 3)`` or ``(3F,)`` integer indices into the vertices.
        binary: binary little-endian (default) or ASCII.

    Returns:
        The path written.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"write_mesh writes PLY files: give a path ending in .ply, got {str(path)!r}")
    v = as_vertices(vertices).detach().to(torch.float32).cpu().numpy()
    f = as_faces(faces, v.shape[0])
    if not np.isfinite(v).all():
        raise ValueError("vertices have NaN/Inf entries")
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment written by torchir.geometry",
              f"element vertex {len(v)}", "property float x", "property float y", "property float z",
              f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            out.write(np.ascontiguousarray(v, dtype="<f4").tobytes())
            rows = np.empty(len(f), _FACE)
            rows["count"], rows["index"] = 3, f
            out.write(rows.tobytes())
        else:
            lines = [" ".join(f"{x:.9g}" for x in row) for row in v] + ["3 " + " ".join(map(str, row)) for row in f]
            out.write(("\n".join(lines) + "\n").encode("ascii"))
    return path


def read_mesh(path: str | os.PathLike, device: str | torch.device | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a PLY or OBJ mesh with Mitsuba's loader.

    Args:
        path: a ``.ply`` or ``.obj`` file.
        device: where the tensors go; None: the render device (:func:`torchir.backend.device`).

    Returns:
        ``(vertices (V, 3) float32, faces (F, 3) int64)``, the vertex list as Mitsuba loads it.
    """
    import mitsuba as mi

    from .. import backend

    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("ply", "obj"):
        raise ValueError(f"read_mesh reads .ply and .obj files, got {str(path)!r}")
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {str(path)!r}")
    backend.variant()
    mesh = mi.load_dict({"type": kind, "filename": str(path.resolve())})
    device = torch.device(backend.device() if device is None else device)
    v = np.array(mesh.vertex_positions_buffer(), dtype=np.float32).reshape(-1, 3)
    f = np.array(mesh.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    return torch.as_tensor(v, device=device), torch.as_tensor(f, device=device)
