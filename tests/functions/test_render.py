"""render(): image and gradient against native Mitsuba and finite differences, the
interleaving/double-render trap, kernel reuse, extremes and every bad-input error."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import pytest
import torch

import torchir
from torchir.functions import render
from torchir.testing import gradcheck

from tests.helpers import DEVICE, RES

KEY = "red.reflectance.value"


def _weights(seed: int = 0) -> torch.Tensor:
    return torch.rand(3, RES, RES, generator=torch.Generator(device=DEVICE).manual_seed(seed))


def _grad(scene, value, seed, seed_grad=None, weights=None, spp=8):
    x = value.detach().clone().requires_grad_()
    img = render(scene, {KEY: x}, spp=spp, seed=seed, seed_grad=seed_grad)
    (img * (_weights() if weights is None else weights)).sum().backward()
    return x.grad


def test_shape_dtype_and_layout(cbox):
    img = render(cbox, spp=1, seed=0)
    assert img.shape == (3, RES, RES) and img.dtype == torch.float32
    assert bool(img.isfinite().all()) and float(img.min()) >= 0


def test_equals_native_mitsuba_image_and_gradient():
    """With the same seeds, torchir's op must reproduce mi.render + dr.backward exactly."""
    ours = torchir.Scene.builtin("cbox", resolution=RES)
    red = ours.get(KEY).requires_grad_()
    img = render(ours, {KEY: red}, spp=8, seed=3, seed_grad=11)
    w = _weights()
    (img * w).sum().backward()

    native = torchir.Scene.builtin("cbox", resolution=RES)
    params = mi.traverse(native.mi_scene)
    dr.enable_grad(params[KEY])
    params.update()
    ref = mi.render(native.mi_scene, params, spp=8, seed=3, seed_grad=11)
    dr.backward(dr.sum(ref * mi.TensorXf(w.permute(1, 2, 0).contiguous().cpu().numpy()), axis=None))

    assert torch.equal(img.detach(), ref.torch().permute(2, 0, 1))
    torch.testing.assert_close(red.grad, dr.grad(params[KEY]).torch().reshape(3), rtol=1e-5, atol=1e-6)


def test_gradient_matches_finite_differences_albedo(cbox, red):
    target = render(cbox, {}, spp=64, seed=1000).detach() * 0.7

    def loss(p, seed):
        return ((render(cbox, p, spp=16, seed=seed) - target) ** 2).mean()

    assert gradcheck(loss, {KEY: red}, seeds=range(12), directions=2)


def test_gradient_matches_finite_differences_texture(painting):
    key = "canvas.bsdf.reflectance.data"
    tex = painting.get(key).requires_grad_()
    w = _weights(1)

    def loss(p, seed):
        return (render(painting, p, spp=8, seed=seed) * w).mean()

    assert gradcheck(loss, {key: tex}, seeds=range(8), directions=3)


