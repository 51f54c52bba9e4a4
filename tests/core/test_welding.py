"""Topology from positions on meshes as exporters write them (uv seams, split corners, open
borders, a non-manifold edge), loaded from OBJ and PLY files that torchir did not make."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from torchir.integrators._mesh_edges import back_seen_past_border, edges_of, has_open_border, mesh_edges
from torchir.welding import WeldedFaces, mesh_weld, weld_map

# per exported mesh: (vertices as loaded, distinct positions, edges of the welded surface, open-border
# edges, creases: edges whose faces meet through differently shaded copies)
EXPECTED = {
    "uv_sphere": (185, 146, 432, 0, 0),
    "cube": (24, 8, 18, 0, 12),  # the box's edges, not the faces' diagonals
    "flat_blob": (504, 86, 252, 0, 252),
    "open_cylinder": (34, 32, 64, 32, 0),
    "holed_sphere": (99, 99, 286, 8, 0),
    "fin_box": (9, 9, 19, 2, 0),
}


def _load(path) -> mi.Mesh:
    return mi.load_dict({"type": str(path).rsplit(".", 1)[1], "filename": str(path)})


@pytest.mark.parametrize("kind", ["obj", "ply"])
@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_edges_come_from_positions_on_exported_meshes(exported, name, kind):
    """Seams, poles and flat-shaded splits are interior edges; a tube's rims, a hole's rim and the
    fin's free edges are borders; Euler's formula holds for the closed ones."""
    mesh = _load(exported[name][kind])
    vertices, positions, edges, borders, creases = EXPECTED[name]
    assert mesh.vertex_count() == vertices
    assert len(np.unique(weld_map(np.asarray(mesh.vertex_positions_buffer())))) == positions
    table = edges_of(mesh)
    assert len(table.a) == edges and int((table.c1 == table.c2).sum()) == borders and int(table.crease.sum()) == creases
    assert has_open_border(table) == (borders > 0)
    rep = mesh_weld(mesh).rep
    for column in (table.a, table.b, table.c1, table.c2):
        assert np.all(rep[column] == column)  # every index is its position's first vertex
    if name in ("uv_sphere", "cube", "flat_blob"):  # closed genus-0: V - E + F = 2
        assert positions - edges + mesh.face_count() == 2


def test_a_faceted_mesh_that_shares_its_vertices_creases_at_every_bent_edge(exported):
    """Mitsuba's ``face_normals`` (or a mesh built without normals): the faces share their
    vertices, so only the uv seam's copies differ in normal group, yet the shading jumps at every
    edge whose faces meet at an angle (the diagonals of the sphere's planar quads are not creases)."""
    mesh = mi.load_dict({"type": "obj", "filename": str(exported["uv_sphere"]["obj"]), "face_normals": True})
    table = edges_of(mesh)
    quads = 16 * 8  # the default sphere's 16 segments x 8 bands of quads, one diagonal each
    assert mesh_weld(mesh).flat and len(table.a) == 432
    assert int(table.crease.sum()) == 432 - quads  # was 40: the seam's and poles' edges alone


def test_index_topology_takes_seams_for_borders(exported):
    """What Mitsuba and torchir did before: by indices a uv sphere's seam and poles are borders."""
    mesh = _load(exported["uv_sphere"]["obj"])
    by_index = mesh_edges(np.asarray(mesh.faces_buffer()))
    assert int((by_index.c1 == by_index.c2).sum()) > 0 == int((edges_of(mesh).c1 == edges_of(mesh).c2).sum())


def test_weld_map_first_vertex_and_signed_zero():
    p = np.array([[0, 0, 0], [1, 0, 0], [-0.0, 0, 0], [1, 0, 0], [1, 1e-7, 0]], np.float32)
    assert weld_map(p).tolist() == [0, 1, 0, 1, 4]
    assert weld_map(np.zeros((0, 3))).shape == (0,)


def test_non_manifold_edge_keeps_the_faces_that_bound_the_others():
    """Three faces around an edge: the two at the ends of the widest gap; a fourth filling the gap
    (no wedge under a half turn) drops the edge: it never outlines the mesh."""
    p = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0.5], [0, 1, 0.5], [-1, 0.2, 0.5], [0.3, -1, 0.5]], np.float64)
    fan = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    table = mesh_edges(fan, p)
    row = int(np.flatnonzero((table.a == 0) & (table.b == 1))[0])
    assert {int(table.c1[row]), int(table.c2[row])} == {2, 4}  # 3 lies between them (at 90 degrees)
    closed = mesh_edges(np.vstack([fan, [[0, 1, 5]]]), p)
    assert not np.any((closed.a == 0) & (closed.b == 1))


