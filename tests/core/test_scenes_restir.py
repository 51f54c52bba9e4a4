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

from tests.helpers import RES  # the kernels compile once

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


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_ajar_painting_closed_door_without_fill_is_exactly_dark():
    """No light reaches the closed room: the image and texture gradient are exactly 0 (not NaN)
    for prb, spatiotemporal reuse and guided persistent chains. (In CI: the geometry in
    test_ajar_painting_closed_door_and_no_fill_let_no_light_reach_the_painting, the renders in
    tests/integrators/test_light_guide.py::test_an_unlit_room_renders_exactly_zero_with_zero_gradients.)"""
    scene = torchir.Scene.builtin("ajar_painting", resolution=RES, door=0, fill=0)
    key = "painting.bsdf.reflectance.data"
    guided = ReSTIRSampler(scene, preset="persistent", burn_in=2, light_guide=0.5)  # its guides never find a light
    for sampler in (None, ReSTIRSampler(scene, burn_in=2), guided, guided):
        img, grad = _texture_gradient(scene, key, sampler)
        assert torch.equal(img, torch.zeros_like(img)), "light leaks into the closed room"
        assert not bool(grad.isnan().any()) and torch.equal(grad, torch.zeros_like(grad))


def test_ajar_painting_closed_door_and_no_fill_let_no_light_reach_the_painting():
    """The geometry behind the slow test above (whose rendering half runs in CI as
    tests/integrators/test_light_guide.py::test_an_unlit_room_renders_exactly_zero_with_zero_gradients):
    ``door=0`` closes the slit, so no segment from 4096 points of the gap light to 4096 points
    spread over the painting is unoccluded (the open door's slit passes a few percent of them,
    see the next test), and ``fill=0`` removes the fill light: the room holds no other emitter."""
    scene = torchir.Scene.builtin("ajar_painting", resolution=4, door=0, fill=0).mi_scene
    (light,) = scene.emitters()
    assert light.get_shape() is not None and light.get_shape().id() == "gap_light"
    rng = np.random.default_rng(1)
    n = 4096
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(*(rng.uniform(-0.95, 0.95, (2, n)).astype(np.float32)), np.full(n, 0.002, np.float32))
    si.n = mi.Normal3f(0, 0, 1)
    ps = light.get_shape().sample_position(0.0, mi.Point2f(rng.random(n), rng.random(n)))
    assert dr.count(~scene.ray_test(si.spawn_ray_to(ps.p)))[0] == 0
    opened = torchir.Scene.builtin("ajar_painting", resolution=4, fill=0).mi_scene
    assert dr.count(~opened.ray_test(si.spawn_ray_to(ps.p)))[0] > 0  # the same segments through the slit


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


def test_occluded_lights_crown_blocker_is_closed_and_mostly_off_the_shadow_outline():
    """The "Tree"-like blocker: a closed welded mesh of 6 r (r - 1) edges, of which only a few
    percent lie on its outline seen from the small light, casting a shadow like the box's."""
    from torchir.integrators._mesh_edges import edges_of

    rings = 12
    scene = torchir.Scene.builtin("occluded_lights", resolution=RES, blocker="crown", rings=rings)
    mesh = next(s for s in scene.mi_scene.shapes() if s.id() == "blocker")
    table = edges_of(mesh)
    assert len(table.a) == 6 * rings * (rings - 1)
    assert bool(np.all(table.c1 != table.c2))  # every edge between two faces: a closed surface
    v = scene.get("blocker.vertex_positions").reshape(-1, 3).double().cpu().numpy()
    a, b, c1, c2 = (v[i.astype(np.int64)] for i in (table.a, table.b, table.c1, table.c2))
    normal = np.cross(b - a, np.array([-2.6, 0.2, 2.3]) - a)  # the plane through the edge and the small light
    side1, side2 = np.einsum("ij,ij->i", c1 - a, normal), np.einsum("ij,ij->i", c2 - a, normal)
    outline = int(np.sum(side1 * side2 > 0))  # both faces on one side: the edge is on the outline
    assert 0 < outline < 0.15 * len(table.a), outline
    box = torchir.Scene.builtin("occluded_lights", resolution=RES)
    a, b = render(box, {}, spp=64, seed=0), render(scene, {}, spp=64, seed=0)
    unblocked = render(box, {"blocker.vertex_positions": box.get("blocker.vertex_positions") + 50.0}, spp=64, seed=0)
    assert float(b.mean()) < 0.97 * float(unblocked.mean())  # the crown's shadow darkens the view
    assert abs(float(a.mean()) - float(b.mean())) < 0.1 * float(a.mean())  # a shadow of about the box's size
    for bad in ({"blocker": "tree"}, {"blocker": "crown", "rings": 2}):
        with pytest.raises(ValueError, match=r"^(blocker must be|rings must be)"):
            torchir.scenes.get("occluded_lights").build(resolution=RES, **bad)


def test_pig_blind_stripes_the_light_on_the_blob():
    """``pig(blind=...)``: slats across the light's beam leave the blob lit in stripes (about
    the open 30 % of the light on average); bad periods are refused."""
    from torchir.scenes import pig

    open_scene = torchir.Scene.builtin("pig", resolution=RES)
    blind = torchir.Scene.builtin("pig", resolution=RES, blind=0.25)
    assert sum(s.id().startswith("slat_") for s in blind.mi_scene.shapes()) == 11
    a, b = render(open_scene, {}, spp=256, seed=0), render(blind, {}, spp=256, seed=0)
    ratio = float(b.mean()) / float(a.mean())
    assert 0.2 < ratio < 0.6, ratio  # the floor and blob get about the open share of the light
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match=r"^blind must be in \[0, 1\], got "):
            pig.build(resolution=RES, blind=bad)


def test_oxalis_lite_views_on_an_arc_all_see_the_canvas():
    scene = torchir.Scene.builtin("oxalis_lite", resolution=16, views=3)
    assert scene.sensor_count == 3 and torchir.Scene.builtin("oxalis_lite", resolution=16).sensor_count == 1
    images = [render(scene, {}, spp=4, seed=1, sensor=v) for v in range(3)]
    assert all(float(i.mean()) > 0.01 for i in images)
    assert not torch.allclose(images[0], images[2])  # different viewpoints
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match=r"^views must be an int >= 1, got "):
            torchir.scenes.get("oxalis_lite").build(resolution=16, views=bad)
