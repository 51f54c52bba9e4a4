"""Meshes of the geometry tests: a UV sphere as exporters write it (seam and poles repeated) and
its welded copy, from ``torchir.bench.exported_meshes``, and closed spheres of any radius."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.helpers import DEVICE
from torchir.bench.exported_meshes import uv_sphere
from torchir.geometry import read_mesh


def pooled(corners) -> tuple[torch.Tensor, torch.Tensor]:
    """The welded mesh behind an exporter's corners: its position pool and the faces' position indices."""
    v = torch.tensor(np.array(corners.v), dtype=torch.float32, device=DEVICE)
    f = torch.tensor([[corner[0] for corner in face] for face in corners.faces], dtype=torch.int64, device=DEVICE)
    return v, f


@pytest.fixture(scope="module")
def split_sphere(exported) -> tuple[torch.Tensor, torch.Tensor]:
    """The exported UV sphere's PLY as Mitsuba loads it: 185 vertices at 146 positions."""
    return read_mesh(exported["uv_sphere"]["ply"], device=DEVICE)


@pytest.fixture(scope="module")
def welded_sphere() -> tuple[torch.Tensor, torch.Tensor]:
    """The same UV sphere, welded: one vertex per position (146)."""
    return pooled(uv_sphere())


@pytest.fixture(scope="module")
def sphere():
    """``sphere(radius, segments, rings)``: a closed welded UV sphere about the origin."""
    return lambda radius=0.5, segments=16, rings=10: pooled(uv_sphere(segments=segments, rings=rings, radius=radius))
