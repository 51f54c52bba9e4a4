"""render_pixels(): statistical agreement with render (values and gradients), index handling,
interleaving, and errors."""
from __future__ import annotations

import math

import pytest
import torch

import torchir
from torchir.functions import render, render_pixels

from tests.helpers import DEVICE, RES, run_in_fresh_process

KEY = "red.reflectance.value"
ALL = torch.arange(RES * RES)


def _z(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """z-scores of mean(a) - mean(b) over dim 0, from the samples' own variances."""
    se2 = a.var(0) / a.shape[0] + b.var(0) / b.shape[0]
    return (a.mean(0) - b.mean(0)) / se2.clamp_min(1e-30).sqrt()


def test_shape_repeats_and_budgets(cbox):
    one = render_pixels(cbox, {}, torch.tensor([17]), spp=1, seed=0)
    assert one.shape == (1, 3)
    over = torch.cat([ALL, ALL])  # a budget larger than the image: draws with replacement
    values = render_pixels(cbox, {}, over, spp=1, seed=0)
    assert values.shape == (2 * RES * RES, 3) and bool(values.isfinite().all())
    assert not torch.equal(values[: RES * RES], values[RES * RES :])  # repeats are independent draws


def test_pixel_values_agree_with_render(cbox):
    """Per pixel, the mean of R independent subset renders matches R full renders."""
    R = 24
    subset = torch.stack([render_pixels(cbox, {}, ALL, spp=4, seed=s) for s in range(R)])  # (R, P, 3)
    full = torch.stack([render(cbox, {}, spp=4, seed=1000 + s).permute(1, 2, 0).reshape(-1, 3) for s in range(R)])
    z = _z(subset, full)
    z = z[subset.var(0) + full.var(0) > 0]
    # |z| > 4 has probability 6e-5 per entry under the null (t with 46 dof: ~3e-4).
    assert float((z.abs() > 4).float().mean()) < 0.01, z.abs().max()
    assert abs(float(z.mean())) < 4 / math.sqrt(z.numel()) * 3  # no systematic offset


def test_gradient_agrees_with_render(cbox):
    """E[grad of a pixel-subset loss over all pixels] == E[grad of the full-image loss]."""
    w = torch.rand(RES * RES, 3, generator=torch.Generator(device=DEVICE).manual_seed(3))
    R = 24

    def grad_subset(seed):
        x = cbox.get(KEY).requires_grad_()
        (render_pixels(cbox, {KEY: x}, ALL, spp=4, seed=seed) * w).sum().backward()
        return x.grad

    def grad_full(seed):
        x = cbox.get(KEY).requires_grad_()
        (render(cbox, {KEY: x}, spp=4, seed=seed).permute(1, 2, 0).reshape(-1, 3) * w).sum().backward()
        return x.grad

    gs = torch.stack([grad_subset(s) for s in range(R)])
    gf = torch.stack([grad_full(500 + s) for s in range(R)])
    assert float(gs.abs().mean()) > 0
    assert bool((_z(gs, gf).abs() < 4).all()), _z(gs, gf)


def test_interleaved_pixel_renders(cbox):
    index = torch.tensor([3, 40, 41, 200])
    a, b = cbox.get(KEY), torch.tensor([0.0, 0.8, 0.2])

    def alone(value, seed):
        x = value.clone().requires_grad_()
        render_pixels(cbox, {KEY: x}, index, spp=8, seed=seed).sum().backward()
        return x.grad

    xa, xb = a.clone().requires_grad_(), b.clone().requires_grad_()
    va = render_pixels(cbox, {KEY: xa}, index, spp=8, seed=1)
    vb = render_pixels(cbox, {KEY: xb}, index, spp=8, seed=2)
    (va.sum() + vb.sum()).backward()
    torch.testing.assert_close(xa.grad, alone(a, 1), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(xb.grad, alone(b, 2), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    ("index", "error", "match"),
    [
        (torch.tensor([0, RES * RES]), IndexError, "out of range"),
        (torch.tensor([-1, 3]), IndexError, "out of range"),
        (torch.tensor([0.0, 1.0]), TypeError, "integer tensor"),
        (torch.zeros(2, 2, dtype=torch.long), ValueError, "1-D"),
        (torch.zeros(0, dtype=torch.long), ValueError, "non-empty"),
        ([0, 1], TypeError, "LongTensor"),
    ],
)
def test_bad_index(cbox, index, error, match):
    with pytest.raises(error, match=match):
        render_pixels(cbox, {}, index, spp=1, seed=0)


def test_needs_a_path_replay_integrator():
    scene = torchir.Scene.from_dict(
        {"type": "scene", "integrator": {"type": "path"}, "sensor": {"type": "perspective"}, "s": {"type": "sphere"}}
    )
    with pytest.raises(TypeError, match="path-replay integrator"):
        render_pixels(scene, {}, torch.tensor([0]), spp=1)


def test_warns_about_non_box_filters():
    scene = torchir.Scene.from_dict(
        {
            "type": "scene",
            "integrator": {"type": "prb"},
            "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
            "s": {"type": "sphere"},
        }
    )
    with pytest.warns(UserWarning, match="box"):
        render_pixels(scene, {}, torch.tensor([0]), spp=1)


@pytest.mark.frozen
def test_frozen_replays_match_a_fresh_unfrozen_call():
    """From the second use of a pixel count, the passes are frozen; a replay with new pixels,
    values and seeds gives what a fresh (unfrozen) scene gives for the same call. In a fresh
    process (:func:`tests.helpers.run_in_fresh_process`: in the shared worker this test's replays
    once left the session scene's mesh pointing at freed memory)."""
    code = f"""
import torch, torchir
from torchir.functions import render_pixels
from torchir.functions.render_pixels import _pixel_passes

key = "red.reflectance.value"
replayed, fresh = (torchir.Scene.builtin("cbox", resolution={RES}) for _ in range(2))
generator = torch.Generator(device=torchir.backend.device()).manual_seed(0)

def call(scene, index, value, seed):
    red = value.clone().requires_grad_()
    out = render_pixels(scene, {{key: red}}, index, spp=2, seed=seed)
    out.sum().backward()
    return out.detach(), red.grad

for step in range(3):  # use 1 traces, use 2 records, use 3 replays
    index = torch.randint(0, {RES * RES}, (40,), generator=generator)
    value = torch.rand(3, generator=generator)
    out, grad = call(replayed, index, value, seed=step)
reference_out, reference_grad = call(fresh, index, value, seed=2)
passes = _pixel_passes(replayed)
assert passes._primal.n_recordings >= 1 and passes._adjoint.n_recordings >= 1
torch.testing.assert_close(out, reference_out, rtol=1e-6, atol=1e-7)
torch.testing.assert_close(grad, reference_grad, rtol=1e-5, atol=1e-7)
print("ok")
"""
    assert run_in_fresh_process(code).split()[-1] == "ok"


def test_each_view_samples_its_own_shutter_interval():
    """One wavefront over several views: a lane's ray time lies in *its* sensor's shutter
    interval (it took the first sensor's for every view)."""
    import drjit as dr
    import mitsuba as mi

    from torchir.functions.render_pixels import _pixel_rays, _seeded_sampler

    def sensor(open_, close):
        return mi.load_dict({"type": "perspective", "shutter_open": open_, "shutter_close": close,
                             "film": {"type": "hdrfilm", "width": 4, "height": 4}})

    sensors = [sensor(0.0, 0.0), sensor(2.0, 3.0), sensor(5.0, 5.0)]
    index = mi.UInt32(dr.arange(mi.UInt32, 3 * 16))
    ray, _ = _pixel_rays(sensors, index, _seeded_sampler(0, 3 * 16))
    t = torch.tensor(ray.time.numpy()).view(3, 16)  # host: a Dr.Jit array
    assert bool((t[0] == 0).all()) and bool((t[2] == 5).all())
    assert bool(((t[1] >= 2) & (t[1] <= 3)).all()) and float(t[1].std()) > 0.1
