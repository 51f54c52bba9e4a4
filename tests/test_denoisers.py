"""Denoisers of paper 002: target-aware (ours) and the G-buffer baselines (spec §6.1)."""
from __future__ import annotations

import warnings

import kornia
import pytest
import torch
import torch.nn.functional as F

from torchir.modules import (
    DENOISERS,
    CrossBilateralDenoiser,
    GBufferRegressionDenoiser,
    TargetAwareDenoiser,
    cross_bilateral_denoise,
    gbuffer_regression_denoise,
    target_aware_denoise,
)
from torchir.modules.target_aware import target_aware_denoise_reference

D = torch.float64


def rand(*shape, seed=0, dtype=D):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=dtype)


def neighbours(x: torch.Tensor, r: int) -> torch.Tensor:
    """``(B, C, K*K, H, W)``: x at c + delta, zero outside the image (row-major offsets)."""
    B, C, H, W = x.shape
    K = 2 * r + 1
    return F.unfold(x, K, padding=r).view(B, C, K * K, H, W)


# --------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("weight_mode", ["rgb", "per_channel"])
@pytest.mark.parametrize("order", [0, 1])
@pytest.mark.parametrize("radius", [2, 3])
def test_equals_bruteforce_lstsq(weight_mode, order, radius):
    """U1: the tap implementation equals a per-pixel weighted lstsq of Eq. 10 (9x11, batch 2)."""
    target, noisy = rand(2, 3, 9, 11, seed=1), rand(2, 3, 9, 11, seed=2)
    kw = dict(radius=radius, order=order, weight_mode=weight_mode, clamp_min=None)
    out = target_aware_denoise(noisy, target, var_floor=1e-12, **kw)
    ref = target_aware_denoise_reference(noisy, target, **kw)
    assert (out - ref).abs().max() < 1e-8


def test_affine_in_target_reproduced():
    """U3: noisy = p + q * target (per channel) is reproduced exactly, incl. noisy = target."""
    target = rand(1, 3, 12, 10, seed=3)
    p = torch.tensor([0.1, -0.2, 0.3], dtype=D).view(1, 3, 1, 1)
    q = torch.tensor([2.0, 0.5, -1.0], dtype=D).view(1, 3, 1, 1)
    for noisy in (p + q * target, target):
        out = target_aware_denoise(noisy, target, radius=3, clamp_min=None, var_floor=1e-12)
        assert (out - noisy).abs().max() < 1e-8


@pytest.mark.parametrize("kind", ["random", "constant", "black"])
def test_constant_preserved(kind):
    """U4: a constant noisy image stays constant for any target (rows of L sum to 1)."""
    target = {"random": rand(1, 3, 8, 9, seed=4), "constant": torch.full((1, 3, 8, 9), 0.4, dtype=D),
              "black": torch.zeros(1, 3, 8, 9, dtype=D)}[kind]
    noisy = torch.full((1, 3, 8, 9), 0.7, dtype=D)
    out = target_aware_denoise(noisy, target, radius=3, clamp_min=None)
    assert (out - 0.7).abs().max() < 1e-12


@pytest.mark.parametrize("weight_mode", ["rgb", "per_channel"])
def test_smoother_identities_and_bias_formula(weight_mode):
    """U5, U6: sum l = 1, sum l (I_i - I_c) = 0, and the exact bias of a quadratic (Eq. 16)."""
    r = 2
    target = rand(1, 3, 8, 10, seed=5)
    l = TargetAwareDenoiser(radius=r, weight_mode=weight_mode, var_floor=1e-12).smoother_weights(target)
    I_nb = neighbours(target, r)
    x = I_nb - target.unsqueeze(2)
    assert (l.sum(2) - 1).abs().max() < 1e-9
    assert (l * x).sum(2).abs().max() < 1e-9
    f = lambda I: 0.3 + 0.5 * I + 0.2 * I.square()
    bias = (l * neighbours(f(target), r)).sum(2) - f(target)
    assert (bias - 0.2 * (l * x.square()).sum(2)).abs().max() < 1e-9


