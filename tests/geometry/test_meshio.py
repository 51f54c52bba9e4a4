"""Mesh files: PLY written by torchir reads back through Mitsuba's own ``ply`` plugin with the
same positions and faces (binary and ASCII), and ``read_mesh`` returns what Mitsuba loads, for
PLY and for an exporter's OBJ (whose corners become vertices)."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest
import torch

from tests.helpers import DEVICE, raised_message
from torchir.bench.exported_meshes import uv_sphere
from torchir.geometry import read_mesh, remesh, write_mesh


@pytest.mark.parametrize("binary", [True, False])
def test_written_ply_is_read_by_mitsuba_with_the_same_positions_and_faces(tmp_path, split_sphere, binary):
    """Positions that need all of float32's digits (a remeshed sphere, then scaled by 1/3)
    survive exactly, in the file's vertex order; faces likewise."""
    v, f = remesh(*split_sphere, edge_length=0.15)
    v = v / 3
    path = write_mesh(tmp_path / "out.ply", v, f, binary=binary)
    mesh = mi.load_dict({"type": "ply", "filename": str(path)})
    np.testing.assert_array_equal(np.array(mesh.vertex_positions_buffer()).reshape(-1, 3), v.cpu().numpy())
    np.testing.assert_array_equal(np.array(mesh.faces_buffer()).reshape(-1, 3), f.cpu().numpy())
    v_read, f_read = read_mesh(path, device=DEVICE)
    assert v_read.dtype == torch.float32 and f_read.dtype == torch.int64 and v_read.device == v.device
    assert bool((v_read == v).all()) and bool((f_read == f).all())


def test_read_mesh_of_an_obj_is_mitsubas_load(exported):
    """The exporter's OBJ (separate position, uv and normal pools): Mitsuba makes one vertex per
    distinct corner, and ``read_mesh`` gives that list; every face's corners are at the pool's
    positions of the face as written."""
    v, f = read_mesh(exported["uv_sphere"]["obj"], device=DEVICE)
    mesh = mi.load_dict({"type": "obj", "filename": str(exported["uv_sphere"]["obj"])})
    assert v.shape == (mesh.vertex_count(), 3) and f.shape == (mesh.face_count(), 3)
    np.testing.assert_array_equal(v.cpu().numpy().ravel(), np.array(mesh.vertex_positions_buffer()))
    written = uv_sphere()
    pool = np.array(written.v, dtype=np.float32)
    corners = np.array([[c[0] for c in face] for face in written.faces])
    np.testing.assert_allclose(v.cpu().numpy()[f.cpu().numpy()], pool[corners], rtol=0, atol=1e-6)  # OBJ text: 7 digits


def test_bad_paths_and_values_are_refused(tmp_path):
    v = torch.zeros(3, 3, device=DEVICE)
    f = torch.tensor([[0, 1, 2]], device=DEVICE)
    assert "ending in .ply" in raised_message(ValueError, write_mesh, tmp_path / "a.obj", v, f)
    assert "NaN/Inf" in raised_message(ValueError, write_mesh, tmp_path / "a.ply", v * float("nan"), f)
    assert "not found" in raised_message(FileNotFoundError, read_mesh, tmp_path / "missing.ply")
    assert "reads .ply and .obj" in raised_message(ValueError, read_mesh, tmp_path / "a.stl")
