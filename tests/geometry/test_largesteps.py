"""``LargeSteps``: ``u = (I + λL) x`` on the welded surface, against references outside its code
path: the paper's matrix built densely with numpy, Mitsuba's own ``mi.ad.LargeSteps``, and the
exporter's welded copy of a UV sphere whose file repeats its seam and poles."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

import torchir
from tests.helpers import DEVICE, raised_message
from torchir.device_audit import device_audit
from torchir.geometry import AdamUniform, LargeSteps, read_mesh

OCTAHEDRON_V = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
OCTAHEDRON_F = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]


def octahedron() -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor(OCTAHEDRON_V, dtype=torch.float32, device=DEVICE),
            torch.tensor(OCTAHEDRON_F, dtype=torch.int64, device=DEVICE))


def paper_matrix(n: int, faces: np.ndarray, lam: float) -> np.ndarray:
    """``I + λ L`` of Nicolet et al. 2021, dense: ``L = D - A`` with ``A`` the vertex adjacency."""
    adjacency = np.zeros((n, n))
    for a, b, c in faces:
        for i, j in ((a, b), (b, c), (c, a)):
            adjacency[i, j] = adjacency[j, i] = 1.0
    return np.eye(n) + lam * (np.diag(adjacency.sum(1)) - adjacency)


def dense(ls: LargeSteps) -> np.ndarray:
    return ls.matrix().to_dense().cpu().numpy()


def copy_sums(ls: LargeSteps, per_vertex: torch.Tensor) -> torch.Tensor:
    """``(n, 3)``: the rows of a per-file-vertex field summed over each welded vertex's copies."""
    out = torch.zeros(ls.welded_count, 3, dtype=per_vertex.dtype, device=per_vertex.device)
    return out.index_add_(0, ls.welded_index.to(per_vertex.device), per_vertex)


def test_matches_the_papers_matrix_and_its_solve_computed_densely():
    """On an octahedron: the matrix is the paper's ``I + λL``; ``to_differential`` is its product
    and ``from_differential`` its solve, in float32 and (with the double factor) in float64."""
    v, f = octahedron()
    ls = LargeSteps(v, f, lambda_=7.0)
    reference = paper_matrix(6, np.array(OCTAHEDRON_F), 7.0)
    np.testing.assert_array_equal(dense(ls), reference)
    x = torch.randn(6, 3, dtype=torch.float64, device=DEVICE)
    np.testing.assert_allclose(ls.to_differential(x).cpu().numpy(), reference @ x.cpu().numpy(), rtol=1e-12, atol=1e-12)
    u = torch.randn(6, 3, dtype=torch.float64, device=DEVICE)
    solved = np.linalg.solve(reference, u.cpu().numpy())
    np.testing.assert_allclose(ls.from_differential(u).cpu().numpy(), solved, rtol=0, atol=1e-12)  # float32 would miss by 1e-7
    np.testing.assert_allclose(ls.from_differential(u.float()).cpu().numpy(), solved, rtol=0, atol=2e-6)


def test_round_trip_x_to_u_to_x_in_both_layouts(split_sphere):
    """``from_differential(to_differential(x)) == x`` on the seamed sphere; ``u`` takes ``x``'s layout
    (flat ``(3V,)`` as ``vertex_positions`` in, flat ``(3n,)`` out; ``(V, 3)`` in, ``(n, 3)`` out)."""
    v, f = split_sphere
    ls = LargeSteps(v, f, lambda_=25.0)
    assert (ls.vertex_count, ls.welded_count) == (185, 146)
    u = ls.to_differential(v)
    assert u.shape == (146, 3)
    torch.testing.assert_close(ls.from_differential(u), v, rtol=0, atol=2e-6)
    flat = ls.to_differential(v.reshape(-1))
    assert flat.shape == (438,)
    x = ls.from_differential(flat)
    assert x.shape == (555,)
    torch.testing.assert_close(x, v.reshape(-1), rtol=0, atol=2e-6)


def test_gradcheck_in_float64_on_a_mesh_of_copies(exported):
    """gradcheck and gradgradcheck of ``from_differential`` in float64 on Mitsuba's ``cube``
    convention (24 vertices at 8 positions: every vertex has three copies)."""
    ls = LargeSteps(*read_mesh(exported["cube"]["ply"], device=DEVICE), lambda_=3.0)
    assert (ls.vertex_count, ls.welded_count) == (24, 8)
    u = torch.randn(8, 3, dtype=torch.float64, device=DEVICE, requires_grad=True)
    assert torch.autograd.gradcheck(ls.from_differential, (u,))
    assert torch.autograd.gradgradcheck(ls.from_differential, (u,))