def test_zeroth_order_equals_kornia_joint_bilateral():
    """U10: order 0 == kornia's joint bilateral blur on log(1+I) without spatial term (interior)."""
    r = 2
    target, noisy = rand(1, 3, 12, 12, seed=6), rand(1, 3, 12, 12, seed=7)
    ours = target_aware_denoise(noisy, target, radius=r, order=0, clamp_min=None)
    ref = kornia.filters.joint_bilateral_blur(noisy, torch.log1p(target), 2 * r + 1, 0.1, (1e6, 1e6),
                                              color_distance_type="l2")
    assert (ours - ref)[..., r:-r, r:-r].abs().max() < 1e-10


# ---------------------------------------------------------------------------- gradients
def test_gradcheck_and_gradgradcheck_clamp_off():
    """U7: the custom Function's backward (transposed taps) and double backward, float64."""
    target = rand(1, 3, 6, 7, seed=8)
    noisy = rand(1, 3, 6, 7, seed=9).requires_grad_()
    f = lambda y: target_aware_denoise(y, target, radius=2, clamp_min=None)
    assert torch.autograd.gradcheck(f, (noisy,))
    assert torch.autograd.gradgradcheck(f, (noisy,))


@pytest.mark.parametrize("impl", ["auto", "taps"])
def test_gradcheck_clamp_on(impl):
    """U7 with the output clamp, inputs away from 0 (clamp inactive but in the graph)."""
    target = rand(1, 3, 5, 6, seed=10) + 0.5
    noisy = (rand(1, 3, 5, 6, seed=11) + 0.5).requires_grad_()
    f = lambda y: target_aware_denoise(y, target, radius=2, impl=impl)
    assert torch.autograd.gradcheck(f, (noisy,))
    assert torch.autograd.gradgradcheck(f, (noisy,))


def test_backward_is_transpose():
    """U8: <L y, g> == <y, L^T g>, and the backward equals the explicit matrix transpose."""
    r = 2
    target, y, g = rand(1, 3, 7, 8, seed=12), rand(1, 3, 7, 8, seed=13), rand(1, 3, 7, 8, seed=14)
    y = y.requires_grad_()
    out = target_aware_denoise(y, target, radius=r, clamp_min=None)
    (grad,) = torch.autograd.grad(out, y, g)
    assert abs(float(((out * g).sum() - (y * grad).sum()).detach())) < 1e-12
    l = TargetAwareDenoiser(radius=r).smoother_weights(target)  # l_{c+delta|c}
    # L^T g at i = sum_c l_{i|c} g_c: scatter each tap by hand with F.fold (the adjoint of unfold).
    explicit = F.fold((l * g.unsqueeze(2)).view(1, -1, 7 * 8), (7, 8), 2 * r + 1, padding=r)
    assert (explicit - grad).abs().max() < 1e-12


def test_no_gradient_to_target_and_warning():
    """U17: a target that requires grad: warning, no gradient reaches it."""
    target = rand(1, 3, 6, 6, seed=15).requires_grad_()
    noisy = rand(1, 3, 6, 6, seed=16).requires_grad_()
    with pytest.warns(UserWarning, match="target requires grad"):
        out = target_aware_denoise(noisy, target, radius=1)
    out.sum().backward()
    assert target.grad is None and noisy.grad is not None


# ---------------------------------------------------------------------- module and cache
def test_module_equals_functional_and_cache_paths():
    """Module == function; tap table == taps on the fly (U9); float32 close to float64."""
    target, noisy = rand(2, 3, 10, 9, seed=17), rand(2, 3, 10, 9, seed=18)
    kw = dict(radius=3, bandwidth=0.2, order=1, clamp_min=0.0)
    fun = target_aware_denoise(noisy, target, **kw)
    cached = TargetAwareDenoiser(**kw, impl="cached")(noisy, target)
    on_the_fly = TargetAwareDenoiser(**kw, impl="taps")(noisy, target)
    assert torch.equal(fun, cached)
    assert (cached - on_the_fly).abs().max() < 1e-12
    single = TargetAwareDenoiser(**kw)(noisy.float(), target.float())
    assert single.dtype == torch.float32 and (single.double() - fun).abs().max() < 1e-5
    assert "radius=3" in repr(TargetAwareDenoiser(**kw)) and not list(TargetAwareDenoiser().parameters())


