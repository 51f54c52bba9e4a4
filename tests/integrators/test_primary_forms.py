"""The camera-ray term of shape derivatives in the attached and material forms, with pixel-level
antithetic sampling and shared reservoirs (``torchir.integrators._primary_forms``, paper 004 §6),
on a bumpy sheet that fills the view: checked against finite differences of the rendered image
(no silhouette or shadow edge there, so the camera-ray term is the whole derivative)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import torchir

torchir.backend.variant()  # the integrator module needs it at import

from torchir.bench.restir_antithetic import scored_pixels  # noqa: E402
from torchir.integrators._primary_forms import derivative_image, screen_projection  # noqa: E402
from torchir.integrators.restir_di import ReSTIRDirectIntegrator  # noqa: E402
from torchir.scenes import pig  # noqa: E402
from torchir.scenes._common import triangle_mesh  # noqa: E402

RES, KEY, UP = 20, "terrain.vertex_positions", (0.0, 0.0, 1.0)


def terrain_scene(res: int, grid: int = 24) -> mi.Scene:
    """A smooth-shaded bumpy sheet filling the view, lit from above by one area light: no
    silhouette and no self-shadow (every normal faces the light), so the camera-ray term is the
    whole derivative. (On ``pig``'s blob the faceted terminator shadows the blob itself: a
    visibility edge each form leaves to its boundary terms, measured as 1-3 % of the derivative.)"""
    x, y = np.meshgrid(np.linspace(-2, 2, grid), np.linspace(-2, 2, grid))
    z = 0.12 * np.sin(2.1 * x + 0.3) * np.cos(1.7 * y) + 0.05 * np.sin(4.0 * y)
    v = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    i = np.arange(grid * grid).reshape(grid, grid)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.uint32)
    mesh = triangle_mesh("terrain", v, faces, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.4]}},
                         smooth=True)
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30, "to_world": T().look_at(origin=[0.3, -2.2, 2.6], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "sample_border": False}},
        "terrain": mesh,
        "light": {"type": "rectangle", "to_world": T().translate([-0.5, 0.3, 3.0]).rotate([1, 0, 0], 180).scale(0.8),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 8.0}}},
        "integrator": {"type": "prb", "max_depth": 2},
    })


@pytest.fixture(scope="module")
def sheet():
    """``(scene, scored mask, finite-difference derivative over the mask, its standard error)``."""
    scene = terrain_scene(RES)
    mask = scored_pixels(scene, "terrain")
    assert mask.sum() > 0.5 * RES * RES
    params = mi.traverse(scene)
    v0 = mi.Float(params[KEY])
    up = mi.Float(np.tile(np.array(UP, np.float32), dr.width(v0) // 3))

    def image(dz: float, seed: int) -> np.ndarray:
        params[KEY] = v0 + dz * up
        params.update()
        return np.asarray(mi.render(scene, spp=1024, seed=seed))

    eps = 0.01
    fds = [(image(eps, s) - image(-eps, s)) / (2 * eps) for s in (1, 2)]  # same seed on both sides
    params[KEY] = v0
    params.update()
    fd_sums = [float(fd[mask].sum()) for fd in fds]
    return scene, mask, float(np.mean(fd_sums)), abs(fd_sums[0] - fd_sums[1]) / 2


def _sums(scene, mask, n: int, **kwargs) -> np.ndarray:
    integrator = kwargs.pop("integrator", None) or ReSTIRDirectIntegrator(candidates=2, temporal=False, spatial=False)
    return np.array([float(np.asarray(derivative_image(integrator, scene, KEY, UP, seed=i, **kwargs))[mask].sum())
                     for i in range(n)])


def test_projection_puts_hit_points_back_on_their_film_positions(sheet):
    scene = sheet[0]
    sensor = scene.sensors()[0]
    project, jacobian = screen_projection(sensor)
    film = np.array([[3.25, 7.5], [10.0, 10.0], [17.8, 16.1], [0.5, 19.5]], np.float32)
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(film[:, 0] / RES, film[:, 1] / RES), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    assert np.all(np.asarray(si.is_valid()))
    s = project(si.p)
    assert np.allclose(np.stack([np.asarray(s.x), np.asarray(s.y)], 1), film, atol=2e-3)
    # J = |det ds/d(u, v)| against central differences of the projection along dp_du, dp_dv
    h = 1e-3
    cols = [(project(si.p + h * d) - project(si.p - h * d)) / (2 * h) for d in (si.dp_du, si.dp_dv)]
    det = np.abs(np.asarray(cols[0].x * cols[1].y - cols[1].x * cols[0].y))
    assert np.allclose(np.asarray(jacobian(si.p, si.dp_du, si.dp_dv)), det, rtol=2e-2)


@pytest.mark.parametrize("form, antithetic", [("attached", False), ("material", True)])
def test_camera_ray_term_agrees_with_finite_differences(sheet, form, antithetic):
    scene, mask, fd, fd_se = sheet
    sums = _sums(scene, mask, 8, spp=8, form=form, antithetic=antithetic)
    se = float(np.hypot(sums.std(ddof=1) / np.sqrt(len(sums)), fd_se))
    assert abs(fd) > 10 * se  # the sheet's shading moves: a derivative the test resolves
    assert abs(sums.mean() - fd) < 4 * se, (sums.mean(), fd, se)


def test_antithetic_pairs_cancel_the_pixel_edge_fluxes(sheet):
    """Without antithetic sampling the material form's edge fluxes do not cancel: its spread
    over the same samples' budget is far larger (measured: 10x at 48²)."""
    scene, mask, _, _ = sheet
    plain = _sums(scene, mask, 8, spp=4, form="material")
    paired = _sums(scene, mask, 8, spp=2, form="material", antithetic=True)  # the same shading points
    assert plain.std() > 3 * paired.std(), (plain.std(), paired.std())