def test_interleaved_render_keeps_its_own_gradient(cbox):
    """Render A, then render B with other values, then backward A: A's gradient must be the
    one it gets alone (Mitsuba's op would replay B's scene)."""
    a = cbox.get(KEY)
    b = torch.tensor([0.05, 0.9, 0.1])
    alone = _grad(cbox, a, seed=5)

    xa, xb = a.clone().requires_grad_(), b.clone().requires_grad_()
    img_a = render(cbox, {KEY: xa}, spp=8, seed=5)
    img_b = render(cbox, {KEY: xb}, spp=8, seed=6)
    (img_b * _weights()).sum().backward()  # B first: the scene still holds B's binding
    (img_a * _weights()).sum().backward()
    torch.testing.assert_close(xa.grad, alone, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(xb.grad, _grad(cbox, b, seed=6), rtol=1e-5, atol=1e-7)
    assert not torch.allclose(xa.grad, xb.grad)  # the scenes really differed


def test_double_render_before_one_backward_sums_both(cbox):
    a = cbox.get(KEY)
    g1, g2 = _grad(cbox, a, seed=7), _grad(cbox, a, seed=8)
    x = a.clone().requires_grad_()
    img1 = render(cbox, {KEY: x}, spp=8, seed=7)
    img2 = render(cbox, {KEY: x}, spp=8, seed=8)
    ((img1 + img2) * _weights()).sum().backward()
    torch.testing.assert_close(x.grad, g1 + g2, rtol=1e-5, atol=1e-7)


def test_unlisted_parameters_keep_their_loaded_value(cbox):
    fresh = torchir.Scene.builtin("cbox", resolution=RES)
    render(cbox, {KEY: torch.tensor([0.9, 0.0, 0.9]), "green.reflectance.value": torch.zeros(3)}, spp=2, seed=1)
    assert torch.equal(render(cbox, {}, spp=4, seed=9), render(fresh, {}, spp=4, seed=9))


def test_only_tensors_requiring_grad_are_differentiated(cbox):
    green = cbox.get("green.reflectance.value")  # no grad
    red = cbox.get(KEY).requires_grad_()
    img = render(cbox, {KEY: red, "green.reflectance.value": green}, spp=4, seed=2)
    img.mean().backward()
    assert green.grad is None and red.grad is not None and float(red.grad.abs().sum()) > 0
    with torch.no_grad():
        assert not render(cbox, {KEY: red}, spp=1, seed=0).requires_grad


def test_kernels_are_reused_across_steps(cbox):
    """After warm-up, new seeds and new parameter values compile nothing."""
    red = cbox.get(KEY).requires_grad_()
    opt = torch.optim.Adam([red], lr=0.05)

    def step(seed):
        opt.zero_grad()
        render(cbox, {KEY: red}, spp=4, seed=seed).mean().backward()
        opt.step()

    for seed in range(2):
        step(seed)
    with torchir.backend.count_kernels() as stats:
        for seed in range(100, 104):
            step(seed)
    assert stats.launched > 0
    assert stats.compiled == 0 and stats.cache_misses == 0, stats


@pytest.mark.parametrize("radiance", [0.0, 1e6])
def test_extreme_radiance_stays_finite(radiance):
    scene = torchir.Scene.builtin("cbox", resolution=RES)
    light = torch.full((3,), radiance)
    red = scene.get(KEY).requires_grad_()
    img = render(scene, {KEY: red, "light.emitter.radiance.value": light}, spp=1, seed=0)
    img.mean().backward()
    assert bool(img.isfinite().all()) and bool(red.grad.isfinite().all())
    if radiance == 0.0:
        assert float(img.detach().abs().max()) == 0.0 and float(red.grad.abs().max()) == 0.0
    else:
        assert float(img.detach().max()) > 1e3


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("params", "error", "match"),
    [
        ({"red.reflectance.valu": torch.zeros(3)}, KeyError, "Did you mean 'red.reflectance.value'"),
        ({KEY: torch.zeros(4)}, ValueError, r"shape \(4,\), expected \(3,\)"),
        ({KEY: torch.zeros(3, dtype=torch.float64)}, TypeError, "float32"),
        ({KEY: torch.zeros(3, dtype=torch.int64)}, TypeError, "dtype"),
        ({KEY: torch.tensor([0.5, float("nan"), 0.5])}, ValueError, "1 NaN/Inf"),
        ({KEY: torch.tensor([0.5, float("inf"), 0.5])}, ValueError, "NaN/Inf"),
        ({KEY: [0.5, 0.5, 0.5]}, TypeError, "torch.Tensor"),
        ({"small-box.faces": torch.zeros(36)}, TypeError, "cannot bind from a tensor: it holds integers"),
        ([KEY], TypeError, "dict"),
    ],
)
def test_bad_params_raise_clear_errors(cbox, params, error, match):
    with pytest.raises(error, match=match):
        render(cbox, params, spp=1, seed=0)


def test_to_world_binds_as_a_4x4_transform(cbox):
    """A shape's to_world binds from a (4, 4) tensor (row-major, as Mitsuba prints it): moving the
    red wall out of view changes the image exactly as moving it in the scene dict would."""
    world = cbox.get("red-wall.to_world")
    assert world.shape == (4, 4) and cbox.info("red-wall.to_world").bindable
    same = render(cbox, {"red-wall.to_world": world}, spp=2, seed=3)
    assert torch.equal(same, render(cbox, {}, spp=2, seed=3))
    moved = world.clone()
    moved[0, 3] -= 10.0  # translate x by -10: far outside the box
    assert not torch.allclose(render(cbox, {"red-wall.to_world": moved}, spp=2, seed=3), same)


def test_texture_in_channel_first_layout_is_explained(painting):
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        render(painting, {"canvas.bsdf.reflectance.data": torch.zeros(3, 8, 8)}, spp=1)


def test_non_differentiable_parameter_with_grad(cbox):
    ball = torchir.Scene.builtin("glossy_ball", resolution=8)
    with pytest.raises(ValueError, match="non-differentiable"):
        render(ball, {"light.position": ball.get("light.position").requires_grad_()}, spp=1)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"spp": 0}, ValueError, "spp must be >= 1"),
        ({"spp": -3}, ValueError, "spp must be >= 1"),
        ({"spp": 2.5}, TypeError, "spp must be an int"),
        ({"spp_grad": 0}, ValueError, "spp_grad must be >= 1"),
        ({"seed": -1}, ValueError, "seed must be in"),
        ({"seed": 3, "seed_grad": 3}, ValueError, "must differ"),
        ({"sensor": 1}, IndexError, "sensor 1 out of range"),
    ],
)
def test_bad_settings_raise_clear_errors(cbox, kwargs, error, match):
    with pytest.raises(error, match=match):
        render(cbox, {}, **{"spp": 1, **kwargs})