def test_batch_equals_single_calls_and_views_cache():
    """U16: a batch of views (each with its own target) == one call per view; cache reuse."""
    target, noisy = rand(2, 3, 8, 8, seed=19), rand(2, 3, 8, 8, seed=20)
    den = TargetAwareDenoiser(radius=2)
    both = den(noisy, target, views=[0, 1])
    for i in range(2):
        assert torch.equal(both[i], den(noisy[i], target[i], views=[i]))
    assert len(den._cache) == 3
    taps = den._cache[((0, 1), (2, 3, 8, 8), D, noisy.device)][2]
    den(noisy, target, views=[0, 1])
    assert den._cache[((0, 1), (2, 3, 8, 8), D, noisy.device)][2] is taps  # reused


def test_target_mutated_in_place_rebuilds():
    """U16: an in-place edit of the target invalidates the cached taps."""
    target, noisy = rand(1, 3, 8, 8, seed=21), rand(1, 3, 8, 8, seed=22)
    den = TargetAwareDenoiser(radius=2)
    den(noisy, target)
    target.mul_(0.5).add_(rand(1, 3, 8, 8, seed=23))
    assert torch.equal(den(noisy, target), target_aware_denoise(noisy, target, radius=2))


def test_memory_budget():
    """impl='cached' over budget: clear error; 'auto' falls back to taps on the fly, same result."""
    target, noisy = rand(1, 3, 8, 8, seed=24), rand(1, 3, 8, 8, seed=25)
    with pytest.raises(ValueError, match="max_cache_bytes"):
        target_aware_denoise(noisy, target, radius=3, impl="cached", max_cache_bytes=1000)
    low = TargetAwareDenoiser(radius=3, max_cache_bytes=1000)
    out = low(noisy, target)
    assert low._cache_bytes() == 0
    assert (out - target_aware_denoise(noisy, target, radius=3)).abs().max() < 1e-12


def test_enabled_switch_and_mask():
    """enabled=False is the identity; masked-out pixels pass through and are no one's neighbour."""
    target, noisy = rand(1, 3, 8, 8, seed=26), rand(1, 3, 8, 8, seed=27)
    assert TargetAwareDenoiser(radius=2, enabled=False)(noisy, target) is noisy
    mask = torch.ones(8, 8, dtype=torch.bool)
    mask[2:5, 3:6] = False
    out = target_aware_denoise(noisy, target, radius=2, mask=mask, clamp_min=None)
    assert torch.equal(out[..., ~mask], noisy[..., ~mask])
    changed = noisy.clone()
    changed[..., ~mask] = 1e3  # excluded pixels must not influence the others
    out2 = target_aware_denoise(changed, target, radius=2, mask=mask, clamp_min=None)
    assert (out2 - out)[..., mask].abs().max() < 1e-12


def test_propagated_variance():
    """E16: Var[f^_c] = sum_i l_{i|c}^2 sigma_i^2; with sigma = 1 it is at most 1 (centre weight)."""
    r = 2
    target, var = rand(1, 3, 7, 8, seed=44), rand(1, 3, 7, 8, seed=45)
    den = TargetAwareDenoiser(radius=r)
    l = den.smoother_weights(target)
    expected = (l.square() * neighbours(var, r)).sum(2)
    assert (den.propagated_variance(var, target) - expected).abs().max() < 1e-12
    flat = den.propagated_variance(torch.ones_like(var), torch.full_like(target, 0.5))
    assert (flat - 1 / neighbours(torch.ones(1, 1, 7, 8, dtype=D), r).sum(2)).abs().max() < 1e-12  # 1/N


