"""render_pixels and probe_pixels pinned in closed form on the zero-variance "wall" scene of
test_functions_core (every sample of image pixel (y, x) is the albedo of texel (H-1-y, x)), on an
irradiance meter under a constant sky (every path is exactly pi * sky radiance, the camera ray
weight being pi), and against render() where the estimate is random (a thin lens)."""
from __future__ import annotations

import importlib
import math
import warnings

import torchir  # noqa: I001 - before torch (its OpenMP setup)
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch
from torchir.functions import probe, render, render_pixels
from torchir.functions.probe import probe_pixels
from torchir.testing import gradcheck
from torchir.scenes import _common

from tests.helpers import DEVICE, H, SUN, TEX, W, albedo_texture, as_image, as_image1, close, raises, tea, wall_dict, weights

rp = importlib.import_module("torchir.functions.render_pixels")  # the module (the package exports the function)
SKY = "sky.radiance.value"


def flat(texture: torch.Tensor) -> torch.Tensor:
    """(H*W, C) pixel values y * W + x of the wall with albedo ``texture``."""
    return texture.flip(0).reshape(-1, texture.shape[-1])


def texel_grad(index: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Gradient of sum(w * render_pixels(index)) w.r.t. the albedo: w summed onto the texels."""
    return torch.zeros(H * W, 3).index_add_(0, index.long(), w).reshape(H, W, 3).flip(0)


def blocks(h: int = H // 2, w: int = W // 2, scale: float = 1.0) -> torch.Tensor:
    """An (H, W, 3) texture constant on 2x2 blocks (the texels of an (h, w) texture)."""
    return (scale * albedo_texture(h, w)).repeat_interleave(2, 0).repeat_interleave(2, 1)


def meter_dict() -> dict:
    return {
        "type": "scene",
        "integrator": {"type": "prb"},
        "probe": {"type": "sphere", "sensor": {"type": "irradiancemeter", "film": _common.film(1, 1)}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 1.0, 2.0]}},
    }


# ------------------------------------------------------------------------ render_pixels
@pytest.mark.frozen
@pytest.mark.parametrize("dtype", [torch.int64, torch.int32])
def test_pixels_and_gradient_in_closed_form(wall, dtype, strict_warnings, settled_registry):
    """Values and gradient of listed pixels (unsorted, repeated), traced, recorded, replayed."""
    generator = torch.Generator(device=DEVICE).manual_seed(1)
    passes, recordings = rp._pixel_passes(wall), []
    for step in range(5):  # use 1 traces, use 2 records the frozen passes, uses 3-5 replay them
        index = torch.tensor([23, 0, 5, 6, 17, 5, 12, 18], dtype=dtype)
        index = index[torch.randperm(8, generator=generator)]
        tex = albedo_texture() * (1 - 0.2 * step)
        x, sun = tex.clone().requires_grad_(), torch.full((3,), math.pi).requires_grad_()
        out = render_pixels(wall, {TEX: x, SUN: sun}, index, spp=2, seed=step, spp_grad=3)
        assert out.shape == (8, 3) and out.dtype == torch.float32
        close(out.detach(), flat(tex)[index.long()])
        w = torch.rand(8, 3, generator=generator) + 0.5
        (out * w).sum().backward()
        close(x.grad, texel_grad(index, w))
        close(sun.grad, (w * flat(tex)[index.long()]).sum(0) / math.pi, 1e-5)
        recordings.append((passes._primal.n_recordings, passes._adjoint.n_recordings))
    assert recordings[2][0] >= 1 and recordings[2][1] >= 1
    assert recordings[2] == recordings[4]  # new seeds, values and pixels replay


def test_second_sensor_pixels_and_probes(strict_warnings):
    """Sensor 1 (rolled 180 degrees: pixel (y, x) sees texel (y, W-1-x)), traced and frozen."""
    scene = torchir.Scene.from_dict(wall_dict(sensors=2))
    index = torch.tensor([0, 7, 13, 23])
    for seed in range(3):
        x = albedo_texture().requires_grad_()
        out = render_pixels(scene, {TEX: x}, index, spp=2, seed=seed, sensor=1)
        close(out.detach(), albedo_texture().flip(1).reshape(-1, 3)[index])
        w = weights(seed, (4, 3))
        (out * w).sum().backward()
        close(x.grad, torch.zeros(H * W, 3).index_add_(0, index, w).reshape(H, W, 3).flip(1))
        radiance, derivative = probe_pixels(scene, {TEX: x}, [(H, W)], passes=1, seed=seed, sensor=1,
                                            tangents={TEX: albedo_texture() - 0.5})
        close(radiance[0][0], as_image1(albedo_texture()))
        close(derivative[0][0], as_image1(albedo_texture() - 0.5), 1e-4)


def test_every_pixel_once(wall):
    index = torch.arange(H * W)
    close(render_pixels(wall, {}, index, spp=1, seed=9), flat(albedo_texture()))


def test_camera_ray_weight_enters_value_and_gradient(strict_warnings):
    """An irradiance meter's rays carry the weight pi: under a constant sky every path is
    pi * radiance, and d(value)/d(radiance) = pi."""
    scene = torchir.Scene.from_dict(meter_dict())
    sky = torch.tensor([0.5, 1.0, 2.0], requires_grad=True)
    out = render_pixels(scene, {SKY: sky}, torch.tensor([0, 0, 0]), spp=3, seed=1)
    close(out.detach(), math.pi * sky.detach().expand(3, 3))
    out.sum().backward()
    close(sky.grad, torch.full((3,), 3 * math.pi))
    tangent = torch.tensor([1.0, -1.0, 2.0])
    radiance, derivative = probe_pixels(scene, {SKY: sky}, [(1, 1)], passes=2, seed=2, tangents={SKY: tangent})
    close(radiance[0], math.pi * sky.detach().reshape(1, 3, 1, 1).expand(2, 3, 1, 1))
    close(derivative[0], math.pi * torch.tensor([1.0, -1.0, 2.0]).reshape(1, 3, 1, 1).expand(2, 3, 1, 1), 1e-4)


def test_render_pixels_defaults_and_seeds(cbox8):
    key = "red.reflectance.value"
    index = torch.tensor([9, 27, 27, 40, 63])
    with torch.no_grad():
        default = render_pixels(cbox8, None, index)
        assert torch.equal(default, render_pixels(cbox8, {}, index, 1, 0, 0))
        assert not torch.equal(default, render_pixels(cbox8, {}, index, 2, 0, 0))
        assert not torch.equal(default, render_pixels(cbox8, {}, index, 1, 1, 0))
        assert not torch.equal(default[1], default[2])  # a repeated pixel is an independent draw
    w = weights(3, (5, 3))

    def grad(**kwargs):
        x = cbox8.get(key).requires_grad_()
        (render_pixels(cbox8, {key: x}, index, spp=2, seed=4, **kwargs) * w).sum().backward()
        return x.grad

    g = grad()  # (a traced and a frozen adjoint may sum in another order: last-bit differences)
    close(g, grad(spp_grad=2, seed_grad=tea(4, 1)[0]), 1e-5)
    assert float((g - grad(spp_grad=3)).abs().max()) > 1e-2
    assert float((g - grad(seed_grad=5)).abs().max()) > 1e-2


def thin_lens() -> torchir.Scene:
    d = wall_dict()
    d["sensor"]["type"] = "thinlens"
    d["sensor"].update(aperture_radius=0.3, focus_distance=2.5)  # the wall 5 away: blurred
    return torchir.Scene.from_dict(d)


def fallback_warnings(record) -> list[str]:
    messages = [str(r.message) for r in record]
    assert all(m.startswith("frozen render pass failed (RuntimeError(") for m in messages), messages
    assert all(m.endswith("); this scene now renders unfrozen") for m in messages), messages
    return messages


@pytest.mark.frozen
def test_thin_lens_falls_back_loudly_and_agrees_with_render():
    """A thin lens cannot be frozen (Mitsuba 3.9): the second call of a count, which records,
    falls back to unfrozen passes with one warning, as render() does (it raised before). The
    mean of render_pixels matches render's (z-test, 256 paths a pixel each; |z| > 5 has
    probability 6e-7 per entry) and resolves the blur."""
    scene = thin_lens()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        with torch.no_grad():
            a = torch.stack([render_pixels(scene, {}, torch.arange(H * W), spp=16, seed=s) for s in range(16)])
            b = torch.stack([render(scene, {}, spp=16, seed=100 + s).permute(1, 2, 0).reshape(-1, 3) for s in range(16)])
    assert len(fallback_warnings(record)) == 1 and not rp._pixel_passes(scene).full_passes.frozen
    se = (a.var(0) / 16 + b.var(0) / 16).sqrt()
    assert float(se.min()) > 0  # the lens blurs every pixel
    z = (a.mean(0) - b.mean(0)) / se
    assert float(z.abs().max()) < 5, z
    sharp = flat(albedo_texture())
    assert float(((a.mean(0) - sharp) / se).abs().max()) > 8  # the blur is resolved


@pytest.mark.frozen
def test_unfreezable_pixel_gradient_and_probe_fall_back():
    index = torch.tensor([7, 8, 15, 16])  # inner pixels: every blurred path still hits the wall
    for call in ("adjoint", "probe"):
        scene = thin_lens()
        rp._pixel_passes(scene).seen[("primal", 0, 4, 1)] = -100  # keep the primal unfrozen
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            for seed in range(3):
                x = albedo_texture().requires_grad_()
                if call == "adjoint":
                    render_pixels(scene, {TEX: x}, index, spp=1, seed=seed).sum().backward()
                    assert float(x.grad.sum()) == pytest.approx(12.0, rel=1e-5)  # 4 paths x 3 channels, one texel each
                else:
                    radiance, _ = probe_pixels(scene, {TEX: x}, [(2, 3)], passes=2, seed=seed)
                    assert radiance[0].shape == (2, 3, 2, 3)
        assert len(fallback_warnings(record)) == 1, call


def test_per_lane_and_seeded_sampler():
    lanes = rp._per_lane(mi.UInt32, mi.UInt32([7, 3, 9]), 2)
    assert lanes.numpy().tolist() == [7, 7, 3, 3, 9, 9]  # host: Dr.Jit arrays
    colours = rp._per_lane(mi.Color3f, mi.Color3f([1.0, 2.0], [3.0, 4.0], [5.0, 6.0]), 3)
    assert np.array(colours).T.tolist() == [[1, 3, 5]] * 3 + [[2, 4, 6]] * 3
    a, b, c = rp._seeded_sampler(5, 4), rp._seeded_sampler(5, 4), rp._seeded_sampler(6, 4)
    assert a.wavefront_size() == 4
    x, y, z = (s.next_1d().numpy() for s in (a, b, c))  # host: Dr.Jit arrays
    assert np.array_equal(x, y) and not np.array_equal(x, z) and len(set(x.tolist())) == 4


@pytest.mark.frozen
def test_frozen_counts_from_their_second_use():
    scene = torchir.Scene.from_dict(wall_dict())
    passes = rp._pixel_passes(scene)
    assert rp._pixel_passes(scene) is passes
    assert [passes._frozen(("a",)) for _ in range(3)] == [False, True, True]
    assert passes.seen == {("a",): 3}
    passes.full_passes.frozen = False  # bindings that do not replay: never frozen
    assert passes._frozen(("b",)) is False and passes._frozen(("b",)) is False
    passes.full_passes.frozen = True


def test_counts_used_once_are_forgotten():
    """Past 4 x the recording limit keys, a new key drops the keys used once (varying multi-view counts)."""
    scene = torchir.Scene.from_dict(wall_dict())  # the passes hold it weakly
    passes = rp._pixel_passes(scene)
    bound = 4 * passes.limit
    assert passes.limit == 10  # 8 + 2 per sensor, one sensor
    passes._frozen("twice")
    passes._frozen("twice")
    for k in range(bound - 2):
        passes._frozen(k)
    assert len(passes.seen) == bound - 1
    passes._frozen(bound - 2)  # bound keys: still at the bound
    assert len(passes.seen) == bound
    passes._frozen(0)  # a known key: nothing forgotten
    assert len(passes.seen) == bound and passes.seen[0] == 2
    passes._frozen("new")
    assert passes.seen == {"twice": 2, 0: 2, "new": 1}


def test_render_pixels_with_a_different_count_each_call(strict_warnings):
    """Counts (and probe lane counts) used once stay unfrozen: nothing is recorded."""
    wall = torchir.Scene.from_dict(wall_dict())
    for n in (3, 4, 5):
        index = torch.arange(n) * 4
        x = albedo_texture().requires_grad_()
        out = render_pixels(wall, {TEX: x}, index, spp=1, seed=n)
        close(out.detach(), flat(albedo_texture())[index])
        out.sum().backward()
        close(x.grad, texel_grad(index, torch.ones(n, 3)))
        radiance, _ = probe_pixels(wall, {}, [(1, n)], passes=1, seed=n)
        assert radiance[0].shape == (1, 3, 1, n)
    passes = rp._pixel_passes(wall)
    assert (passes._primal.n_recordings, passes._adjoint.n_recordings, passes._one_path.n_recordings) == (0, 0, 0)


@pytest.mark.frozen
def test_pixel_recordings_are_bounded(strict_warnings):
    """Each pixel pass keeps at most ``limit`` recordings (one per lane count; 8 + 2 per sensor)."""
    scene = torchir.Scene.from_dict(wall_dict())
    limit = rp._pixel_passes(scene).limit
    for n in range(1, limit + 3):
        for seed in range(2):  # a count freezes (records) on its second use
            x = albedo_texture().requires_grad_()
            render_pixels(scene, {TEX: x}, torch.arange(n), spp=1, seed=seed).sum().backward()
            probe_pixels(scene, {}, [(1, n)], passes=1, seed=seed)
    passes = rp._pixel_passes(scene)
    assert [f.n_cached_recordings for f in (passes._primal, passes._adjoint, passes._one_path)] == [limit] * 3


def test_pixel_passes_call_sample_as_mitsuba_render_does(strict_warnings):
    """As ADIntegrator.render: depth=UInt32(0), δaovs=None, active=True, and δL/state_in only in
    the backward pass (prb ignores depth and δaovs, a custom path-replay integrator may not)."""
    from mitsuba.python.ad.integrators.prb import PRBIntegrator

    calls = []

    class RecordingPRB(PRBIntegrator):
        def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
            depth = kwargs.get("depth", "missing")
            depth = (type(depth).__name__, depth.numpy().tolist()) if isinstance(depth, mi.UInt32) else depth  # host: a Dr.Jit array
            calls.append((mode, depth, kwargs.get("δaovs", "missing"), δL is None, state_in is None, bool(dr.all(active))))
            return super().sample(mode, scene, sampler, ray, δL, state_in, active, **kwargs)

    mi.register_integrator("torchir_test_recording_prb", lambda props: RecordingPRB(props))
    d = wall_dict()
    d["integrator"]["type"] = "torchir_test_recording_prb"
    scene = torchir.Scene.from_dict(d)
    x = albedo_texture().requires_grad_()
    out = render_pixels(scene, {TEX: x}, torch.tensor([3, 20]), spp=2, seed=1)
    close(out.detach(), flat(albedo_texture())[[3, 20]])
    out.sum().backward()
    close(x.grad, texel_grad(torch.tensor([3, 20]), torch.ones(2, 3)))
    radiance, _ = probe_pixels(scene, {}, [(H, W)], passes=1, seed=2)
    close(radiance[0][0], as_image(albedo_texture()))
    zero = (type(mi.UInt32(0)).__name__, [0])
    primal, backward = dr.ADMode.Primal, dr.ADMode.Backward
    assert calls == [
        (primal, zero, None, True, True, True),  # render_pixels
        (primal, zero, None, True, True, True),  # its adjoint: the primal replay...
        (backward, zero, None, False, False, True),  # ...and the backward pass
        (primal, zero, None, True, True, True),  # probe_pixels
    ]


# ------------------------------------------------------------------------------- checks
def test_check_index():
    assert rp._check_index(torch.tensor([0, 23]), 24).dtype == torch.int32
    assert rp._check_index(torch.tensor([3], dtype=torch.int32), 24).tolist() == [3]
    cases = [
        ([0, 1], TypeError, "index must be a torch.LongTensor of pixel indices, got list"),
        (torch.tensor([0.0]), TypeError, "index must be an integer tensor (int64 or int32), got torch.float32"),
        (torch.tensor([0], dtype=torch.int16), TypeError,
         "index must be an integer tensor (int64 or int32), got torch.int16"),
        (torch.zeros(2, 2, dtype=torch.long), ValueError, "index must be a non-empty 1-D tensor, got shape (2, 2)"),
        (torch.zeros(0, dtype=torch.long), ValueError, "index must be a non-empty 1-D tensor, got shape (0,)"),
        (torch.tensor([0, 24]), IndexError, "pixel index out of range: got [0, 24], the sensor has 24 pixels (y * W + x)"),
        (torch.tensor([5, -1]), IndexError, "pixel index out of range: got [-1, 5], the sensor has 24 pixels (y * W + x)"),
    ]
    for index, error, message in cases:
        with raises(error, message):
            rp._check_index(index, 24)


def test_render_pixels_input_errors(wall):
    with raises(IndexError, f"pixel index out of range: got [0, {H * W}], the sensor has {H * W} pixels (y * W + x)"):
        render_pixels(wall, {}, torch.tensor([0, H * W]))
    with raises(IndexError, "sensor 1 out of range: the scene has 1 sensor(s)"):
        render_pixels(wall, {}, torch.tensor([0]), sensor=1)
    with raises(ValueError, "spp must be >= 1, got 0"):
        render_pixels(wall, {}, torch.tensor([0]), spp=0)
    with raises(TypeError, "scene must be a torchir.Scene (Scene.builtin / from_file / from_dict), got dict"):
        render_pixels({}, {}, torch.tensor([0]))
    with raises(ValueError, f"params[{SUN!r}] has shape (4,), expected (3,)"):
        render_pixels(wall, {SUN: torch.zeros(4)}, torch.tensor([0]))
    path = torchir.Scene.from_dict(wall_dict(integrator="path"))
    message = (
        "render_pixels needs a path-replay integrator (prb, prb_basic, prbvolpath); the scene uses "
        f"{type(path.integrator).__name__}"
    )
    with raises(TypeError, message):
        render_pixels(path, {}, torch.tensor([0]))
    with raises(TypeError, message):
        probe_pixels(path, {}, [(1, 1)])


def test_non_box_filter_warns_once(wall, strict_warnings):
    render_pixels(wall, {}, torch.tensor([0]))  # box: silent
    scene = torchir.Scene.from_dict(wall_dict(rfilter="gaussian"))
    name = type(scene.sensor(0).film().rfilter()).__name__
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        render_pixels(scene, {}, torch.tensor([0]))
        render_pixels(scene, {}, torch.tensor([1]))
    two = torchir.Scene.from_dict(wall_dict(rfilter="gaussian", sensors=2))
    with warnings.catch_warnings(record=True) as record2:
        warnings.simplefilter("always")
        render_pixels(two, {}, torch.tensor([0]), sensor=1)
        render_pixels(two, {}, torch.tensor([0]), sensor=0)
        render_pixels(two, {}, torch.tensor([0]), sensor=1)
    message = (
        "sensor {} uses a " + name + " reconstruction filter: render_pixels estimates box-filtered pixels, which "
        "differ from this film's pixels. Use rfilter={{'type': 'box'}} (all built-in scenes do)."
    )
    assert [str(r.message) for r in record] == [message.format(0)]
    assert [str(r.message) for r in record2] == [message.format(1), message.format(0)]


# ------------------------------------------------------------------------------- probes
def test_grid_lanes():
    xs, ys, ws, hs = probe._grid_lanes([(2, 3), (1, 2)], 2)
    assert xs.tolist() == [0, 1, 2, 0, 1, 2] * 2 + [0, 1] * 2
    assert ys.tolist() == [0, 0, 0, 1, 1, 1] * 2 + [0, 0] * 2
    assert ws.tolist() == [3] * 12 + [2] * 4 and hs.tolist() == [2] * 12 + [1] * 4
    assert all(a.dtype == np.float32 for a in (xs, ys, ws, hs))
    lanes = probe._lanes(torchir.backend.variant(), ((2, 3), (1, 2)), 2)
    assert lanes is probe._lanes(torchir.backend.variant(), ((2, 3), (1, 2)), 2)
    assert all(isinstance(a, mi.Float) for a in lanes)
    assert [a.numpy().tolist() for a in lanes] == [a.tolist() for a in (xs, ys, ws, hs)]  # host: Dr.Jit arrays


@pytest.mark.frozen
def test_probe_radiance_and_derivative_in_closed_form(wall, strict_warnings, settled_registry):
    """Three grids (full, half, half again): each probe pixel is the block it covers, the
    derivative along a tangent is that tangent; traced, recorded, then replayed."""
    grids = [(H, W), (H // 2, W // 2), (H // 2, W // 2)]
    generator = torch.Generator(device=DEVICE).manual_seed(2)
    one_path, recordings = rp._pixel_passes(wall)._one_path, []
    for step in range(5):
        value = blocks(scale=1 - 0.2 * step).requires_grad_()
        tangent = (torch.randint(0, 2, (H // 2, W // 2, 3), generator=generator) * 2 - 1).float()
        tangent = tangent.repeat_interleave(2, 0).repeat_interleave(2, 1)
        radiance, derivative = probe_pixels(wall, {TEX: value}, grids, passes=2, seed=step, tangents={TEX: tangent})
        assert [r.shape for r in radiance] == [(2, 3, H, W), (2, 3, H // 2, W // 2), (2, 3, H // 2, W // 2)]
        assert [d.shape for d in derivative] == [r.shape for r in radiance]
        coarse, coarse_tangent = (t[::2, ::2] for t in (value.detach(), tangent))
        for got, want in zip(radiance, [value.detach(), coarse, coarse]):
            close(got, as_image(want).expand_as(got))
        for got, want in zip(derivative, [tangent, coarse_tangent, coarse_tangent]):
            close(got, as_image(want).expand_as(got), 1e-4)
        assert not any(r.requires_grad for r in radiance + derivative)
        recordings.append(one_path.n_recordings)
    assert recordings[2] >= 1 and recordings[2] == recordings[4]
    radiance, none = probe_pixels(wall, None, [(H, W)], passes=1, seed=1)
    assert none is None
    close(radiance[0][0], as_image(albedo_texture()))  # the loaded texture


def test_probe_defaults(wall):
    default, _ = probe_pixels(wall, {}, [(1, 1)])
    assert default[0].shape == (4, 3, 1, 1)
    explicit, _ = probe_pixels(wall, {}, [(1, 1)], passes=4, seed=0, sensor=0)
    assert torch.equal(default[0], explicit[0])
    other, _ = probe_pixels(wall, {}, [(1, 1)], passes=4, seed=1)
    assert not torch.equal(default[0], other[0])
    for _ in range(2):  # traced, then frozen: the passes are independent paths (random texels)
        many, _ = probe_pixels(wall, {}, [(1, 1)], passes=16, seed=2)
        assert len(set(many[0][:, 0].flatten().tolist())) > 4


def test_probe_central_difference(monkeypatch, wall):
    """radiance = (I(v + h t) + I(v - h t)) / 2, derivative = (I(v + h t) - I(v - h t)) / 2h, h = 1e-2
    by default, with the same paths (seed) at both points."""
    calls = []

    def one_path(scene, values, lanes, sensor, seed):
        calls.append((values, sensor, seed))
        v = values[SUN].double()
        f = (v**3).tolist()
        n = dr.width(lanes[0])
        return mi.Color3f(*(mi.Float([c] * n) for c in f))

    monkeypatch.setattr(probe, "_one_path", one_path)
    v, t = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([1.0, -1.0, 0.5], dtype=torch.float64)
    radiance, derivative = probe_pixels(wall, {SUN: v}, [(1, 1)], passes=1, seed=7, tangents={SUN: t})
    (plus, _, s1), (minus, _, s2) = calls
    assert s1 == s2 == 7
    assert torch.equal(plus[SUN], v + 1e-2 * t.float()) and torch.equal(minus[SUN], v - 1e-2 * t.float())
    fp, fm = plus[SUN].double() ** 3, minus[SUN].double() ** 3
    close(radiance[0].reshape(3).double(), (fp + fm) / 2, 1e-6)
    close(derivative[0].reshape(3).double(), (fp - fm) / 2e-2, 1e-3)
    calls.clear()
    probe_pixels(wall, {SUN: v}, [(1, 1)], passes=1, tangents={SUN: t}, step=0.5)
    assert torch.equal(calls[0][0][SUN], v + 0.5 * t.float())


def test_probe_input_errors(wall):
    with raises(ValueError, "grids is empty"):
        probe_pixels(wall, {}, [])
    with raises(ValueError, "grid sizes must be >= 1, got (0, 4)"):
        probe_pixels(wall, {}, [(2, 2), (0, 4)])
    with raises(ValueError, "grid sizes must be >= 1, got (4, 0)"):
        probe_pixels(wall, {}, [(4, 0)])
    with raises(KeyError, f"tangents for parameters not in params: [{SUN!r}]"):
        probe_pixels(wall, {TEX: albedo_texture()}, [(1, 1)], tangents={SUN: torch.ones(3)})
    with raises(ValueError, f"tangent of {SUN!r} has shape (4,), the parameter (3,)"):
        probe_pixels(wall, {SUN: torch.ones(3)}, [(1, 1)], tangents={SUN: torch.ones(4)})
    with raises(ValueError, "passes must be >= 1, got 0"):
        probe_pixels(wall, {}, [(1, 1)], passes=0)
    with raises(ValueError, "seed must be in [0, 2^32), got -1"):
        probe_pixels(wall, {}, [(1, 1)], seed=-1)
    with raises(IndexError, "sensor 2 out of range: the scene has 1 sensor(s)"):
        probe_pixels(wall, {}, [(1, 1)], sensor=2)
    with raises(ValueError, f"params[{SUN!r}] has shape (4,), expected (3,)"):
        probe_pixels(wall, {SUN: torch.ones(4)}, [(1, 1)])
    with raises(TypeError, "scene must be a torchir.Scene (Scene.builtin / from_file / from_dict), got int"):
        probe_pixels(3, {}, [(1, 1)])


# ------------------------------------------------------------ several sensors in one wavefront
MV_KEY = "object.bsdf.reflectance.data"


@pytest.fixture(scope="module")
def views3() -> torchir.Scene:
    return torchir.Scene.builtin("multiview", resolution=8, views=3, texture=4)


def test_listed_sensors_trace_each_lane_through_its_own_sensor(views3):
    """A lane's ray and path depend only on its sensor, pixel and lane number: lanes all in view 2
    render bitwise as with ``sensor=2``, whichever other sensors are listed and in what order."""
    hw = 64
    pixels = torch.tensor([3, 10, 40, 63])
    alone = render_pixels(views3, {}, pixels, spp=2, seed=5, sensor=2)
    assert torch.equal(render_pixels(views3, {}, 2 * hw + pixels, spp=2, seed=5, sensor=[0, 1, 2]), alone)
    assert torch.equal(render_pixels(views3, {}, hw + pixels, spp=2, seed=5, sensor=[0, 2]), alone)
    mixed = render_pixels(views3, {}, torch.tensor([3, hw + 10, 2 * hw + 40]), spp=2, seed=5, sensor=[0, 1, 2])
    swapped = render_pixels(views3, {}, torch.tensor([hw + 3, 10, 2 * hw + 40]), spp=2, seed=5, sensor=[1, 0, 2])
    assert torch.equal(mixed, swapped)
    other_views = render_pixels(views3, {}, torch.tensor([3, hw + 10, 2 * hw + 40]), spp=2, seed=5, sensor=[1, 2, 0])
    assert not torch.equal(mixed, other_views)  # the sensor really is per lane


def test_listed_sensors_gradient_matches_finite_differences(views3):
    index = torch.tensor([5, 64 + 20, 128 + 33, 128 + 34, 64 + 21, 9])
    w = torch.rand(6, 3, generator=torch.Generator(device=DEVICE).manual_seed(2)) + 0.5

    def loss(params, seed):
        return (render_pixels(views3, params, index, spp=16, seed=seed, sensor=[0, 1, 2]) * w).sum()

    assert gradcheck(loss, {MV_KEY: views3.get(MV_KEY).requires_grad_()}, seeds=range(6), directions=2)


@pytest.mark.frozen
def test_listed_sensors_replay_frozen_whatever_the_per_view_counts(views3, settled_registry):
    """One wavefront keys its recording on the listed sensors and the total count only: batches
    whose per-view counts change every step replay one recording (per-view passes re-traced)."""
    x = views3.get(MV_KEY).requires_grad_()
    g = torch.Generator(device=DEVICE).manual_seed(0)
    recordings = []
    for step in range(5):
        index = torch.randint(0, 3 * 64, (40,), generator=g)  # new per-view counts every step
        render_pixels(views3, {MV_KEY: x}, index, spp=1, seed=step, sensor=[0, 1, 2]).sum().backward()
        passes = rp._pixel_passes(views3)
        recordings.append(passes._primal.n_recordings + passes._adjoint.n_recordings)
    assert recordings[1] >= 2 and recordings[-1] == recordings[2]


@pytest.mark.parametrize(
    ("sensor", "error", "match"),
    [([], ValueError, "non-empty list"), ([0, True], TypeError, "list of ints"), ([0, 7], Exception, "7")],
)
def test_bad_sensor_lists_raise_clear_errors(views3, sensor, error, match):
    with pytest.raises(error, match=match):
        render_pixels(views3, {}, torch.tensor([0]), sensor=sensor)


def test_index_beyond_the_listed_sensors_is_explained(views3):
    with pytest.raises(IndexError, match=r"the 2 sensors have 128 pixels \(k \* H \* W \+ y \* W \+ x\)"):
        render_pixels(views3, {}, torch.tensor([0, 128]), sensor=[0, 1])