def test_scene_must_be_a_torchir_scene(cbox):
    with pytest.raises(TypeError, match="torchir.Scene"):
        render(cbox.mi_scene, {}, spp=1)


# ---------------------------------------------------------------------- frozen render passes
def test_frozen_and_unfrozen_passes_agree_exactly():
    from torchir.functions._passes import passes

    w = _weights(2)
    results = []
    for frozen in (True, False):
        torchir.backend.set_frozen_renders(frozen)
        try:
            scene = torchir.Scene.builtin("cbox", resolution=RES)
            x = scene.get(KEY).requires_grad_()
            images = []
            for seed in range(3):  # record, then replay
                img = render(scene, {KEY: x}, spp=4, seed=seed)
                (img * w).sum().backward()
                images.append(img.detach())
            assert passes(scene).frozen is frozen
            results.append((torch.stack(images), x.grad.clone()))
        finally:
            torchir.backend.set_frozen_renders(True)
    assert torch.equal(results[0][0], results[1][0])
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-6, atol=0)


@pytest.mark.frozen
def test_warm_frozen_passes_do_not_retrace(cbox):
    from torchir.functions._passes import passes

    x = cbox.get(KEY).requires_grad_()
    for seed in range(3):
        render(cbox, {KEY: x * 0.9}, spp=4, seed=seed).mean().backward()
    recordings = passes(cbox).recordings
    for seed in range(10, 15):  # new seeds and new values
        render(cbox, {KEY: x * (0.5 + seed / 30)}, spp=4, seed=seed).mean().backward()
    assert passes(cbox).frozen and passes(cbox).recordings == recordings


def test_projective_integrators_run_unfrozen():
    from torchir.functions._passes import passes

    scene = torchir.Scene.from_dict(
        {"type": "scene", "integrator": {"type": "direct_projective"}, "sensor": {"type": "perspective"}, "s": {"type": "sphere"}}
    )
    assert not passes(scene).frozen


def test_nn_parameter_inputs_get_gradients(cbox):
    param = torch.nn.Parameter(cbox.get(KEY))
    opt = torch.optim.Adam([param], lr=0.1)
    render(cbox, {KEY: param}, spp=2, seed=0).mean().backward()
    assert param.grad is not None and float(param.grad.abs().sum()) > 0
    before = param.detach().clone()
    opt.step()
    assert not torch.equal(before, param.detach())


def test_one_channel_texture_rebinding_is_exact():
    """Re-binding a 1-channel bitmap made frozen replays read stale memory (values ~1e26); such
    renders run unfrozen, so the same values and seed give the same image again."""
    import mitsuba as mi

    from torchir.scenes import textured_wall

    description = textured_wall.build(16)
    description["back"]["bsdf"]["reflectance"]["data"] = mi.TensorXf(textured_wall.wall_texture(16, 1))
    scene = torchir.Scene.from_dict(description)
    key = "back.bsdf.reflectance.data"
    truth = scene.get(key)
    assert truth.shape[-1] == 1
    with torch.no_grad():
        first = render(scene, {key: truth}, spp=4, seed=5)
        other = render(scene, {key: torch.full_like(truth, 0.5)}, spp=4, seed=5)
        again = render(scene, {key: truth}, spp=4, seed=5)
    assert torch.equal(first, again) and not torch.equal(first, other)


def test_moved_geometry_renders_as_a_fresh_scene():
    """Frozen replays traced rays against the recorded geometry after a mesh moved; renders that
    bind geometry run unfrozen, so a moved box looks as it does in a freshly loaded scene."""
    import warnings

    key = "small-box.vertex_positions"
    moved = torchir.Scene.builtin("cbox", resolution=RES)
    fresh = torchir.Scene.builtin("cbox", resolution=RES)
    v = moved.get(key)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # geometry under prb: visibility edges are not differentiated
        for dz in (0.0, 0.1, 0.2):
            w = v.clone()
            w[2::3] += dz
            image = render(moved, {key: w}, spp=4, seed=3)
        reference = render(fresh, {key: w}, spp=4, seed=3)
    assert torch.equal(image, reference)