def test_gradient_wrt_u_is_the_solve_of_the_gradient_wrt_x(split_sphere):
    """For ``loss = sum(g * x)`` the gradient w.r.t. ``u`` is ``(I + λL)^{-1}`` of ``g`` summed
    over each vertex's copies, by a dense solve of the paper's matrix (float64)."""
    v, f = split_sphere
    ls = LargeSteps(v, f, lambda_=3.0)
    u = torch.randn(ls.welded_count, 3, dtype=torch.float64, device=DEVICE, requires_grad=True)
    g = torch.randn(ls.vertex_count, 3, dtype=torch.float64, device=DEVICE)
    (ls.from_differential(u) * g).sum().backward()
    expected = np.linalg.solve(paper_matrix(ls.welded_count, ls.welded_faces.cpu().numpy(), 3.0), copy_sums(ls, g).cpu().numpy())
    np.testing.assert_allclose(u.grad.cpu().numpy(), expected, rtol=0, atol=1e-11)


def test_a_seamed_sphere_is_its_welded_copy_and_its_copies_move_together(split_sphere, welded_sphere):
    """The exported UV sphere (seam and poles repeated: 185 vertices) has the matrix of the
    exporter's welded copy (146), up to the order of the vertices; ``x(u)`` is the copy's, every
    copy of a vertex gets the same position, and the gradients of the copies sum."""
    (v, f), (vw, fw) = split_sphere, welded_sphere
    ls, lw = LargeSteps(v, f, lambda_=19.0), LargeSteps(vw, fw, lambda_=19.0)
    assert ls.welded_count == lw.welded_count == 146
    # welded vertex k of the file -> the copy's vertex at its position (the PLY text keeps 7 digits)
    positions = np.zeros((ls.welded_count, 3))
    positions[ls.welded_index.cpu().numpy()] = v.cpu().numpy()
    distance, perm = cKDTree(vw.cpu().numpy()).query(positions)
    assert distance.max() < 1e-6 and len(set(perm)) == 146
    np.testing.assert_array_equal(dense(ls), dense(lw)[np.ix_(perm, perm)])

    u_copy = torch.randn(146, 3, device=DEVICE)
    perm_t = torch.as_tensor(perm, device=DEVICE)
    u = u_copy[perm_t].requires_grad_()
    x = ls.from_differential(u)
    torch.testing.assert_close(x, lw.from_differential(u_copy)[perm_t][ls.welded_index], rtol=1e-6, atol=1e-6)
    for k in range(ls.welded_count):  # every copy exactly where its first copy is
        copies = x[ls.welded_index == k]
        assert bool((copies == copies[0]).all())
    assert int((torch.bincount(ls.welded_index) > 1).sum()) == 2 + 9  # the poles and the seam's 9 rings

    g = torch.randn(185, 3, device=DEVICE)
    (x * g).sum().backward()
    u_copy.requires_grad_()
    (lw.from_differential(u_copy) * copy_sums(ls, g)[torch.argsort(perm_t)]).sum().backward()
    torch.testing.assert_close(u.grad, u_copy.grad[perm_t], rtol=1e-5, atol=1e-6)


def test_matches_mitsubas_large_steps(split_sphere):
    """Mitsuba's ``mi.ad.LargeSteps`` on the same seamed file (it welds by ``np.unique``, in its
    own vertex order): the same ``u`` of the file's vertices and the same ``x`` of a latent."""
    v, f = split_sphere
    ls = LargeSteps(v, f, lambda_=25.0)
    theirs = mi.ad.LargeSteps(mi.Float(v.reshape(-1).cpu().numpy()), mi.UInt(f.reshape(-1).cpu().numpy().astype(np.uint32)), 25.0)
    ours_of_theirs = ls.welded_index.cpu().numpy()[np.array(theirs.index)]  # their welded k -> ours
    assert theirs.n_verts == ls.welded_count and len(set(ours_of_theirs)) == ls.welded_count
    x = v + 0.05 * torch.randn(ls.welded_count, 3, device=DEVICE)[ls.welded_index]  # moved, copies together
    u_theirs = np.array(theirs.to_differential(mi.Float(x.reshape(-1).cpu().numpy()))).reshape(-1, 3)
    np.testing.assert_allclose(ls.to_differential(x).cpu().numpy()[ours_of_theirs], u_theirs, rtol=1e-5, atol=1e-5)
    y = torch.randn(ls.welded_count, 3, device=DEVICE)
    x_theirs = np.array(theirs.from_differential(mi.Float(y.cpu().numpy()[ours_of_theirs].reshape(-1)))).reshape(-1, 3)
    np.testing.assert_allclose(ls.from_differential(y).cpu().numpy(), x_theirs, rtol=1e-5, atol=1e-6)


