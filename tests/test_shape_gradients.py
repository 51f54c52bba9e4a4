"""Shape gradients through boundary terms on the built-in scenes: a blocker seen only through its
shadow, and the welded meshes those terms need. Apart from ``test_scenes_restir.py``, whose
module-wide scenes include ``many_lights``: while its many emitters are alive every Dr.Jit call
over emitters covers them too (measured: these renders 5x slower)."""
from __future__ import annotations

import mitsuba as mi
import pytest
import torch

import torchir
from torchir.functions import render

RES = 16  # as tests/conftest.py: the kernels compile once


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