def test_welded_faces_rebind_and_restore(exported):
    """Inside: the faces index first copies only and a flat-shaded mesh shades with face normals
    (same image); on exit the user's faces and normals are back, bit for bit."""
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "mesh": {"type": "obj", "filename": str(exported["cube"]["obj"])},
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(origin=[1, -3, 1.5], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8}},
        "light": {"type": "point", "position": [2, -2, 3], "intensity": {"type": "rgb", "value": 10.0}},
    })
    params, mesh = mi.traverse(scene), scene.shapes()[0]
    faces, normals = np.array(mesh.faces_buffer()), np.array(mesh.vertex_normals_buffer())
    image = np.array(mi.render(scene, spp=4, seed=1))
    weld = mesh_weld(mesh)
    assert weld.flat and weld.repeats == 16
    with WeldedFaces(params, [mesh]) as welded:
        assert bool(welded)
        assert np.array_equal(np.array(mesh.faces_buffer()).reshape(-1, 3), weld.welded_faces)
        assert not mesh.has_vertex_normals()
        assert np.allclose(np.array(mi.render(scene, spp=4, seed=1)), image, atol=1e-5)
    assert np.array_equal(np.array(mesh.faces_buffer()), faces)
    assert np.array_equal(np.array(mesh.vertex_normals_buffer()), normals)
    assert not WeldedFaces(params, [_load(exported["holed_sphere"]["obj"])])  # welded already: nothing to do


def test_back_of_an_open_border_seen_into_a_tube_and_from_behind_a_hole(exported):
    tube = _load(exported["open_cylinder"]["obj"])
    assert back_seen_past_border(tube, np.array([0.0, -3.0, 2.0]))  # looking into the tube
    holed = _load(exported["holed_sphere"]["obj"])  # the hole opens towards +y: its rim faces +y
    assert back_seen_past_border(holed, np.array([0.0, -3.0, 0.0])) and not back_seen_past_border(holed, np.array([0.0, 3.0, 0.0]))
    scene = mi.load_dict({"type": "scene", "tube": {"type": "obj", "filename": str(exported["open_cylinder"]["obj"])},
                          "holed": {"type": "obj", "filename": str(exported["holed_sphere"]["obj"])}})
    tube, holed = sorted(scene.shapes(), key=lambda s: s.vertex_count())
    assert back_seen_past_border(tube, np.array([0.0, -3.0, 2.0]), scene)  # the far rim, over the near one
    assert not back_seen_past_border(holed, np.array([0.0, -3.0, 0.0]), scene)  # the rim hides behind the sphere


def test_group_normals_are_smooth_across_seams_and_keep_hard_edges(exported):
    """Mitsuba recomputes a moving mesh's normals over its index topology (seams become creases);
    torchir binds normals per group: one normal for a seam's copies, a cube's faces stay flat."""
    import drjit as dr

    from torchir.welding import group_normals

    sphere = _load(exported["uv_sphere"]["obj"])
    weld = mesh_weld(sphere)
    params = mi.traverse(sphere)
    params["vertex_positions"] = dr.ravel(dr.unravel(mi.Point3f, params["vertex_positions"]) * 1.1)
    params.update()
    one_sided = np.array(sphere.vertex_normals_buffer()).reshape(-1, 3)
    n = np.array(group_normals(sphere, weld)).reshape(-1, 3)
    seam = weld.rep != np.arange(len(weld.rep))
    assert np.abs(one_sided[seam] - one_sided[weld.rep[seam]]).max() > 0.05  # Mitsuba's: a crease at the seam
    assert np.abs(n[seam] - n[weld.rep[seam]]).max() < 1e-6  # ours: one normal per position
    p = np.array(sphere.vertex_positions_buffer()).reshape(-1, 3)
    assert np.all(np.einsum("vk,vk->v", n, p / np.linalg.norm(p, axis=1, keepdims=True)) > 0.97)  # close to the sphere's
    cube = _load(exported["cube"]["obj"])
    assert np.allclose(np.array(group_normals(cube, mesh_weld(cube))), np.array(cube.vertex_normals_buffer()), atol=1e-6)


def test_a_mesh_outside_a_scene_is_welded_again_once_it_differs_from_its_weld(exported):
    """Kept by identity alone, the weld of a freed mesh went to a later mesh at its address (a
    flat-shaded load of the same file got the smooth one's weld): the weld is kept only while the
    mesh's faces, positions and normals are those it was made from."""
    mesh = _load(exported["uv_sphere"]["obj"])
    weld = mesh_weld(mesh)
    assert mesh_weld(mesh) is weld and not weld.flat and weld.repeats > 0
    params = mi.traverse(mesh)
    moved = np.asarray(params["vertex_positions"]).copy()
    moved[3 * 7] += 0.25  # one vertex off its place: a different mesh at the same address, as far as the key goes
    params["vertex_positions"] = mi.Float(moved)
    params.update()
    again = mesh_weld(mesh)
    assert again is not weld and np.array_equal(again.rep, weld_map(moved))