def test_a_scene_mesh_is_taken_by_its_id(split_sphere, exported):
    """``LargeSteps(scene, "shape")`` (or its key ``"shape.vertex_positions"``) is the one of the
    mesh's own vertices and faces; an unknown id names the scene's meshes."""
    scene = torchir.Scene.from_dict({"type": "scene", "shape": {"type": "ply", "filename": str(exported["uv_sphere"]["ply"])}})
    by_id, by_key = LargeSteps(scene, "shape"), LargeSteps(scene, "shape.vertex_positions", lambda_=19.0)
    direct = LargeSteps(*split_sphere)
    assert by_id.device == torch.device(torchir.backend.device())
    for ls in (by_id, by_key):
        np.testing.assert_array_equal(dense(ls), dense(direct))
        torch.testing.assert_close(ls.welded_index, direct.welded_index.to(ls.device))
    assert "['shape']" in raised_message(KeyError, LargeSteps, scene, "bunny")


def test_refuses_bad_inputs_with_clear_errors():
    v, f = octahedron()
    assert "lambda_ must be finite and >= 0" in raised_message(ValueError, LargeSteps, v, f, lambda_=-1.0)
    assert "index vertices in [0, 6], but there are 6" in raised_message(ValueError, LargeSteps, v, torch.where(f == 5, 6, f))
    assert "integer vertex indices" in raised_message(TypeError, LargeSteps, v, f.float())
    assert "(V, 3) or flat (3V,)" in raised_message(ValueError, LargeSteps, v[:, :2], f)
    ls = LargeSteps(v, f)
    wrong_count, integers = torch.zeros(5, 3, device=DEVICE), torch.zeros(6, 3, dtype=torch.int32, device=DEVICE)
    assert "u must be (6, 3) or (18,), got (5, 3)" in raised_message(ValueError, ls.from_differential, wrong_count)
    assert "float32 or float64" in raised_message(TypeError, ls.to_differential, integers)


def test_the_optimisation_step_stays_on_the_device(split_sphere):
    """``from_differential``, its backward and ``AdamUniform.step`` make no torch factory without
    a device and no host transfer (on a GPU each would be a mismatch or a copy and a wait)."""
    v, f = split_sphere
    ls = LargeSteps(v, f, lambda_=25.0)
    u = ls.to_differential(v.reshape(-1)).requires_grad_()
    opt = AdamUniform([u], lr=0.1)
    target = v.reshape(-1) * 1.1
    with device_audit() as audit:
        for _ in range(2):
            loss = (ls.from_differential(u) - target).square().sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
    assert audit.factories() == [] and audit.transfers() == [], str(audit)
    assert float(loss.detach()) < float((v.reshape(-1) - target).square().sum())


def test_a_process_that_ends_with_a_factor_alive_prints_no_leak():
    """A Large Steps graph still referenced at exit (as a run's module holds it): nanobind printed
    "leaked instance ... CholeskySolverF" and five more lines after every Large Steps fit."""
    import subprocess
    import sys

    script = ("import builtins, torch\nfrom torchir.geometry import LargeSteps\n"
              "v = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])\n"
              "f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])\n"
              "ls = LargeSteps(v, f, lambda_=10.0)\n"
              "builtins.kept = (ls, ls.from_differential(ls.to_differential(v).requires_grad_()))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "leaked" not in done.stderr, done.stderr


def test_the_shading_band_warning_does_not_advise_large_steps_to_a_mesh_that_has_them(exported):
    """Under an environment (ReSTIR refuses it) a smooth mesh through direct_projective gets the
    shading-horizon warning, whose remedy is Large Steps; Mitsuba's shape tutorial as a torchir
    config has them already, and was told to add them."""
    import warnings

    from torchir.functions.render import _check_projective_silhouettes  # what render runs first

    def warned(with_large_steps: bool) -> str:
        scene = torchir.Scene.from_dict({
            "type": "scene", "integrator": {"type": "direct_projective", "sppi": 0},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0.4, 0.5, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
            "sphere": {"type": "obj", "filename": str(exported["uv_sphere"]["obj"]), "bsdf": {"type": "diffuse"}},
            "sky": {"type": "constant"},
        })
        if with_large_steps:
            LargeSteps(scene, "sphere", lambda_=25.0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _check_projective_silhouettes(scene, frozenset({"sphere.vertex_positions"}), 0)
        (message,) = [str(w.message) for w in caught if "shading-horizon band" in str(w.message)]
        return message

    plain, spread = warned(False), warned(True)
    assert "parametrization: {type: large_steps}" in plain and "environment emitters" in plain
    assert "parametrization: {type: large_steps}" not in spread and "this mesh's Large Steps parametrization" in spread
