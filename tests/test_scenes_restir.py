"""The ReSTIR built-in scenes (paper 004, Figs. 9-11): ajar_painting, occluded_lights, many_lights."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir
from torchir.functions import render
from torchir.samplers import ReSTIRSampler

RES = 16  # as tests/conftest.py: the kernels compile once

SCENES = ("ajar_painting", "occluded_lights", "many_lights")


@pytest.fixture(scope="module")
def scenes() -> dict[str, torchir.Scene]:
    return {name: torchir.Scene.builtin(name, resolution=RES) for name in SCENES}


def _key(name: str) -> str:
    return torchir.scenes.get(name).parameters[0]


@pytest.mark.parametrize("name", SCENES)
def test_scene_is_direct_illumination_and_renders_with_and_without_restir(scenes, name):
    from torchir.integrators.restir_di import check_scene  # needs the Mitsuba variant

    scene = scenes[name]
    check_scene(scene.mi_scene)  # raises for what ReSTIR DI does not handle
    assert scene.mi_scene.integrator().max_depth == 2
    assert len(torchir.scenes.get(name).parameters) == 1 and _key(name) in scene.parameter_names(differentiable_only=True)
    plain = render(scene, {}, spp=4, seed=0)
    sampler = ReSTIRSampler(scene, burn_in=2)
    for seed in range(2):  # the second step reuses the first one's reservoirs
        restir = render(scene, {}, spp=1, seed=seed, sampler=sampler)
    for img in (plain, restir):
        assert img.shape == (3, RES, RES) and bool(img.isfinite().all()) and float(img.min()) >= 0
        assert float(img.mean()) > 0


def _texture_gradient(scene, key, sampler=None):
    t = torch.full_like(scene.get(key), 0.5).requires_grad_()
    img = render(scene, {key: t}, spp=4, seed=3, sampler=sampler)
    (img * torch.linspace(1.0, 2.0, img.numel()).reshape(img.shape)).sum().backward()  # nonzero adjoint
    assert t.grad is not None
    return img.detach(), t.grad


def test_ajar_painting_closed_door_without_fill_is_exactly_dark():
    scene = torchir.Scene.builtin("ajar_painting", resolution=RES, door=0, fill=0)
    key = "painting.bsdf.reflectance.data"
    for sampler in (None, ReSTIRSampler(scene, burn_in=2)):
        img, grad = _texture_gradient(scene, key, sampler)
        assert torch.equal(img, torch.zeros_like(img)), "light leaks into the closed room"
        assert not bool(grad.isnan().any()) and torch.equal(grad, torch.zeros_like(grad))


def test_ajar_painting_is_lit_mostly_through_the_door_gap(scenes):
    key = "painting.bsdf.reflectance.data"
    gap_only = torchir.Scene.builtin("ajar_painting", resolution=RES, fill=0)
    img, grad = _texture_gradient(gap_only, key)
    assert float(img.mean()) > 0.05 and float(grad.abs().sum()) > 0  # the gap light reaches the painting
    fill_only = torchir.Scene.builtin("ajar_painting", resolution=RES, door=0)
    both = render(scenes["ajar_painting"], {}, spp=256, seed=1)
    assert float(render(fill_only, {}, spp=4, seed=1).mean()) < 0.25 * float(both.mean())
    # the gap light is hidden: almost every point of it is occluded from the painting's centre
    mi_scene = gap_only.mi_scene
    light = next(e for e in mi_scene.emitters() if e.get_shape() is not None)
    si = dr.zeros(mi.SurfaceInteraction3f, 4096)
    si.p = mi.Point3f(0.0, 0.0, 0.002)
    si.n = mi.Normal3f(0, 0, 1)
    rng = np.random.default_rng(0)
    ps = light.get_shape().sample_position(0.0, mi.Point2f(rng.random(4096), rng.random(4096)))
    visible = ~mi_scene.ray_test(si.spawn_ray_to(ps.p))
    fraction = dr.count(visible)[0] / 4096
    assert 0 < fraction < 0.05


def test_many_lights_count_and_most_lights_are_occluded():
    assert len(torchir.Scene.builtin("many_lights", resolution=4, lights=40).mi_scene.emitters()) == 40
    scene = torchir.Scene.builtin("many_lights", resolution=4)
    emitters = scene.mi_scene.emitters()
    assert len(emitters) == 256
    lights = np.array([mi.traverse(e)["position"] for e in emitters], dtype=np.float64).reshape(-1, 3)
    grid = np.linspace(-0.8, 0.8, 5)
    points = np.array([(x, y, 0.0) for x in grid for y in grid])  # 25 canvas points
    p = np.repeat(points, len(lights), axis=0)
    q = np.tile(lights, (len(points), 1))
    si = dr.zeros(mi.SurfaceInteraction3f, len(p))
    si.p = mi.Point3f(*(p.T.astype(np.float32) + np.array([[0], [0], [1e-3]], np.float32)))
    si.n = mi.Normal3f(0, 0, 1)
    visible = ~scene.mi_scene.ray_test(si.spawn_ray_to(mi.Point3f(*q.T.astype(np.float32))))
    fraction = dr.count(visible)[0] / len(p)
    assert 0.01 < fraction < 0.3, fraction


def test_occluded_lights_blocker_is_a_mesh_whose_shadow_is_seen():
    scene = torchir.Scene.builtin("occluded_lights", resolution=RES)
    assert "blocker.vertex_positions" in scene.parameter_names(differentiable_only=True)
    corners = scene.get("blocker.vertex_positions").reshape(-1, 3)
    assert corners.shape == (8, 3) and torch.unique(corners, dim=0).shape[0] == 8  # welded: 8 shared corners
    turned = torchir.Scene.builtin("occluded_lights", resolution=RES, angle=75.0)
    a, b = render(scene, {}, spp=64, seed=0), render(turned, {}, spp=64, seed=0)
    assert float((a - b).abs().mean()) > 0.1 * float(a.mean())  # turning the blocker moves its shadow
    no_blocker = scene.get("blocker.vertex_positions") + torch.tensor([0.0, 0.0, 50.0]).repeat(8)
    lit = render(scene, {"blocker.vertex_positions": no_blocker}, spp=64, seed=0)
    assert float(lit.mean()) > 1.05 * float(a.mean())  # the shadow darkens the view


def test_oxalis_lite_views_on_an_arc_all_see_the_canvas():
    scene = torchir.Scene.builtin("oxalis_lite", resolution=16, views=3)
    assert scene.sensor_count == 3 and torchir.Scene.builtin("oxalis_lite", resolution=16).sensor_count == 1
    images = [render(scene, {}, spp=4, seed=1, sensor=v) for v in range(3)]
    assert all(float(i.mean()) > 0.01 for i in images)
    assert not torch.allclose(images[0], images[2])  # different viewpoints
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match=r"^views must be an int >= 1, got "):
            torchir.scenes.get("oxalis_lite").build(resolution=16, views=bad)


def test_occluded_lights_shadow_gradient_agrees_with_finite_differences():
    """The blocker is seen only through its shadow, so its gradient is direct_projective's
    secondary boundary term. With Mitsuba's ``cube`` (faces that do not share vertices) that term
    was 2.0x the finite-difference derivative; the welded box must agree within 4 s.e."""
    res, n, spp = 16, 48, 64
    scene = torchir.Scene.builtin("occluded_lights", resolution=res, override_integrator={"type": "direct_projective", "guiding": "none"})
    key = "blocker.vertex_positions"
    v0 = scene.get(key)
    up = torch.tensor([0.0, 0.0, 1.0]).repeat(v0.numel() // 3)  # the blocker moves up
    # weights that make the loss follow the shadow: the sign of the image's change
    image = lambda dz, seed: render(scene, {key: v0 + dz * up}, spp=4096, seed=seed)  # noqa: E731
    adjoint = torch.sign(image(0.02, 9) - image(-0.02, 9)) / (res * res)

    def loss(dz: float, seed: int) -> float:
        return float((image(dz, seed) * adjoint).sum())

    fd = sum((loss(0.02, s) - loss(-0.02, s)) / 0.04 for s in range(2)) / 2
    grads = []
    for i in range(n):
        dz = torch.zeros(1, requires_grad=True)
        (render(scene, {key: v0 + dz * up}, spp=spp, seed=100 + i) * adjoint).sum().backward()
        grads.append(float(dz.grad))
    g = torch.tensor(grads)
    se = float(g.std()) / n**0.5
    assert abs(fd) > 4 * se  # the shadow moves: a derivative the test can resolve
    assert abs(float(g.mean()) - fd) < 4 * se, (float(g.mean()), fd, se)


def test_unwelded_mesh_under_shape_gradients_warns_once():
    T = mi.ScalarTransform4f
    scene = torchir.Scene.from_dict({
        "type": "scene",
        "integrator": {"type": "direct_projective"},
        "sensor": {"type": "perspective", "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "light": {"type": "point", "position": [0, 0, 3], "intensity": {"type": "rgb", "value": 5.0}},
        "box": {"type": "cube"},  # 24 vertices: each face its own four
    })
    v = scene.get("box.vertex_positions").clone().requires_grad_(True)
    with pytest.warns(UserWarning, match=r"'box.vertex_positions': 16 of the mesh's 24 vertices repeat"):
        render(scene, {"box.vertex_positions": v}, spp=1, seed=0)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render(scene, {"box.vertex_positions": v}, spp=1, seed=1)
    assert not [w for w in caught if "repeat another vertex" in str(w.message)]  # once per scene and key
    welded = torchir.Scene.builtin("occluded_lights", resolution=RES)
    w = welded.get("blocker.vertex_positions").clone().requires_grad_(True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render(welded, {"blocker.vertex_positions": w}, spp=1, seed=0)
    assert not [x for x in caught if "repeat another vertex" in str(x.message)]