def test_taps_path_memory_is_bounded():
    """U18: impl='taps' never materialises the (2r+1)^2 x C x H x W table (87 MB here in float32):
    the peak resident memory of a forward+backward at 128^2, r = 10 grows by less than 20 MB."""
    import os

    if not os.path.exists("/proc/self/clear_refs"):
        pytest.skip("needs Linux /proc to reset the peak RSS")

    def rss(field: str) -> int:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith(field))

    target = rand(1, 3, 128, 128, seed=46, dtype=torch.float32)
    noisy = rand(1, 3, 128, 128, seed=47, dtype=torch.float32).requires_grad_()
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset VmHWM (peak RSS) to the current RSS
    base = rss("VmRSS:")
    target_aware_denoise(noisy, target, radius=10, impl="taps").sum().backward()
    assert rss("VmHWM:") - base < 20 * 2**20


# -------------------------------------------------------------------------- extremes
def test_constant_and_black_targets():
    """U11: a flat target gives the (truncated) window mean; black in, black out; finite."""
    r = 2
    noisy = rand(1, 3, 7, 9, seed=28)
    ones = torch.ones(1, 1, 7, 9, dtype=D)
    box = lambda x: neighbours(x, r).sum(2)
    out = target_aware_denoise(noisy, torch.full_like(noisy, 0.3), radius=r, clamp_min=None)
    assert (out - box(noisy) / box(ones)).abs().max() < 1e-12
    zeros = torch.zeros_like(noisy)
    assert torch.equal(target_aware_denoise(zeros, zeros, radius=r), zeros)


def test_firefly_stays_local():
    """U12: a 1e6 firefly changes only its window: by exactly l_{p|c} (1e6 - old)."""
    r, H, W, p = 2, 12, 12, (5, 6)
    target, noisy = rand(1, 3, H, W, seed=29), rand(1, 3, H, W, seed=30)
    fire = noisy.clone()
    fire[..., p[0], p[1]] = 1e6
    kw = dict(radius=r, clamp_min=None)
    diff = target_aware_denoise(fire, target, **kw) - target_aware_denoise(noisy, target, **kw)
    assert torch.isfinite(diff).all()
    window = torch.zeros(H, W, dtype=torch.bool)
    window[p[0] - r : p[0] + r + 1, p[1] - r : p[1] + r + 1] = True
    assert torch.equal(diff[..., ~window], torch.zeros_like(diff[..., ~window]))
    l = TargetAwareDenoiser(**kw).smoother_weights(target)
    for cy in range(p[0] - r, p[0] + r + 1):
        for cx in range(p[1] - r, p[1] + r + 1):
            k = (p[0] - cy + r) * (2 * r + 1) + (p[1] - cx + r)
            expected = l[0, :, k, cy, cx] * (1e6 - noisy[0, :, p[0], p[1]])
            assert torch.allclose(diff[0, :, cy, cx], expected, rtol=1e-9, atol=1e-6)


def test_hdr_target_with_emitters():
    """HDR targets (emitters of 1e4, float32): no overflow; emitter and non-emitter pixels do not
    mix (their log-space weight underflows to 0), so the emitter centre is the mean of the emitter's
    noisy values and the rest equals a run with the emitter masked out."""
    target = rand(1, 3, 16, 16, seed=31, dtype=torch.float32)
    emitter = torch.zeros(16, 16, dtype=torch.bool)
    emitter[4:7, 4:7] = True
    target[..., emitter] = 1e4
    noisy = target * (1 + 0.1 * torch.randn(1, 3, 16, 16, generator=torch.Generator().manual_seed(0)))
    out = target_aware_denoise(noisy, target, radius=3, clamp_min=None)
    assert torch.isfinite(out).all()
    mean = noisy[..., emitter].mean(-1)
    assert ((out[..., 5, 5] - mean).abs() / mean).max() < 1e-5
    rest = target_aware_denoise(noisy, target, radius=3, clamp_min=None, mask=~emitter)
    assert (out - rest)[..., ~emitter].abs().max() < 1e-5


