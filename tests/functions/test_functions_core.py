"""torchir.functions core (argument checks, the bound op, frozen passes, sampler op, render,
render_gbuffers), pinned on tiny scenes whose images and gradients are known in closed form.

The "wall" scene: a pinhole camera facing a diffuse rectangle that exactly fills its 4x6 view,
lit head-on by a directional light of irradiance pi, nothing else. A camera ray through pixel
(y, x) hits texel (H-1-y, x) of the wall's nearest-filtered albedo texture, and the light
reflects ``albedo / pi * irradiance * cos 0 = albedo`` there; the path's next bounce escapes
(a directional light cannot be hit). So every sample of pixel (y, x) is exactly the albedo of
that texel: the image is the texture flipped upside down, with zero variance, and the gradient
of ``sum(w * image)`` is ``spp * (w / spp)`` = ``w`` at the matching texel, and
``sum(w_c * albedo_c) / pi`` for the irradiance. (Float rounding aside: tolerance 1e-6.)
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import os
import warnings

import torchir  # noqa: I001 - before torch (its OpenMP setup)
import drjit as dr
import mitsuba as mi
import pytest
import torch
from torchir.functions import _args, _passes, gbuffers, render, render_gbuffers
from torchir.functions._bound_op import BoundRenderOp

from tests.helpers import H, SUN, TEX, W, albedo_texture, as_image, as_image1, close, raises, tea, wall_dict, weights

POSE = "wall.to_world"


def as_texture(image: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`as_image`: an image-space (C, H, W) weight at the texels it sees."""
    return image.permute(1, 2, 0).flip(0)


def assert_warned_from_caller(warning, caller: str) -> None:
    """The warning points at torchir's caller of the failed pass (stacklevel), not into
    _passes.py. Under mutmut its trampolines add frames, so there only "not _passes.py"."""
    if "MUTANT_UNDER_TEST" in os.environ:
        assert not warning.filename.endswith(os.path.join("functions", "_passes.py")), warning.filename
    else:
        assert warning.filename.endswith(os.path.join("functions", caller)), warning.filename


# ------------------------------------------------------------------------------ _args
def test_check_scene(wall):
    assert _args.check_scene(wall) is wall
    with raises(TypeError, "scene must be a torchir.Scene (Scene.builtin / from_file / from_dict), got str"):
        _args.check_scene("cbox")


def test_check_count():
    assert _args.check_count("spp", 1) == 1 and _args.check_count("passes", 7) == 7
    with raises(ValueError, "spp must be >= 1, got 0"):
        _args.check_count("spp", 0)
    with raises(ValueError, "passes must be >= 1, got -3"):
        _args.check_count("passes", -3)
    with raises(TypeError, "spp must be an int, got bool"):
        _args.check_count("spp", True)
    with raises(TypeError, "spp_grad must be an int, got float"):
        _args.check_count("spp_grad", 2.0)


def test_check_seed():
    assert _args.check_seed("seed", 0) == 0
    assert _args.check_seed("seed", 2**32 - 1) == 2**32 - 1
    with raises(ValueError, "seed must be in [0, 2^32), got 4294967296"):
        _args.check_seed("seed", 2**32)
    with raises(ValueError, "seed_grad must be in [0, 2^32), got -1"):
        _args.check_seed("seed_grad", -1)
    with raises(TypeError, "seed must be an int, got bool"):
        _args.check_seed("seed", False)
    with raises(TypeError, "seed must be an int, got float"):
        _args.check_seed("seed", 1.0)


def test_seeds_default_gradient_seed_is_a_tea_hash():
    for seed in (0, 5, 2**32 - 1):
        assert _args.seeds(seed, None) == (seed, tea(seed, 1)[0])
    assert _args.seeds(5, 7) == (5, 7)
    assert _args.seeds(0, 2**32 - 1) == (0, 2**32 - 1)
    with raises(ValueError, "seed_grad must differ from seed: a gradient pass that reuses the primal's samples is biased"):
        _args.seeds(4, 4)
    with raises(ValueError, "seed_grad must be in [0, 2^32), got -1"):
        _args.seeds(4, -1)
    with raises(ValueError, "seed must be in [0, 2^32), got -1"):
        _args.seeds(-1, 4)
    with raises(TypeError, "seed_grad must be an int, got float"):
        _args.seeds(4, 2.0)