def test_a_scene_mesh_keeps_the_weld_it_was_loaded_with_however_its_vertices_move(exported):
    """A torchir.Scene welds its meshes as loaded; moving the vertices (the seam's copies apart,
    as an optimiser moves them) leaves the weld, its seams interior edges."""
    import torchir

    scene = torchir.Scene.from_dict({"type": "scene", "sphere": {"type": "obj", "filename": str(exported["uv_sphere"]["obj"])}})
    mesh = next(s for s in scene.mi_scene.shapes() if isinstance(s, mi.Mesh))
    weld = scene.mesh_weld(mesh)
    assert mesh_weld(mesh) is weld and weld.repeats == 185 - 146
    spread = np.asarray(scene.params["sphere.vertex_positions"]) + np.random.default_rng(0).normal(0, 1e-3, 3 * 185)
    scene.params["sphere.vertex_positions"] = mi.Float(spread.astype(np.float32))
    scene.params.update()
    assert len(np.unique(weld_map(spread.astype(np.float32)))) == 185  # no two copies coincide now
    assert mesh_weld(mesh) is weld and scene.mesh_weld(_load(exported["uv_sphere"]["obj"])) is None  # not this scene's


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_a_mesh_gets_its_loaded_normals_back_when_a_render_unbinds_its_positions(exported, fmt):
    """``render(scene, {})`` after a render that moved a mesh renders the loaded mesh: its file's
    normals, not the ones recomputed at the restored positions (before, the update left normals
    recomputed over the faces, seams creased and weighted otherwise than the exporter's)."""
    import torch

    import torchir
    from torchir.functions import render

    scene = torchir.Scene.from_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0.4, 0.5, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 12, "rfilter": {"type": "box"}}},
        "sphere": {"type": fmt, "filename": str(exported["uv_sphere"][fmt]), "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [1.0, 2.0, 2.0], "intensity": {"type": "rgb", "value": 8.0}},
    })
    key, normals = "sphere.vertex_positions", "sphere.vertex_normals"
    loaded_normals = np.array(scene.params[normals])
    before = render(scene, {}, spp=4, seed=3)
    moved = scene.get(key) * torch.tensor([1.2, 0.9, 1.0]).repeat(185)
    render(scene, {key: moved}, spp=4, seed=3)
    assert not np.allclose(np.array(scene.params[normals]), loaded_normals, atol=1e-3)  # bound: the moved mesh's
    after = render(scene, {}, spp=4, seed=3)
    np.testing.assert_array_equal(np.array(scene.params[normals]), loaded_normals)
    torch.testing.assert_close(after, before, rtol=0, atol=0)


def test_a_pass_without_indirect_silhouettes_keeps_the_acceleration_structure(exported, monkeypatch):
    """direct_projective with ``sppi: 0`` (Mitsuba's shape tutorial) welds a textured UV sphere's
    faces for its boundary pass without rebuilding the acceleration structure, and goes back
    without rebuilding it either: the gradient is the one with both rebuilds, and the image after
    the step, uvs across the seam included, is a freshly loaded scene's."""
    import torch

    import torchir
    import torchir.functions._passes as passes
    from tests.helpers import DEVICE
    from torchir.functions import render

    def scene():
        return torchir.Scene.from_dict({
            "type": "scene", "integrator": {"type": "direct_projective", "sppi": 0},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0.4, 0.5, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
            "sphere": {"type": "obj", "filename": str(exported["uv_sphere"]["obj"]),
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard"}}},
            "light": {"type": "point", "position": [1.0, 2.0, 2.0], "intensity": {"type": "rgb", "value": 8.0}},
        })

    key = "sphere.vertex_positions"
    weights = torch.rand(3, 16, 16, generator=torch.Generator(device=DEVICE).manual_seed(0))

    def step(s):
        x = (s.get(key) * 1.05).requires_grad_()
        (render(s, {key: x}, spp=8, seed=2) * weights).sum().backward()
        return x.grad

    kept, rebuilt = scene(), scene()
    grad = step(kept)

    class Rebuilding(WeldedFaces):
        def __init__(self, params, meshes, indirect: bool = True) -> None:
            super().__init__(params, meshes, indirect=True)

    with monkeypatch.context() as m:
        m.setattr(passes, "WeldedFaces", Rebuilding)
        reference = step(rebuilt)
    assert grad.abs().max() > 0
    torch.testing.assert_close(grad, reference, rtol=1e-4, atol=1e-6 * float(reference.abs().max()))
    fresh = scene()
    with torch.no_grad():
        render(fresh, {key: fresh.get(key) * 1.05}, spp=1, seed=0)  # bound as the step left ``kept``
    after, loaded = (np.array(mi.render(s.mi_scene, spp=8, seed=4)) for s in (kept, fresh))  # nothing updated since
    np.testing.assert_allclose(after, loaded, rtol=0, atol=1e-6)
