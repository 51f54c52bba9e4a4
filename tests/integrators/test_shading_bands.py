"""The shading-horizon term of smooth meshes (``torchir.integrators._shading_bands``): a vertex
beside the silhouette of a coarse smooth-shaded UV sphere (8 x 6, as Blender writes it) turns the
vertex normals around it, and with them the inner edge of the black band where the camera sees
the surface below its shading normal's horizon. Before the term, ReSTIR (any preset) and
Mitsuba's ``direct_projective`` missed that edge's motion: measured at 16² (b2, 32 steps of 16
spp), -2.11 +- 0.02 against -0.23 +- 0.04 by finite differences for one vertex, -0.11 +- 0.04
against -1.76 +- 0.09 for another; with it -0.297 +- 0.007 and -1.74 +- 0.06.

Each bound is the Student-t quantile that a correct estimator exceeds with probability 1e-4
(``z_bound``), for the combined standard error of the estimate (32 independent steps: ``b2``
keeps nothing across steps) and the reference (8 seeds)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir

torchir.backend.variant()  # the integrator module needs it at import

from torchir.bench.exported_meshes import uv_sphere, write_obj  # noqa: E402
from torchir.bench.mesh_gradients import KEY, Problem, mean_and_se, scene_dict, welch_dof, z_bound  # noqa: E402
from torchir.integrators import _shading_bands  # noqa: E402
from torchir.integrators.restir_di import ReSTIRDirectIntegrator  # noqa: E402
from torchir.welding import mesh_weld  # noqa: E402

from tests.helpers import DEVICE  # noqa: E402

RES = 16
REF_SEEDS = 8
STEPS = 32
SPP = 16


def _turned_sphere(path):
    """Blender's 8 x 6 UV sphere with its poles along y (so that rings of vertices outline it)."""
    sphere = uv_sphere(8, 6)
    sphere.v = [(x, -z, y) for x, y, z in sphere.v]
    sphere.vn = [(x, -z, y) for x, y, z in sphere.vn]
    write_obj(sphere, path)
    return path


@pytest.fixture(scope="module")
def sphere(tmp_path_factory) -> Problem:
    return Problem(_turned_sphere(tmp_path_factory.mktemp("bands") / "sphere.obj"), RES)


def _use_vertex(problem: Problem, world) -> None:
    """Displace the welded vertex nearest ``world`` (with all its copies)."""
    mesh = mi.load_dict(problem.spec)
    weld = mesh_weld(mesh)
    p = np.asarray(mesh.vertex_positions_buffer()).reshape(-1, 3)[problem.keep]
    problem.vertex = int(np.argmin(np.linalg.norm(p - np.asarray(world), axis=1)))
    problem.user_vertex_mask = torch.from_numpy(weld.rep == problem.keep[problem.vertex]).to(DEVICE)