def test_render_settings(wall):
    s = _args.render_settings(wall, 0, 3, 5, None, None)
    assert s == _args.RenderSettings(sensor=0, spp=3, seed=5, spp_grad=3, seed_grad=tea(5, 1)[0])
    assert _args.render_settings(wall, 0, 3, 5, 2, 9) == _args.RenderSettings(0, 3, 5, 2, 9)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.spp = 4
    with raises(ValueError, "spp_grad must be >= 1, got 0"):
        _args.render_settings(wall, 0, 3, 5, 0, None)
    with raises(ValueError, "spp must be >= 1, got 0"):
        _args.render_settings(wall, 0, 0, 5, None, None)
    with raises(IndexError, "sensor 1 out of range: the scene has 1 sensor(s)"):
        _args.render_settings(wall, 1, 3, 5, None, None)


def test_split_params(wall):
    assert _args.split_params(wall, None) == ({}, frozenset())
    plain, grad = albedo_texture(), torch.full((3,), 2.0).requires_grad_()
    values, names = _args.split_params(wall, {TEX: plain, SUN: grad})
    assert values[TEX] is plain and values[SUN] is grad and names == frozenset({SUN})
    with torch.no_grad():
        assert _args.split_params(wall, {SUN: grad})[1] == frozenset()
    # an nn.Parameter goes through as a plain tensor that still back-propagates to it
    param = torch.nn.Parameter(torch.full((3,), 2.0))
    values, names = _args.split_params(wall, {SUN: param})
    assert type(values[SUN]) is torch.Tensor and names == frozenset({SUN})
    (values[SUN] * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
    assert torch.equal(param.grad, torch.tensor([1.0, 2.0, 3.0]))
    with raises(ValueError, f"params[{SUN!r}] has shape (4,), expected (3,)"):
        _args.split_params(wall, {SUN: torch.zeros(4)})


def test_split_params_expands_derived_parameters():
    scene = torchir.Scene.from_dict(wall_dict())
    assert scene.derive(SUN, lambda level: level.expand(3), {"sun.level": [math.pi]}) == ["sun.level"]
    level = torch.tensor([2.0], requires_grad=True)
    values, names = _args.split_params(scene, {"sun.level": level})
    assert list(values) == [SUN] and names == frozenset({SUN})
    assert torch.equal(values[SUN].detach(), torch.full((3,), 2.0))


# ------------------------------------------------------------------ render: closed forms
def test_render_image_and_gradients_in_closed_form(wall, strict_warnings):
    tex = albedo_texture()
    x, sun = tex.clone().requires_grad_(), torch.full((3,), math.pi).requires_grad_()
    img = render(wall, {TEX: x, SUN: sun}, spp=3, seed=1)
    assert img.shape == (3, H, W) and img.dtype == torch.float32
    close(img.detach(), as_image(tex))
    w = weights()
    (img * w).sum().backward()
    close(x.grad, as_texture(w))
    close(sun.grad, (w * as_image(tex)).sum((1, 2)) / math.pi, 1e-5)
    assert _passes.passes(wall).frozen


@pytest.mark.parametrize("frozen", [True, False])
def test_second_sensor(frozen, strict_warnings):
    torchir.backend.set_frozen_renders(frozen)
    try:
        scene = torchir.Scene.from_dict(wall_dict(sensors=2))
        _passes.passes(scene)  # the passes read the setting when made
    finally:
        torchir.backend.set_frozen_renders(True)
    w = weights(13)
    for seed in range(3):
        x = albedo_texture().requires_grad_()
        img = render(scene, {TEX: x}, spp=2, seed=seed, sensor=1)
        close(img.detach(), as_image1(albedo_texture()))
        (img * w).sum().backward()
        close(x.grad, (w.permute(1, 2, 0).flip(1)))
    close(render(scene, {}, spp=1, sensor=0), as_image(albedo_texture()))
    g = render_gbuffers(scene, {TEX: 0.5 * albedo_texture()}, spp=1, sensor=1)
    assert torch.equal(g[:3], as_image1(0.5 * albedo_texture()))
    assert _args.render_settings(scene, 1, 1, 0, None, None).sensor == 1


def test_gradient_with_constant_parameters_bound(wall, strict_warnings):
    """Parameters bound without grad (a texture, a colour) are constants of the gradient pass."""
    tex = albedo_texture()
    sun = torch.full((3,), 2.0).requires_grad_()
    img = render(wall, {TEX: 0.5 * tex, SUN: sun}, spp=2, seed=3)
    close(img.detach(), as_image(tex) / math.pi)
    w = weights(1)
    (img * w).sum().backward()
    close(sun.grad, (w * as_image(0.5 * tex)).sum((1, 2)) / math.pi, 1e-5)
    x = tex.clone().requires_grad_()
    (render(wall, {TEX: x, SUN: torch.full((3,), 2 * math.pi)}, spp=2, seed=4) * w).sum().backward()
    close(x.grad, 2 * as_texture(w))


def test_render_defaults(cbox8):
    """spp=4, seed=0, sensor=0, spp_grad=spp, seed_grad=tea(seed): the same as Mitsuba's render."""
    with torch.no_grad():
        image = render(cbox8)
        assert torch.equal(image, render(cbox8, {}, 4, 0, 0))
        native = mi.render(torchir.Scene.builtin("cbox", resolution=8).mi_scene, seed=0, spp=4)
        assert torch.equal(image, native.torch().permute(2, 0, 1))
        assert not torch.equal(image, render(cbox8, {}, 5, 0))

    def grad(**kwargs):
        x = cbox8.get("red.reflectance.value").requires_grad_()
        (render(cbox8, {"red.reflectance.value": x}, spp=2, seed=7, **kwargs) * weights(2, (3, 8, 8))).sum().backward()
        return x.grad

    default = grad()  # (a traced and a frozen adjoint may sum in another order: last-bit differences)
    close(default, grad(spp_grad=2, seed_grad=tea(7, 1)[0]), 1e-5)
    assert float((default - grad(spp_grad=3)).abs().max()) > 1e-2
    assert float((default - grad(seed_grad=8)).abs().max()) > 1e-2


@pytest.mark.parametrize("frozen", [True, False])
def test_matches_native_mitsuba_with_gradient_seed_and_spp(frozen, strict_warnings):
    """Image and gradient equal mi.render + dr.backward with the same spp/seed/spp_grad/seed_grad,
    through the frozen passes (record, then replay) and unfrozen."""
    key = "red.reflectance.value"
    torchir.backend.set_frozen_renders(frozen)
    try:
        ours = torchir.Scene.builtin("cbox", resolution=8)
        _passes.passes(ours)  # the passes read the setting when made
    finally:
        torchir.backend.set_frozen_renders(True)
    native = torchir.Scene.builtin("cbox", resolution=8)
    params = mi.traverse(native.mi_scene)
    w = weights(3, (3, 8, 8))
    for seed in (3, 4, 5):
        red = ours.get(key).requires_grad_()
        img = render(ours, {key: red}, spp=2, seed=seed, spp_grad=3, seed_grad=seed + 10)
        (img * w).sum().backward()
        dr.enable_grad(params[key])
        params.update()
        ref = mi.render(native.mi_scene, params, spp=2, seed=seed, spp_grad=3, seed_grad=seed + 10)
        dr.backward(dr.sum(ref * mi.TensorXf(w.permute(1, 2, 0).contiguous().cpu().numpy()), axis=None))
        assert torch.equal(img.detach(), ref.torch().permute(2, 0, 1))
        torch.testing.assert_close(red.grad, dr.grad(params[key]).torch().reshape(3), rtol=1e-5, atol=1e-7)
        dr.disable_grad(params[key])
    assert _passes.passes(ours).frozen is frozen


def test_render_reseeds_the_sensor_sampler():
    scene = torchir.Scene.from_dict(wall_dict())
    with torch.no_grad():
        render(scene, {}, spp=3)
    assert scene.sensor(0).sampler().wavefront_size() == 1


# --------------------------------------------------------------------------- the bound op
class _BindLog:
    """Wraps scene.bind: records the owner of every binding."""

    def __init__(self, scene):
        self.scene, self.bind, self.owners = scene, scene.bind, []

    def __call__(self, values, grad_names=frozenset(), owner=None):
        self.owners.append(owner)
        return self.bind(values, grad_names, owner=owner)


@pytest.fixture()
def bind_log(wall, monkeypatch):
    log = _BindLog(wall)
    monkeypatch.setattr(wall, "bind", log)
    return log


def test_render_then_backward_binds_once(wall, bind_log, strict_warnings):
    x = albedo_texture().requires_grad_()
    img = render(wall, {TEX: x}, spp=2, seed=0)
    (owner,) = bind_log.owners
    assert isinstance(owner, BoundRenderOp) and wall.owns_live_binding(owner)
    w = weights(4)
    (img * w).sum().backward()
    assert len(bind_log.owners) == 1 and not wall.owns_live_binding(owner)
    close(x.grad, as_texture(w))


def test_interleaved_renders_rebind_their_own_values(wall, bind_log, strict_warnings):
    a, b = albedo_texture(), albedo_texture().flip(1) * 0.5
    xa, xb = a.clone().requires_grad_(), b.clone().requires_grad_()
    sa, sb = torch.full((3,), math.pi).requires_grad_(), torch.full((3,), 2 * math.pi).requires_grad_()
    img_a = render(wall, {TEX: xa, SUN: sa}, spp=2, seed=1)
    img_b = render(wall, {TEX: xb, SUN: sb}, spp=2, seed=2)
    close(img_b.detach(), 2 * as_image(b))
    wa, wb = weights(5), weights(6)
    (img_a * wa).sum().backward()  # B holds the scene: A re-binds its own values
    assert len(bind_log.owners) == 3 and bind_log.owners[2] is bind_log.owners[0]
    close(xa.grad, as_texture(wa))
    close(sa.grad, (wa * as_image(a)).sum((1, 2)) / math.pi, 1e-5)
    (img_b * wb).sum().backward()  # A's re-binding consumed the scene: B re-binds too
    assert len(bind_log.owners) == 4 and bind_log.owners[3] is bind_log.owners[1]
    close(xb.grad, 2 * as_texture(wb))
    close(sb.grad, (wb * as_image(b)).sum((1, 2)) / math.pi, 1e-5)


def test_double_render_before_one_backward(wall, strict_warnings):
    x = albedo_texture().requires_grad_()
    img1 = render(wall, {TEX: x}, spp=2, seed=1)
    img2 = render(wall, {TEX: x}, spp=3, seed=2)
    w1, w2 = weights(7), weights(8)
    ((img1 * w1).sum() + (img2 * w2).sum()).backward()
    close(x.grad, as_texture(w1 + w2))


def test_no_grad_render_has_no_graph(wall):
    x = albedo_texture().requires_grad_()
    with torch.no_grad():
        img = render(wall, {TEX: x}, spp=1)
    assert not img.requires_grad
    assert not render(wall, {TEX: x.detach()}, spp=1).requires_grad


def test_forward_mode_is_refused():
    with raises(NotImplementedError, "forward-mode derivatives through torchir's render are not supported"):
        BoundRenderOp().forward()
    assert BoundRenderOp().name() == "BoundRenderOp"


# ------------------------------------------------------------------------ frozen passes
def test_freezable_integrators(wall):
    from mitsuba.python.ad.integrators.prb import PRBIntegrator

    class CustomPRB(PRBIntegrator):
        pass

    assert _passes._freezable(wall.integrator)
    assert not _passes._freezable(CustomPRB(mi.Properties()))  # a Python integrator outside Mitsuba
    assert not _passes._freezable(mi.load_dict({"type": "path"}))  # not path replay
    assert _passes.passes(wall) is _passes.passes(wall)
    assert _passes.passes(wall) is not _passes.passes(torchir.Scene.from_dict(wall_dict()))


def test_replayable_bindings():
    """Frozen replays only for RGB textures and non-geometry values (see _passes' docstring)."""
    scene = torchir.Scene.from_dict(wall_dict())
    grey = torchir.Scene.from_dict(wall_dict(channels=1))
    passes, grey_passes = _passes.passes(scene), _passes.passes(grey)

    def bind(s, values):
        s.bind({k: s.to_drjit(k, mi.TensorXf(v.cpu().numpy())) for k, v in values.items()})

    pose = scene.get(POSE)
    cases = [
        (scene, {}, True),
        (scene, {TEX: albedo_texture()}, True),
        (scene, {SUN: torch.ones(3)}, True),
        (scene, {POSE: pose}, False),
        (scene, {TEX: albedo_texture(), POSE: pose}, False),
        (scene, {TEX: albedo_texture(), SUN: torch.ones(3)}, True),
        (grey, {TEX: albedo_texture()[..., :1].contiguous()}, False),
        (grey, {SUN: torch.ones(3)}, True),
    ]
    for s, values, replayable in cases:
        bind(s, values)
        assert _passes.passes(s)._replayable() is replayable, (s is grey, list(values))
    passes.frozen = False
    bind(scene, {})
    assert passes._replayable() is False
    assert grey_passes.frozen


_TRACES: dict[str, itertools.count] = {}  # opaque to dr.freeze: a counter it can see keys new recordings
_PASS_FUNCTIONS = {"primal": _passes._primal, "adjoint": _passes._adjoint}


def _counting_primal(*args):
    next(_TRACES["primal"])
    return _PASS_FUNCTIONS["primal"](*args)


def _counting_adjoint(*args):
    next(_TRACES["adjoint"])
    return _PASS_FUNCTIONS["adjoint"](*args)


def test_recordings_count_the_traces(monkeypatch, strict_warnings):
    """``recordings`` is how often the passes were traced, and stays constant once warm."""
    _TRACES.update(primal=itertools.count(), adjoint=itertools.count())
    monkeypatch.setattr(_passes, "_primal", _counting_primal)
    monkeypatch.setattr(_passes, "_adjoint", _counting_adjoint)
    scene = torchir.Scene.from_dict(wall_dict())
    w = weights(9)

    def step(seed):
        x = (albedo_texture() * (0.3 + 0.1 * seed)).requires_grad_()
        img = render(scene, {TEX: x}, spp=2, seed=seed)
        close(img.detach(), as_image(x.detach()))
        (img * w).sum().backward()
        close(x.grad, as_texture(w))

    for seed in range(3):
        step(seed)
    recordings = _passes.passes(scene).recordings
    for seed in range(10, 13):  # warm: new seeds and values replay
        step(seed)
    assert _passes.passes(scene).recordings == recordings
    traced = next(_TRACES["primal"]) + next(_TRACES["adjoint"])
    assert recordings == traced and next(_TRACES["adjoint"]) >= 2  # (read once each before)


def test_recordings_are_bounded_per_pass(strict_warnings):
    scene = torchir.Scene.from_dict(wall_dict())
    limit = torchir.backend.frozen_recordings(scene.sensor_count)
    assert limit == 10  # 8 + 2 per sensor, one sensor
    with torch.no_grad():
        for spp in range(1, limit + 3):  # more configurations than the bound
            render(scene, {}, spp=spp)
    assert _passes.passes(scene)._primal.n_cached_recordings == limit
    for spp in range(1, limit + 3):
        x = albedo_texture().requires_grad_()
        render(scene, {TEX: x}, spp=1, spp_grad=spp).sum().backward()
    assert _passes.passes(scene)._adjoint.n_cached_recordings == limit


@pytest.mark.parametrize("failing", ["_primal", "_adjoint", "partial _adjoint"])
def test_failed_frozen_pass_falls_back_loudly(failing):
    """A frozen pass that fails warns once, and the scene renders unfrozen from then on. A
    recording that fails after accumulating (part of) the gradient, as a thin lens's pixel
    adjoint does, must not count it twice."""
    scene = torchir.Scene.from_dict(wall_dict())
    passes = _passes.passes(scene)

    def fail(*args, **kwargs):
        if failing == "partial _adjoint":
            _passes._adjoint(*args, **kwargs)
        raise RuntimeError("boom")

    setattr(passes, failing.split()[-1], fail)
    x = albedo_texture().requires_grad_()
    w = weights(10)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        img = render(scene, {TEX: x}, spp=2, seed=0)
        (img * w).sum().backward()
    assert [str(r.message) for r in record] == [
        "frozen render pass failed (RuntimeError('boom')); this scene now renders unfrozen"
    ]
    assert_warned_from_caller(record[0], "render.py")
    assert passes.frozen is False and passes._replayable() is False
    close(img.detach(), as_image(albedo_texture()))
    close(x.grad, as_texture(w))


def test_unfrozen_renders_are_exact():
    torchir.backend.set_frozen_renders(False)
    try:
        scene = torchir.Scene.from_dict(wall_dict())
        _passes.passes(scene)  # the passes read the setting when made
    finally:
        torchir.backend.set_frozen_renders(True)
    w = weights(11)
    for seed in range(2):
        x = (albedo_texture() * (1 - 0.2 * seed)).requires_grad_()
        img = render(scene, {TEX: x}, spp=2, seed=seed)
        close(img.detach(), as_image(x.detach()))
        (img * w).sum().backward()
        close(x.grad, as_texture(w))
    assert not _passes.passes(scene).frozen and _passes.passes(scene).recordings == 0


# ------------------------------------------------------------- render(sampler=...) op
class _Integrator:
    """A stateful integrator: the wall's exact image as the step, a backward that records its
    arguments and gives each parameter the gradient ``seed`` (so the plumbing is visible)."""

    def __init__(self) -> None:
        self.steps, self.backwards, self.options = [], [], []

    def step(self, mi_scene, sensor, seed, spp, **options):
        self.steps.append((mi_scene, sensor, seed, spp))
        self.options.append(options)
        return mi.render(mi_scene, sensor=sensor, seed=seed, spp=spp), ("cache", seed)

    def backward(self, mi_scene, cache, grad_image, seed, spp, geometry, params):
        self.backwards.append((mi_scene, cache, float(dr.sum(grad_image.array)[0]), seed, spp, geometry, sorted(params)))
        for value in params.values():
            assert dr.grad_enabled(value)
            shape = dr.shape(value) if dr.is_tensor_v(value) else dr.width(value)
            dr.set_grad(value, dr.full(type(value), float(seed), shape))


class _Sampler:
    def __init__(self, scene) -> None:
        self.scene, self.integrator, self.checked = scene, _Integrator(), []

    def render_seed(self, seed: int) -> int:
        return 3 * seed + 1

    def check_gradients(self, grad_names) -> None:
        self.checked.append(grad_names)


def test_sampler_render_reaches_its_integrator(wall):
    sampler = _Sampler(wall)
    x = albedo_texture().requires_grad_()
    img = render(wall, {TEX: x, SUN: torch.full((3,), math.pi)}, spp=2, seed=5, spp_grad=3, seed_grad=9, sampler=sampler)
    assert sampler.checked == [frozenset({TEX})]
    assert sampler.integrator.steps == [(wall.mi_scene, 0, 16, 2)]
    assert sampler.integrator.options == [{}]  # an integrator without zero_remainder gets no option
    assert img.shape == (3, H, W)
    close(img.detach(), as_image(albedo_texture()))
    (2.0 * img).sum().backward()
    assert sampler.integrator.backwards == [(wall.mi_scene, ("cache", 16), 2.0 * H * W * 3, 28, 3, False, [TEX])]
    assert torch.equal(x.grad, torch.full_like(x, 28.0))


def test_sampler_render_flags_geometry_and_seeds_by_default(wall):
    sampler = _Sampler(wall)
    x, pose = albedo_texture().requires_grad_(), wall.get(POSE).requires_grad_()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # geometry under prb: interior term only
        img = render(wall, {TEX: x, POSE: pose}, spp=1, seed=2, sampler=sampler)
    img.sum().backward()
    ((_, _, _, seed, spp, geometry, names),) = sampler.integrator.backwards
    assert (seed, spp, geometry, names) == (3 * tea(2, 1)[0] + 1, 1, True, sorted([TEX, POSE]))
    assert sampler.integrator.steps[0][1:] == (0, 7, 1)
    assert torch.equal(x.grad, torch.full_like(x, float(seed))) and pose.grad is not None


def test_sampler_interleaved_backwards_get_their_own_cache(wall):
    sampler = _Sampler(wall)
    xa, xb = albedo_texture().requires_grad_(), (0.5 * albedo_texture()).requires_grad_()
    img_a = render(wall, {TEX: xa}, spp=1, seed=1, seed_grad=2, sampler=sampler)
    img_b = render(wall, {TEX: xb}, spp=1, seed=3, seed_grad=4, sampler=sampler)
    close(img_b.detach(), as_image(0.5 * albedo_texture()))
    img_a.sum().backward()
    img_b.sum().backward()
    assert [b[1] for b in sampler.integrator.backwards] == [("cache", 4), ("cache", 10)]
    assert torch.equal(xa.grad, torch.full_like(xa, 7.0)) and torch.equal(xb.grad, torch.full_like(xb, 13.0))


def test_sampler_asks_for_the_zero_remainder_where_a_differentiated_value_is_zero(wall):
    """An integrator with ``zero_remainder = True`` gets ``zero_remainder=`` in each step: True
    exactly when a differentiated non-geometry value has an entry 0 (ReSTIR's black texels)."""
    black = albedo_texture()
    black[1, 2, 1] = 0.0
    pose = wall.get(POSE)  # a transform with zero entries: geometry is not asked about
    cases = [
        ({TEX: albedo_texture()}, {TEX}, False),
        ({TEX: black}, {TEX}, True),
        ({SUN: torch.tensor([1.0, 0.0, 2.0])}, {SUN}, True),
        ({SUN: torch.tensor([1.0, 1.0, 2.0])}, {SUN}, False),
        ({SUN: torch.tensor([1.0, 1.0, 2.0]), TEX: black}, {SUN}, False),  # the black texture is a constant
        ({POSE: pose, TEX: albedo_texture()}, {POSE, TEX}, False),
        ({POSE: pose, TEX: black}, {POSE, TEX}, True),
    ]
    for zero_remainder in (True, False):
        sampler = _Sampler(wall)
        sampler.integrator.zero_remainder = zero_remainder
        for values, differentiated, expected in cases:
            params = {k: v.clone().requires_grad_(k in differentiated) for k, v in values.items()}
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # geometry under prb: interior term only
                render(wall, params, spp=1, sampler=sampler).sum().backward()
        want = [{"zero_remainder": expected} for _, _, expected in cases] if zero_remainder else [{}] * len(cases)
        assert sampler.integrator.options == want


def test_differentiates_a_zero_skips_geometry_in_any_order(wall):
    from torchir.functions._sampler_op import SamplerRenderOp

    black = albedo_texture()
    black[0, 0, 2] = 0.0
    native = {
        TEX: wall.to_drjit(TEX, mi.TensorXf(black.cpu().numpy())),
        POSE: wall.to_drjit(POSE, mi.TensorXf(wall.get(POSE).cpu().numpy())),
        SUN: wall.to_drjit(SUN, mi.TensorXf(torch.ones(3).cpu().numpy())),
    }
    op = SamplerRenderOp()
    op.values = native
    for names, expected in [((POSE, TEX), True), ((TEX, POSE), True), ((POSE, SUN), False), ((POSE,), False)]:
        op.grad_names = names
        assert op.differentiates_a_zero() is expected, names


def test_sampler_errors(wall):
    other = torchir.Scene.from_dict(wall_dict())
    with raises(ValueError, "the _Sampler was built for another Scene: build one per scene"):
        render(wall, {}, spp=1, sampler=_Sampler(other))

    class NoCheck:
        scene, integrator = wall, _Integrator()

        def render_seed(self, seed):
            return seed

    with raises(
        TypeError,
        "render(sampler=...) takes a sampler with its own integrator, such as torchir.samplers.ReSTIRSampler, "
        "got NoCheck (pixel samplers go through render_pixels)",
    ):
        render(wall, {}, spp=1, sampler=NoCheck())


# ----------------------------------------------------------------------------- G-buffers
def test_gbuffer_channel_names():
    assert gbuffers.GBUFFER_CHANNELS == ("albedo.r", "albedo.g", "albedo.b", "normal.x", "normal.y", "normal.z", "depth")


def test_gbuffers_of_the_wall(wall):
    x = (0.5 * albedo_texture()).requires_grad_()
    g = render_gbuffers(wall, {TEX: x}, spp=2, seed=1)
    assert g.shape == (7, H, W) and g.dtype == torch.float32 and g.is_contiguous()
    assert not g.requires_grad and x.grad is None
    assert torch.equal(g[:3], as_image(0.5 * albedo_texture()))
    assert torch.equal(g[3:6], torch.tensor([0.0, 0.0, 1.0])[:, None, None].expand(3, H, W))
    # depth: ray length from the near clip plane; the wall is 5 ahead, its corners sqrt(25 + 1 + 4/9)
    near = wall.get("sensor.near_clip").item()
    assert bool((g[6] > 5 - near - 1e-4).all()) and bool((g[6] < math.sqrt(25 + 1 + (H / W) ** 2)).all())
    assert wall.sensor(0).sampler().wavefront_size() == 1
    assert torch.equal(render_gbuffers(wall)[:3], as_image(albedo_texture()))  # params unbound again


def test_gbuffers_defaults_and_native_aov(cbox8):
    g = render_gbuffers(cbox8)
    assert torch.equal(g, render_gbuffers(cbox8, None, 4, 0, 0))
    assert not torch.equal(g, render_gbuffers(cbox8, None, 5, 0, 0))
    assert not torch.equal(g, render_gbuffers(cbox8, None, 4, 1, 0))
    aov = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth"})
    native = mi.render(torchir.Scene.builtin("cbox", resolution=8).mi_scene, integrator=aov, seed=3, spp=2)
    assert torch.equal(render_gbuffers(cbox8, {}, spp=2, seed=3), native.torch().permute(2, 0, 1))
    assert gbuffers._aov_integrator() is gbuffers._aov_integrator()


def test_aov_integrator_made_once_per_variant(wall, monkeypatch):
    monkeypatch.setattr(gbuffers, "_INTEGRATORS", {})
    g = render_gbuffers(wall, spp=1)
    assert torch.equal(g[:3], as_image(albedo_texture()))
    (variant,) = gbuffers._INTEGRATORS
    assert variant == torchir.backend.variant()
    assert gbuffers._aov_integrator() is gbuffers._INTEGRATORS[variant]


def test_gbuffers_between_render_and_backward(wall, strict_warnings):
    x = albedo_texture().requires_grad_()
    img = render(wall, {TEX: x}, spp=2, seed=0)
    g = render_gbuffers(wall, {TEX: 0.25 * albedo_texture()}, spp=1)
    assert torch.equal(g[:3], as_image(0.25 * albedo_texture()))
    w = weights(12)
    (img * w).sum().backward()
    close(x.grad, as_texture(w))


def test_gbuffer_errors(wall, monkeypatch):
    with raises(ValueError, "spp must be >= 1, got 0"):
        render_gbuffers(wall, spp=0)
    with raises(ValueError, "seed must be in [0, 2^32), got -1"):
        render_gbuffers(wall, seed=-1)
    with raises(IndexError, "sensor 1 out of range: the scene has 1 sensor(s)"):
        render_gbuffers(wall, sensor=1)
    with raises(ValueError, f"params[{SUN!r}] has shape (4,), expected (3,)"):
        render_gbuffers(wall, {SUN: torch.zeros(4)})
    with raises(TypeError, "scene must be a torchir.Scene (Scene.builtin / from_file / from_dict), got NoneType"):
        render_gbuffers(None)
    monkeypatch.setattr(gbuffers, "_aov_integrator", lambda: mi.load_dict({"type": "aov", "aovs": "dd:depth"}))
    with raises(RuntimeError, "aov integrator returned 1 channels, expected 7"):
        render_gbuffers(wall)
