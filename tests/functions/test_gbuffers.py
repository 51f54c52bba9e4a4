"""G-buffers through Mitsuba's aov integrator, and denoisers inside a real render (spec §6.2)."""
from __future__ import annotations

import pytest
import torch

from torchir.functions import render, render_gbuffers
from torchir.modules import CrossBilateralDenoiser, TargetAwareDenoiser, l1_loss

KEY = "canvas.bsdf.reflectance.data"


def test_gbuffer_channels(painting):
    """(7,H,W): albedo follows the bound texture linearly, unit normals facing the camera, depth > 0."""
    tex = painting.get(KEY)
    g = render_gbuffers(painting, {KEY: 0.5 * tex}, spp=2, seed=3)
    assert g.shape == (7, *painting.resolution) and g.dtype == torch.float32 and not g.requires_grad
    g2 = render_gbuffers(painting, {KEY: 0.25 * tex}, spp=2, seed=3)  # same samples, half the albedo
    assert torch.allclose(g2[:3], 0.5 * g[:3], rtol=1e-5, atol=1e-7)
    assert torch.equal(g2[3:], g[3:])
    assert torch.allclose(g[3:6].norm(dim=0), torch.ones(painting.resolution), atol=1e-4)
    assert (g[5] > 0.99).all()  # the canvas faces the camera (+z)
    assert (g[6] > 0).all()
    assert g[:3].amax() <= tex.amax() * 0.5 + 1e-6  # box-filtered albedo stays within the texture's range


def test_gbuffer_input_errors(painting):
    with pytest.raises(ValueError, match="spp"):
        render_gbuffers(painting, spp=0)
    with pytest.raises(KeyError, match="unknown scene parameter"):
        render_gbuffers(painting, {"nope": torch.zeros(3)})
    with pytest.raises(IndexError):
        render_gbuffers(painting, sensor=3)


def test_a_sensor_object_selects_its_view(tmp_path):
    """``sensor=`` takes one of the scene's ``mi.Sensor`` objects, as ``render`` does (Mitsuba's
    tutorials pass sensors): the G-buffers of sensor object k are those of index k, and a sensor
    the scene was not loaded with is refused."""
    import mitsuba as mi

    import torchir
    from torchir import rigs

    sensors = rigs.orbit(count=2, distance=4.0, elevation=20.0, fov=40.0, resolution=8, filter="box")
    scene = torchir.Scene.from_dict({"type": "scene", "ball": {"type": "sphere"}}, sensors=sensors)
    own = scene.mi_scene.sensors()
    for k in range(2):
        assert torch.equal(render_gbuffers(scene, sensor=own[k], spp=1), render_gbuffers(scene, sensor=k, spp=1))
    assert not torch.equal(render_gbuffers(scene, sensor=own[0], spp=1), render_gbuffers(scene, sensor=own[1], spp=1))
    stranger = mi.load_dict(sensors[0])
    with pytest.raises(ValueError, match="not one of the scene's"):
        render_gbuffers(scene, sensor=stranger, spp=1)


def test_denoised_render_backward_with_gbuffers(painting):
    """I1/I2: render -> denoisers -> L1 -> backward, with G-buffers rendered before the
    differentiable render or between it and its backward (the §5.5 pitfall): the gradient is
    finite, non-zero, and the same either way (the G-buffer render did not disturb the replay)."""
    tex = painting.get(KEY)
    target = render(painting, {KEY: tex}, spp=16, seed=100)
    den, cbf = TargetAwareDenoiser(radius=3), CrossBilateralDenoiser(radius=2)

    def step(when: str) -> torch.Tensor:
        x = torch.full_like(tex, 0.5).requires_grad_()
        if when == "before":
            guide = render_gbuffers(painting, {KEY: 0.9 * x.detach()})
        img = render(painting, {KEY: x}, spp=4, seed=7)
        if when == "between":
            guide = render_gbuffers(painting, {KEY: 0.9 * x.detach()})
        l1_loss(den(cbf(img, target, guide), target), target).backward()
        return x.grad

    before, between = step("before"), step("between")
    assert torch.isfinite(before).all() and before.abs().sum() > 0
    # equal to float32 summation order (Dr.Jit accumulates gradients with parallel atomics:
    # measured 2e-8 of the largest entry in 1 of 4 runs); a disturbed replay is off by 50-100%
    torch.testing.assert_close(between, before, rtol=0, atol=1e-5 * float(before.abs().max()))


def test_denoised_adjoint_variance_and_bias(painting):
    """I3 (cheap Fig. 9): over 64 seeds at 4 spp, the image-space L1 adjoint dL^/df~ through the
    target-aware denoiser has lower per-pixel variance than the raw sign(f~ - I) on >= 90 % of
    the pixels, and its seed mean is closer to the adjoint of 4096-spp renders."""
    tex = painting.get(KEY)
    x = torch.full_like(tex, 0.5)
    with torch.no_grad():
        target = render(painting, {KEY: tex}, spp=4096, seed=10**6)[None]
        reference = torch.sign(render(painting, {KEY: x}, spp=4096, seed=10**6 + 1)[None] - target)[0]
    den = TargetAwareDenoiser(radius=3)
    raw, denoised = [], []
    for seed in range(64):
        img = render(painting, {KEY: x}, spp=4, seed=seed)[None].requires_grad_()
        (grad,) = torch.autograd.grad((den(img, target) - target).abs().sum(), img)
        denoised.append(grad[0])
        raw.append(torch.sign(img.detach() - target)[0])
    raw, denoised = torch.stack(raw), torch.stack(denoised)
    assert (denoised.var(0) < raw.var(0)).float().mean() >= 0.9
    assert (denoised.mean(0) - reference).square().mean() < (raw.mean(0) - reference).square().mean()