@pytest.mark.parametrize("form, antithetic, shared", [
    ("attached", False, True),
    # Not shared, each member of a pair combines with its own neighbours: the code the attached
    # case runs for its one member, while the pair's combination (MIS and normal test at each
    # member's own point, whichever neighbour set) is the shared case's. 16 s of kernels: slow.
    pytest.param("material", True, False, marks=pytest.mark.slow),
    ("material", True, True),
])
def test_reused_reservoirs_keep_the_estimate_unbiased(sheet, form, antithetic, shared):
    """With reservoirs of an earlier step combined (for an antithetic pair: independently per
    point, or one neighbour set for the pair, Eq. 29) the estimate still agrees with finite
    differences."""
    scene, mask, fd, fd_se = sheet
    integrator = ReSTIRDirectIntegrator(candidates=2, neighbors=2, burn_in=2)
    _, cache = integrator.step(scene, 0, 0, 1, zero_remainder=False)
    assert cache.prev is not None
    sums = _sums(scene, mask, 8, spp=8, form=form, antithetic=antithetic, shared=shared, prev=cache.prev,
                 integrator=integrator)
    se = float(np.hypot(sums.std(ddof=1) / np.sqrt(len(sums)), fd_se))
    assert abs(sums.mean() - fd) < 4 * se, (sums.mean(), fd, se)


def test_vertices_are_restored(sheet):
    """The same Dr.Jit variable, without gradients, is back in the scene after a call (so the
    integrator sees no geometry change), and a second scene can be differentiated while the
    first lives (a vertex array left bound to θ broke Dr.Jit's traversal there)."""
    scene = sheet[0]
    index = mi.traverse(scene)[KEY].index
    integrator = ReSTIRDirectIntegrator(candidates=2, temporal=False, spatial=False)
    derivative_image(integrator, scene, KEY, UP, form="material", antithetic=True)
    after = mi.traverse(scene)[KEY]
    assert after.index == index and not dr.grad_enabled(after)
    other = terrain_scene(8, grid=6)
    d = np.asarray(derivative_image(integrator, other, KEY, UP))
    assert d.shape == (8, 8, 3) and np.isfinite(d).all() and np.abs(d).max() > 0


def test_a_dark_scene_has_a_zero_derivative(sheet):
    scene = sheet[0]
    params = mi.traverse(scene)
    key = "light.emitter.radiance.value"
    lit = mi.Color3f(params[key])
    params[key] = mi.Color3f(0.0)
    params.update()
    integrator = ReSTIRDirectIntegrator(candidates=2, temporal=False, spatial=False)
    try:
        for form, anti in (("attached", False), ("material", True)):
            d = np.asarray(derivative_image(integrator, scene, KEY, UP, form=form, antithetic=anti))
            assert d.shape == (RES, RES, 3) and np.all(d == 0.0)
    finally:
        params[key] = lit
        params.update()


def test_bad_arguments_are_named(sheet):
    scene = sheet[0]
    integrator = ReSTIRDirectIntegrator(candidates=2, temporal=False, spatial=False)
    with pytest.raises(ValueError, match="form must be one of"):
        derivative_image(integrator, scene, KEY, UP, form="psdr")
    with pytest.raises(ValueError, match="antithetic sampling applies to the material form"):
        derivative_image(integrator, scene, KEY, UP, form="attached", antithetic=True)
    with pytest.raises(KeyError, match="not a mesh's vertex_positions"):
        derivative_image(integrator, scene, "terrain.bsdf.reflectance.value", UP)
    with pytest.raises(ValueError, match="velocity must be finite"):
        derivative_image(integrator, scene, KEY, (0.0, 1.0))
    with pytest.raises(ValueError, match="velocity must be finite"):
        derivative_image(integrator, scene, KEY, (0.0, float("nan"), 1.0))
    ortho = mi.load_dict({**pig.build(4, rings=6, segments=8),
                          "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4, "height": 4}}})
    with pytest.raises(ValueError, match="pinhole perspective sensor"):
        derivative_image(integrator, ortho, "pig.vertex_positions", UP)


def test_pig_options_are_checked_and_dome_lights_share_the_main_lights_power():
    with pytest.raises(ValueError, match="light_size must be > 0"):
        pig.build(8, light_size=0.0)
    with pytest.raises(ValueError, match="dome_lights must be >= 0"):
        pig.build(8, dome_lights=-1)
    built = pig.build(8, dome_lights=5)
    domes = [v for k, v in built.items() if k.startswith("dome_")]
    assert len(domes) == 5
    # radiance x area (side 0.1): together the main light's 25
    power = sum(np.mean(d["emitter"]["radiance"]["value"]) * 0.01 for d in domes)
    assert power == pytest.approx(25.0, rel=1e-6)