def _b2_estimates(problem: Problem, bands: bool) -> np.ndarray:
    """(1, STEPS, 2) derivatives (translation, vertex) through ReSTIR's ``b2`` preset."""
    from torchir.functions import render
    from torchir.samplers import ReSTIRSampler

    scene = problem.scene("b2")
    v0 = scene.get(KEY)
    d_t, d_v = problem.directions(problem.user_vertex_mask, v0.numel() // 3)
    sampler = ReSTIRSampler(scene, preset="b2", seed=11, shading_bands=bands)
    out = np.zeros((1, STEPS, 2))
    for i in range(STEPS):
        t = torch.zeros(2, requires_grad=True)
        image = render(scene, {KEY: v0 + t[0] * d_t + t[1] * d_v}, spp=SPP, seed=300 + i, sampler=sampler)
        (image * problem.adjoint).sum().backward()
        out[0, i] = t.grad.cpu().numpy()
    return out


def _z(estimates: np.ndarray, ref, k: int, direction: str) -> tuple[float, float]:
    means, ses, dof = mean_and_se(estimates)
    mean, se = float(means[k]), float(ses[k])
    r_mean, r_se = ref[direction]
    combined = math.sqrt(se**2 + r_se**2)
    return abs(mean - r_mean) / combined, z_bound(welch_dof(se, dof, r_se, REF_SEEDS - 1))


@pytest.mark.parametrize("world", [(0.354, 0.0, 1.154), (0.306, 0.25, 1.106)], ids=["on_the_outline", "just_behind_it"])
def test_a_vertex_beside_a_smooth_silhouette_agrees_with_finite_differences(sphere, world):
    """With the band term (the default on smooth meshes) the vertex's and the translation's
    derivatives agree with central differences; without it the vertex's is off by far more
    than the bound (the bias the term removes: it shows this test can fail)."""
    _use_vertex(sphere, world)
    ref = sphere.reference(spp=1024, seeds=REF_SEEDS)
    assert abs(ref["vertex"][0]) > 4 * ref["vertex"][1]  # the reference resolves the derivative
    with_bands = _b2_estimates(sphere, True)
    for k, direction in enumerate(("translation", "vertex")):
        z, bound = _z(with_bands, ref, k, direction)
        assert z < bound, (direction, mean_and_se(with_bands)[0][k], ref[direction], z, bound)
    z_without, bound = _z(_b2_estimates(sphere, False), ref, 1, "vertex")
    assert z_without > bound, (z_without, bound)


def test_band_arguments_support_and_extremes(sphere):
    """Bad arguments raise; a faceted mesh has no band; no light or a zero adjoint give exactly 0."""
    scene = sphere.scene("b2").mi_scene
    mesh = [m for m in scene.shapes() if m.id() == "mesh"]
    sensor = scene.sensors()[0]
    integrator = ReSTIRDirectIntegrator(candidates=1, temporal=False, spatial=False)
    assert _shading_bands.supported(scene, sensor, mesh) and _shading_bands.smooth_shaded(mesh[0])
    assert not _shading_bands.smooth_shaded(mi.load_dict(dict(sphere.spec, face_normals=True)))
    zero = mi.TensorXf(np.zeros((RES, RES, 3), np.float32))
    with pytest.raises(ValueError, match="samples"):
        _shading_bands.band_backward(integrator, scene, 0, zero, mesh, 0, 0)
    with pytest.raises(ValueError, match="box filter"):
        _shading_bands.band_backward(integrator, scene, 0, zero, [], 16, 0)
    with pytest.raises(ValueError, match="shading_bands"):
        ReSTIRDirectIntegrator(shading_bands="sometimes")
    with pytest.raises(AttributeError, match=r"ReSTIRSampler\(scene, shading_bands=True\)"):
        integrator.shading_bands = True
    params = mi.traverse(scene)
    v0 = mi.Float(params[KEY])
    try:
        params[KEY] = dr.zeros(mi.Float, dr.width(v0)) + v0  # a fresh leaf: no gradient left by earlier renders
        dr.enable_grad(params[KEY])
        params.update()
        _shading_bands.band_backward(integrator, scene, 0, zero, mesh, 256, 0)
        ones = mi.TensorXf(np.ones((RES, RES, 3), np.float32))
        dark = mi.load_dict({k: v for k, v in scene_dict(sphere.spec, {"type": "direct"}, RES).items() if k != "light"})
        dark_params = mi.traverse(dark)
        dr.enable_grad(dark_params[KEY])
        dark_params.update()
        _shading_bands.band_backward(integrator, dark, 0, ones, [m for m in dark.shapes() if m.id() == "mesh"], 256, 0)
        for g in (dr.grad(params[KEY]), dr.grad(dark_params[KEY])):
            g = np.asarray(g)
            assert np.isfinite(g).all() and (g == 0).all()
    finally:
        params[KEY] = v0
        params.update()


def test_direct_projective_on_a_smooth_mesh_warns_that_it_misses_the_band(sphere):
    """Mitsuba's own estimator keeps the bias: torchir says so and names the way round it."""
    from torchir.functions import render

    scene = sphere.scene("direct_projective")
    v = scene.get(KEY).requires_grad_(True)
    with pytest.warns(UserWarning, match="shading-horizon band.*preset='b2'"):
        render(scene, {KEY: v}, spp=1, seed=0)


@pytest.mark.parametrize("change", ["constant_light", "gaussian_filter"])
def test_band_warning_advises_what_works_for_the_scene(sphere, change):
    """Where ReSTIR refuses the scene (an environment light, as Mitsuba's shape tutorial has; a
    gaussian filter), the warning says why and offers what applies, not the B.2 preset that
    would then refuse the scene."""
    from torchir.functions import render
    from torchir.samplers import ReSTIRSampler

    spec = scene_dict(sphere.spec, {"type": "direct_projective", "guiding": "none"}, RES)
    if change == "constant_light":
        spec["light"] = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    else:
        spec["sensor"]["film"]["rfilter"] = {"type": "gaussian"}
    scene = torchir.Scene.from_dict(spec)
    with pytest.raises(ValueError):
        ReSTIRSampler(scene, preset="b2")  # the advice the plain scene gets would fail here
    v = scene.get(KEY).requires_grad_(True)
    reason = "environment emitters" if change == "constant_light" else "box reconstruction filter"
    with pytest.warns(UserWarning, match="shading-horizon band") as caught:
        render(scene, {KEY: v}, spp=1, seed=0)
    message = " ".join(str(w.message) for w in caught if "shading-horizon band" in str(w.message))
    assert "preset='b2')) adds" not in message and reason in message and "large_steps" in message


def test_restir_says_when_the_band_term_cannot_run(sphere):
    """A crop window (the term needs the whole film) leaves the term out: ReSTIR warns once."""
    from torchir.functions import render
    from torchir.samplers import ReSTIRSampler

    spec = scene_dict(sphere.spec, {"type": "direct_projective", "guiding": "none"}, RES)
    spec["sensor"]["film"].update(crop_offset_x=2, crop_offset_y=2, crop_width=RES - 4, crop_height=RES - 4)
    scene = torchir.Scene.from_dict(spec)
    v = scene.get(KEY).requires_grad_(True)
    with pytest.warns(UserWarning, match="shading-horizon term needs .* no crop window"):
        render(scene, {KEY: v}, spp=1, seed=0, sampler=ReSTIRSampler(scene, preset="b2")).sum().backward()
    assert v.grad is not None and torch.isfinite(v.grad).all()