class _RecordingIntegrator:
    """A stateful integrator for render(sampler=): Mitsuba's own render as the step, and a
    backward that records what it was given."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def step(self, mi_scene, sensor, seed, spp):
        return mi.render(mi_scene, sensor=sensor, seed=seed, spp=spp), ("cache", seed)

    def backward(self, mi_scene, cache, grad_image, seed, spp, geometry, params):
        self.calls.append((cache, float(dr.sum(grad_image.array)[0]), seed, spp, geometry, sorted(params)))


class _RecordingSampler:
    def __init__(self, scene) -> None:
        self.scene, self.integrator, self.refused = scene, _RecordingIntegrator(), set()

    def render_seed(self, seed: int) -> int:
        return seed + 1

    def check_gradients(self, grad_names) -> None:
        bad = self.refused & set(grad_names)
        if bad:
            raise ValueError(f"cannot differentiate {sorted(bad)}")


def test_render_takes_any_sampler_with_its_own_integrator(cbox, red):
    """render(sampler=) needs only the RenderSampler protocol (the boundary does not know the
    ReSTIR classes): the step's image comes back as (C, H, W), and backward reaches the
    integrator with this render's cache, the gradient image, seed_grad and spp_grad."""
    sampler = _RecordingSampler(cbox)
    img = render(cbox, {KEY: red}, spp=2, seed=5, spp_grad=3, seed_grad=9, sampler=sampler)
    expected = torch.as_tensor(mi.render(cbox.mi_scene, seed=6, spp=2).numpy(), device=DEVICE).permute(2, 0, 1)  # host: a Dr.Jit array
    torch.testing.assert_close(img.detach(), expected)
    (2.0 * img).sum().backward()
    (call,) = sampler.integrator.calls
    assert call == (("cache", 6), 2.0 * img.numel(), 10, 3, False, [KEY])
    sampler.refused = {KEY}
    with pytest.raises(ValueError, match=r"cannot differentiate \['red.reflectance.value'\]"):
        render(cbox, {KEY: red}, spp=1, sampler=sampler)
    with pytest.raises(TypeError, match="takes a sampler with its own integrator"):
        render(cbox, {KEY: red}, spp=1, sampler=object())


@pytest.mark.frozen
def test_many_views_replay_without_re_recording(capfd):
    """A frozen pass keeps a recording per sensor: with more sensors than the base LRU bound (8),
    rendering every view each epoch used to re-record every call (16 views: ~1.6 s a step).
    Those recordings are expected, so Dr.Jit does not warn about them."""
    from torchir.backend import _RECORDINGS_PER_PASS
    from torchir.functions._passes import passes

    views = _RECORDINGS_PER_PASS + 2
    scene = torchir.Scene.builtin("multiview", resolution=8, views=views, texture=4)
    key = "object.bsdf.reflectance.data"
    x = scene.get(key).requires_grad_()
    counts = []
    capfd.readouterr()
    for epoch in range(4):
        for view in range(views):
            render(scene, {key: x}, sensor=view, spp=1, seed=epoch * views + view).mean().backward()
        counts.append(passes(scene).recordings)
    assert passes(scene).frozen and counts[1] >= 2 * views  # a primal and an adjoint recording per view
    assert counts[3] == counts[1]  # warm (as a single view, from its second call): no more recordings
    assert "has been recorded" not in capfd.readouterr().err


def test_the_silhouette_check_judges_each_scene_by_its_own_view(tmp_path):
    """One open tube (a one-sided material) in two scenes: looked into along its axis, the camera
    sees the tube's inside past its rim, and direct_projective is refused; from the side, the rim's
    inside is hidden behind the near wall, and it renders. The verdict was kept by the mesh's
    address: the second scene got the first's (in CI, a closed blob was refused once a freed
    tube's mesh had left it its address)."""
    from torchir.bench.exported_meshes import open_cylinder, write_obj

    write_obj(open_cylinder(), tmp_path / "tube.obj")
    tube = mi.load_dict({"type": "obj", "id": "tube", "filename": str(tmp_path / "tube.obj"), "bsdf": {"type": "diffuse"}})

    def scene(origin):
        return torchir.Scene.from_dict({
            "type": "scene", "integrator": {"type": "direct_projective"}, "tube": tube,
            "light": {"type": "point", "position": [0.0, 0.0, 3.0], "intensity": 10.0},
            "sensor": {"type": "perspective", "fov": 40, "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        })

    from torchir.functions.render import _check_projective_silhouettes  # what render runs first

    key = "tube.vertex_positions"
    for order in ((True, False), (False, True)):
        scenes = {inside: scene([0.0, 0.0, 3.0] if inside else [3.0, 0.0, 0.0]) for inside in order}
        for inside, s in scenes.items():
            if inside:
                with pytest.raises(ValueError, match="back of its one-sided material past an open border"):
                    render(s, {key: s.get(key).requires_grad_()}, spp=1, seed=0)
            else:
                _check_projective_silhouettes(s, frozenset({key}), 0)  # no error (rendering it compiles seconds of kernels)