@pytest.mark.parametrize("shape", [(1, 3, 1, 1), (1, 1, 5, 2), (2, 4, 3, 7), (3, 6, 4)])
def test_tiny_and_odd_shapes(shape):
    """U15: H, W < window (the window is truncated to the image), 1x1, C = 1 and 4, (C,H,W) layout:
    equal to the per-pixel lstsq reference (a 1x1 image is its own fit), constants are fixed points
    (rows of L sum to 1), and r = 0 is the identity."""
    noisy, target = rand(*shape, seed=32), rand(*shape, seed=33)
    out = target_aware_denoise(noisy, target, radius=3, var_floor=1e-12)
    assert out.shape == noisy.shape
    assert (out - target_aware_denoise_reference(noisy, target, radius=3)).abs().max() < 1e-8
    if shape[-2:] == (1, 1):
        assert (out - noisy).abs().max() < 1e-15
    const = torch.full_like(noisy, 0.6)
    assert (target_aware_denoise(const, target, radius=3) - 0.6).abs().max() < 1e-12
    assert torch.equal(target_aware_denoise(noisy, target, radius=0, clamp_min=None), noisy)


def test_bad_input():
    """U13, U14 and shape/device/option errors: clear messages."""
    target, noisy = rand(1, 3, 6, 6, seed=34), rand(1, 3, 6, 6, seed=35)
    bad = noisy.clone()
    bad[0, 0, 0, :2] = float("nan")
    with pytest.raises(ValueError, match="noisy has 2 NaN/Inf"):
        target_aware_denoise(bad, target, radius=1)
    assert torch.isnan(target_aware_denoise(bad, target, radius=1, check_finite=False, clamp_min=None)).any()
    bad_t = target.clone()
    bad_t[0, 1, 2, 2] = float("inf")
    with pytest.raises(ValueError, match="target has 1 NaN/Inf"):
        target_aware_denoise(noisy, bad_t, radius=1)
    with pytest.warns(UserWarning, match="negative"):
        target_aware_denoise(noisy, target - 0.5, radius=1)
    with pytest.raises(ValueError, match="<= -1"):
        target_aware_denoise(noisy, target - 2.0, radius=1)
    with pytest.raises(ValueError, match="differ"):
        target_aware_denoise(noisy, target[..., :5], radius=1)
    with pytest.raises(ValueError, match="expected"):
        target_aware_denoise(noisy[0, 0], target[0, 0], radius=1)
    with pytest.raises(ValueError, match="is on"):
        target_aware_denoise(noisy, target.to("meta"), radius=1)
    with pytest.raises(TypeError, match="float32 or float64"):
        target_aware_denoise(noisy.half(), target, radius=1)
    with pytest.raises(ValueError, match="views"):
        TargetAwareDenoiser(radius=1)(noisy, target, views=[0, 1])


@pytest.mark.parametrize("kw, match", [
    (dict(radius=-1), "radius must be an int >= 0, got -1"),
    (dict(bandwidth=0.0), "bandwidth must be a finite number > 0, got 0.0"),
    (dict(order=2), "order must be 0 or 1 .*got 2"),
    (dict(impl="fast"), "impl must be one of .*got 'fast'"),
    (dict(weight_mode="lab"), "weight_mode must be one of .*got 'lab'"),
    (dict(var_floor=0.0), "var_floor must be > 0, got 0.0"),
    (dict(clamp_min=float("inf")), "clamp_min must be finite or None, got inf"),
])
def test_bad_option(kw, match):
    """Each bad option is rejected with its own message, by the function and the module alike."""
    target, noisy = rand(1, 3, 6, 6, seed=34), rand(1, 3, 6, 6, seed=35)
    with pytest.raises(ValueError, match=match):
        target_aware_denoise(noisy, target, **kw)
    with pytest.raises(ValueError, match=match):
        TargetAwareDenoiser(**kw)


