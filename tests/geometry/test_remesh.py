"""Remeshing (Botsch-Kobbelt through gpytoolbox) on the welded surface: the surface stays, the
edges take the asked length (so the vertex count is the one the area implies), seams are welded
first, and a scene's mesh is replaced in a new scene that renders as the old one did."""
from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir
from tests.helpers import DEVICE, raised_message
from torchir.functions import render
from torchir.geometry import LargeSteps, chamfer_distance, remesh, remesh_scene
from torchir.geometry.remesh import _gpytoolbox

RADIUS = 0.5  # the exported UV sphere's


def edges(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unique undirected edges of ``f`` and how many faces each borders."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def mean_edge(v: np.ndarray, f: np.ndarray) -> float:
    e, _ = edges(f)
    return float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())


def area(v: np.ndarray, f: np.ndarray) -> float:
    p = v[f]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


@pytest.mark.parametrize("relative", [None, 1.0, 0.3])
def test_remesh_keeps_the_surface_with_the_asked_edge_length(welded_sphere, split_sphere, relative):
    """The exported (seamed) sphere remeshed to h (None: half its mean edge, the tutorial's): a
    closed surface (every edge between two faces), mean edge within 15 % of h, about
    ``F = S / (√3/4 h²)`` equilateral faces and ``V = F/2 + 2`` vertices (genus 0; within 10 %),
    and Chamfer² to the old mesh below the two sampling floors plus ``2 δ²``, where δ is the sag
    ``L²/(8R)`` of the old mesh's longest edge L over the sphere (new vertices lie on the old
    surface, both meshes' chords lie within δ of the sphere)."""
    v, f = split_sphere
    vw, fw = welded_sphere[0].double().cpu().numpy(), welded_sphere[1].cpu().numpy()
    h = 0.5 * mean_edge(vw, fw) if relative is None else relative * mean_edge(vw, fw)
    v_new, f_new = remesh(v, f, edge_length=None if relative is None else h)
    assert v_new.dtype == v.dtype and v_new.device == v.device and f_new.dtype == torch.int64
    vn, fn = v_new.double().cpu().numpy(), f_new.cpu().numpy()
    _, borders = edges(fn)
    assert bool((borders == 2).all())
    assert mean_edge(vn, fn) == pytest.approx(h, rel=0.15)
    expected_vertices = area(vw, fw) / (math.sqrt(3) / 4 * h * h) / 2 + 2
    assert len(vn) == pytest.approx(expected_vertices, rel=0.10)
    e, _ = edges(fw.astype(np.int64))
    sag = np.linalg.norm(vw[e[:, 0]] - vw[e[:, 1]], axis=1).max() ** 2 / (8 * RADIUS)
    bound = chamfer_distance((v, f), (v, f)) + chamfer_distance((v_new, f_new), (v_new, f_new)) + 2 * sag**2
    assert chamfer_distance((v_new, f_new), (v, f)) < bound


def test_seams_are_welded_before_remeshing(split_sphere):
    """Remeshed as the file lists it, the seam and poles are open borders that gpytoolbox keeps
    (and splits) as borders; torchir welds them first, so its result is closed. Both keep dtype."""
    v, f = split_sphere
    raw_v, raw_f = _gpytoolbox().remesh_botsch(v.double().cpu().numpy(), f.cpu().numpy().astype(np.int32), i=5, h=0.08)
    assert (edges(raw_f)[1] == 1).any()  # the reference: unwelded, the seam stays open
    v64, f64 = remesh(v.double(), f, edge_length=0.08)
    assert v64.dtype == torch.float64 and bool((edges(f64.cpu().numpy())[1] == 2).all())


def test_bad_settings_are_refused(split_sphere):
    v, f = split_sphere
    assert "edge_length must be finite and > 0" in raised_message(ValueError, remesh, v, f, edge_length=0.0)
    assert "iterations must be a positive int" in raised_message(ValueError, remesh, v, f, iterations=0)
    assert "by keyword" in raised_message(TypeError, remesh, v, f, 0.1)


def _scene(ply: str, emitter: bool = False) -> torchir.Scene:
    shape = {"type": "ply", "filename": ply, "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.3}}}
    if emitter:
        shape["emitter"] = {"type": "area"}
    return torchir.Scene.from_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": 40, "film": {"type": "hdrfilm", "width": 8, "height": 8},
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0])},
        "shape": shape, "light": {"type": "constant"},
    })


def test_remesh_scene_gives_a_new_scene_that_renders_as_the_old(exported):
    """``remesh(scene, "shape", ...)``: a new scene with the new topology under the same id and
    parameter names, the old BSDF (a lost one renders 0.5 where the sphere is 0.3), smooth
    normals, derived parameters kept; the old scene is untouched; the two renders agree but at
    the silhouette, where the surfaces differ by a fraction of a pixel (pixels 0.27 wide there)."""
    scene = _scene(str(exported["uv_sphere"]["ply"]))
    scene.derive("shape.bsdf.reflectance.value", lambda grey: grey.expand(3), {"grey": [0.3]})
    new, positions = remesh(scene, "shape", scene.get("shape.vertex_positions"), edge_length=0.08)
    assert positions.shape == (3 * (positions.numel() // 3),) and positions.device == torch.device(torchir.backend.device())
    torch.testing.assert_close(new.get("shape.vertex_positions"), positions)
    faces = new.get("shape.faces")
    assert faces.numel() // 3 == 2 * (positions.numel() // 3) - 4  # closed, genus 0: F = 2V - 4
    assert set(new.parameter_names()) == set(scene.parameter_names())
    assert scene.get("shape.vertex_positions").numel() == 3 * 185
    assert new.mi_scene.shapes()[0].has_vertex_normals() and LargeSteps(new, "shape").welded_count == positions.numel() // 3
    old_image, new_image = render(scene, {}, spp=16, seed=0), render(new, {}, spp=16, seed=0)
    assert float((old_image - new_image).abs().max()) < 0.1
    assert float(new_image.max()) > 0.9 and float(new_image.min()) < 0.35  # background and sphere both in view


def test_remesh_scene_refuses_what_it_cannot_rebuild(exported):
    scene = _scene(str(exported["uv_sphere"]["ply"]), emitter=True)
    assert "area light" in raised_message(ValueError, remesh_scene, scene, "shape")
    plain = _scene(str(exported["uv_sphere"]["ply"]))
    assert "has 4 vertices, mesh 'shape' has 185" in raised_message(ValueError, remesh_scene, plain, "shape",
                                                                     torch.zeros(4, 3, device=DEVICE))
    assert "no mesh 'bunny'" in raised_message(KeyError, remesh_scene, plain, "bunny")