# ------------------------------------------------------------------- G-buffer baselines
def gbuffers(B, H, W, seed):
    g = rand(B, 7, H, W, seed=seed)
    g[:, 3:6] = F.normalize(g[:, 3:6] - 0.5, dim=1)
    g[:, 6] = 1 + g[:, 6]
    return g


def test_cross_bilateral_equals_kornia():
    """U10: CBF (Eqs. 5-6) == kornia joint_bilateral_blur on the scaled G-buffers (interior)."""
    r, H, W = 2, 11, 12
    noisy, guide = rand(1, 3, H, W, seed=36), gbuffers(1, H, W, 37)
    ours = cross_bilateral_denoise(noisy, guide, radius=r)
    depth = guide[:, 6:7] / guide[:, 6:7].amax()
    feats = torch.cat([guide[:, :3] / 0.05, guide[:, 3:6] / 0.1, depth / 0.1], 1)
    ref = kornia.filters.joint_bilateral_blur(noisy, feats, 2 * r + 1, 1.0, (r / 3, r / 3), color_distance_type="l2")
    assert (ours - ref)[..., r:-r, r:-r].abs().max() < 1e-10
    assert (cross_bilateral_denoise(noisy, guide, radius=r, impl="taps") - ours).abs().max() < 1e-12


@pytest.mark.parametrize("cls", [CrossBilateralDenoiser, GBufferRegressionDenoiser])
def test_gbuffer_denoisers_gradcheck_and_module(cls):
    r = 1
    noisy = (rand(1, 3, 4, 5, seed=40) + 0.5).requires_grad_()
    guide = gbuffers(1, 4, 5, 41)
    den = cls(radius=r)
    assert cls.needs_guide and not list(den.parameters())
    f = lambda y: den(y, None, guide)
    assert torch.autograd.gradcheck(f, (noisy,)) and torch.autograd.gradgradcheck(f, (noisy,))
    fun = cross_bilateral_denoise if cls is CrossBilateralDenoiser else gbuffer_regression_denoise
    assert torch.equal(den(noisy, None, guide), fun(noisy, guide, radius=r))
    assert cls(radius=r, enabled=False)(noisy, None, guide) is noisy
    with pytest.raises(ValueError, match="needs guide"):
        den(noisy, noisy)
    with pytest.raises(ValueError, match="guide: expected"):
        den(noisy, None, guide[:, :6])


def test_cross_bilateral_constant_and_firefly():
    """CBF rows sum to 1 (constants kept); a firefly spreads only within its window."""
    r, H, W = 2, 10, 10
    guide = gbuffers(1, H, W, 42)
    const = torch.full((1, 3, H, W), 0.25, dtype=D)
    assert (cross_bilateral_denoise(const, guide, radius=r) - 0.25).abs().max() < 1e-12
    noisy = rand(1, 3, H, W, seed=43)
    fire = noisy.clone()
    fire[..., 0, 0] = 1e6
    diff = cross_bilateral_denoise(fire, guide, radius=r) - cross_bilateral_denoise(noisy, guide, radius=r)
    assert torch.isfinite(diff).all() and torch.equal(diff[..., r + 1 :, :], torch.zeros_like(diff[..., r + 1 :, :]))


def test_registry():
    assert DENOISERS["target_aware"] is TargetAwareDenoiser and not TargetAwareDenoiser.needs_guide
    assert DENOISERS["cross_bilateral"] is CrossBilateralDenoiser
    assert DENOISERS["gbuffer_regression"] is GBufferRegressionDenoiser
    assert DENOISERS["target_aware"](radius=7).radius == 7
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        TargetAwareDenoiser(radius=1)(rand(1, 3, 4, 4), rand(1, 3, 4, 4))
