"""Denoisers of paper 002: target-aware (ours) and the G-buffer baselines (spec §6.1)."""
from __future__ import annotations

import os
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

from tests.helpers import DEVICE, assert_warned_at

D = torch.float64


def rand(*shape, seed=0, dtype=D):
    g = torch.Generator(device=DEVICE).manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=dtype)


def neighbours(x: torch.Tensor, r: int) -> torch.Tensor:
    """``(B, C, K*K, H, W)``: x at c + delta, zero outside the image (row-major offsets)."""
    B, C, H, W = x.shape
    K = 2 * r + 1
    return F.unfold(x, K, padding=r).view(B, C, K * K, H, W)


def _assert_warned_here(record) -> None:
    assert_warned_at(record, __file__)


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
    noisy = target * (1 + 0.1 * torch.randn(1, 3, 16, 16, generator=torch.Generator(device=DEVICE).manual_seed(0)))
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


# ------------------------------------------- G-buffer baselines against a per-pixel reference
def _src(k: int, n: int, border: str) -> int | None:
    """Pixel read at position k of an axis of n pixels: None outside ("truncate"), else mirrored
    about the edge pixels without repeating them (numpy "reflect")."""
    if border == "truncate":
        return k if 0 <= k < n else None
    if n == 1:
        return 0
    while not 0 <= k < n:
        k = -k if k < 0 else 2 * (n - 1) - k
    return k


def gbuffer_reference(noisy, guide, radius, sigma_space, bands, border, regression):
    """Eqs. 5-6 (and the weighted local linear fit) pixel by pixel: albedo clamped to [0, 1],
    depth / the image's max depth, weights exp(-|df / band|^2 / 2 - |dpos|^2 / (2 b_q^2)) with the
    read pixel's own position, rows [1, dg, dpos / max(r, 1)], ridge 1e-3; no output clamp."""
    B, C, H, W = noisy.shape
    g = guide.double().expand(B, -1, -1, -1).clone()
    g[:, :3] = g[:, :3].clamp(0, 1)
    g[:, 6] = g[:, 6] / g[:, 6].amax(dim=(1, 2)).view(B, 1, 1)
    band = torch.tensor([bands[0]] * 3 + [bands[1]] * 3 + [bands[2]], dtype=D)
    b_q = max(radius, 1) / 3 if sigma_space is None else sigma_space
    out = torch.empty_like(noisy)
    for n in range(B):
        for i in range(H):
            for j in range(W):
                ws, xs, ys = [], [], []
                for di in range(-radius, radius + 1):
                    for dj in range(-radius, radius + 1):
                        si, sj = _src(i + di, H, border), _src(j + dj, W, border)
                        if si is None or sj is None:
                            continue
                        dg = g[n, :, si, sj] - g[n, :, i, j]
                        dpos = torch.tensor([si - i, sj - j], dtype=D)
                        ws.append(torch.exp(-0.5 * (dg / band).square().sum() - dpos.square().sum() / (2 * b_q**2)))
                        xs.append(torch.cat([torch.ones(1, dtype=D), dg, dpos / max(radius, 1)]))
                        ys.append(noisy[n, :, si, sj])
                w, X, Y = torch.stack(ws)[:, None], torch.stack(xs), torch.stack(ys)
                if regression:
                    M = X.T @ (w * X) + 1e-3 * torch.eye(X.shape[1], dtype=D)
                    out[n, :, i, j] = torch.linalg.solve(M, X.T @ (w * Y))[0]
                else:
                    out[n, :, i, j] = (w * Y).sum(0) / w.sum()
    return out


def soft_gbuffers(B, H, W, seed):
    """G-buffers whose differences are O(1) band widths (weights far from 0 and 1): albedo partly
    outside [0, 1] (clamped), unnormalised normals, a depth per image whose max is < 1 or > 1."""
    g = rand(B, 7, H, W, seed=seed)
    g[:, :3] = 1.4 * g[:, :3] - 0.2
    g[:, 3:6] = 2 * g[:, 3:6] - 1
    g[:, 6] = 0.3 + 0.6 * g[:, 6] * torch.arange(1, B + 1, dtype=D).view(B, 1, 1) ** 2
    return g


@pytest.mark.parametrize("regression", [False, True])
@pytest.mark.parametrize("border", ["truncate", "reflect"])
def test_gbuffer_denoisers_equal_the_per_pixel_reference(border, regression):
    """Both baselines, both borders, table and on-the-fly taps, a per-item guide or one shared
    guide, the default spatial bandwidth (r / 3) and an explicit one, r = 1 and 2."""
    fn = gbuffer_regression_denoise if regression else cross_bilateral_denoise
    noisy = rand(2, 2, 5, 6, seed=50) - 0.3
    bands = (0.6, 1.0, 0.5)
    kw = dict(sigma_albedo=bands[0], sigma_normal=bands[1], sigma_depth=bands[2], border=border)
    if regression:
        kw["clamp_min"] = None
    for guide, radius, sigma_space in [(soft_gbuffers(2, 5, 6, 51), 2, 1.3), (soft_gbuffers(1, 5, 6, 52), 1, None)]:
        ref = gbuffer_reference(noisy, guide, radius, sigma_space, bands, border, regression)
        for impl in ("auto", "taps"):
            out = fn(noisy, guide, radius=radius, sigma_space=sigma_space, impl=impl, **kw)
            assert (out - ref).abs().max() < 1e-9, (radius, impl)


@pytest.mark.parametrize("cls", [CrossBilateralDenoiser, GBufferRegressionDenoiser])
def test_gbuffer_defaults_options_and_module_twins(cls):
    """The module's defaults are the function's (radius 15, b_q = r / 3, check_finite on, clamp
    at 0 for the regression), every option reaches the function, float32 noisy stays float32
    (computed like float64) and the torch thread count is restored."""
    import inspect

    fn = cross_bilateral_denoise if cls is CrossBilateralDenoiser else gbuffer_regression_denoise
    defaults = {k: p.default for k, p in inspect.signature(fn).parameters.items() if p.default is not inspect.Parameter.empty}
    assert defaults["radius"] == 15 and defaults["check_finite"] is True and cls()._options() == defaults
    noisy, guide = rand(1, 3, 4, 5, seed=53) - 0.5, soft_gbuffers(1, 4, 5, 54)
    flat = guide[..., :1, :1].expand(1, 7, 4, 5)  # only the spatial term (b_q = 15 / 3) weighs
    ref = gbuffer_reference(noisy, flat, 15, None, (0.05, 0.1, 0.1), "truncate", cls is GBufferRegressionDenoiser)
    clamp = 0.0 if cls is GBufferRegressionDenoiser else None
    expected = ref if clamp is None else ref.clamp_min(clamp)
    assert (fn(noisy, flat) - expected).abs().max() < 1e-9
    assert (cls()(noisy, None, flat) - expected).abs().max() < 1e-9
    options = dict(radius=1, sigma_space=0.8, sigma_albedo=0.5, sigma_normal=0.7, sigma_depth=0.9, border="reflect", impl="taps")
    if cls is GBufferRegressionDenoiser:
        options["clamp_min"] = None
    den = cls(**options)
    assert torch.equal(den(noisy, None, guide), fn(noisy, guide, **options))
    assert (den(noisy, None, guide) - gbuffer_reference(noisy, guide, 1, 0.8, (0.5, 0.7, 0.9), "reflect", cls is GBufferRegressionDenoiser)).abs().max() < 1e-9
    assert repr(den) == f"{cls.__name__}(" + ", ".join(f"{k}={v!r}" for k, v in den._options().items()) + ", enabled=True)"
    if cls is GBufferRegressionDenoiser:
        assert (fn(noisy, guide, radius=1) >= 0).all() and (fn(noisy, guide, radius=1, clamp_min=None) < 0).any()
        torch.testing.assert_close(cls(radius=1)(noisy, None, guide), fn(noisy, guide, radius=1).clamp_min(0), rtol=0, atol=0)
    bad = noisy.clone()
    bad[0, 0, 1, 1] = float("nan")
    for call in (lambda: fn(bad, guide, radius=1), lambda: cls(radius=1)(bad, None, guide)):
        with pytest.raises(ValueError, match=r"^noisy has 1 NaN/Inf value\(s\)"):
            call()
    no_clamp = {} if cls is CrossBilateralDenoiser else dict(clamp_min=None)  # the clamp maps NaN to 0
    assert torch.isnan(cls(radius=1, check_finite=False, **no_clamp)(bad, None, guide)).any()
    assert torch.isnan(fn(bad, guide, radius=1, check_finite=False, **no_clamp)).any()
    with pytest.raises(ValueError, match=f"^{fn.__name__}: impl='cached' needs"):
        cls(radius=1, impl="cached", max_cache_bytes=100)(noisy, None, guide)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        out32 = fn(noisy.float(), guide.float(), radius=1)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert out32.dtype == torch.float32 and (out32.double() - fn(noisy, guide, radius=1)).abs().max() < 1e-5
    torch.testing.assert_close(fn(noisy, guide.float(), radius=1), fn(noisy, guide.float().double(), radius=1), rtol=1e-12, atol=1e-14)


def test_cross_bilateral_table_budget_is_exact():
    """impl='cached' fits exactly in K^2 B H W * itemsize bytes (one weight per tap and pixel,
    shared over channels); one byte less is refused with the function's name."""
    noisy, guide = rand(2, 3, 4, 5, seed=55), soft_gbuffers(2, 4, 5, 56)
    need = 5 * 5 * 2 * 4 * 5 * 8
    out = cross_bilateral_denoise(noisy, guide, radius=2, impl="cached", max_cache_bytes=need)
    assert (out - cross_bilateral_denoise(noisy, guide, radius=2, impl="taps")).abs().max() < 1e-12
    with pytest.raises(ValueError, match=r"^cross_bilateral_denoise: impl='cached' needs 0.00 GiB for the tap table \(5x5 window, 4x5 image\)"):
        cross_bilateral_denoise(noisy, guide, radius=2, impl="cached", max_cache_bytes=need - 1)


def test_gbuffer_bad_arguments():
    noisy, guide = rand(2, 3, 4, 5, seed=57), soft_gbuffers(1, 4, 5, 58)
    nan_guide = guide.clone()
    nan_guide[0, 6, 0, 0] = float("nan")
    cases = [
        (dict(guide=None), ValueError, r"^this denoiser needs guide=\(B,7,H,W\) G-buffers \(albedo, normal, depth\) from torchir.functions.render_gbuffers$"),
        (dict(guide=guide.tolist()), TypeError, "^guide must be a torch.Tensor, got list$"),
        (dict(guide=guide[0, 0]), ValueError, r"^guide: expected \(B,C,H,W\) or \(C,H,W\), got shape \(4, 5\)$"),
        (dict(guide=guide[..., :4]), ValueError, r"^guide: expected \(2 or 1, 7, 4, 5\), got \(1, 7, 4, 4\)$"),
        (dict(guide=guide.expand(3, -1, -1, -1)), ValueError, r"^guide: expected \(2 or 1, 7, 4, 5\), got \(3, 7, 4, 5\)$"),
        (dict(guide=guide.to("meta")), ValueError, "^guide is on meta but noisy is on cpu$"),
        (dict(guide=nan_guide), ValueError, r"^guide has 1 NaN/Inf value\(s\)$"),
        (dict(sigma_albedo=0.0), ValueError, "^sigma_albedo must be > 0, got 0.0$"),
        (dict(sigma_normal=-1.0), ValueError, "^sigma_normal must be > 0, got -1.0$"),
        (dict(sigma_depth=float("inf")), ValueError, "^sigma_depth must be > 0, got inf$"),
        (dict(sigma_space=0.0), ValueError, "^sigma_space must be > 0, got 0.0$"),
        (dict(border="zero"), ValueError, r"^border must be one of \('truncate', 'reflect'\), got 'zero'$"),
    ]
    for fn in (cross_bilateral_denoise, gbuffer_regression_denoise):
        for kw, error, match in cases:
            kw = dict(dict(guide=guide, radius=1), **kw)
            with pytest.raises(error, match=match):
                fn(noisy, **kw)
    with pytest.raises(ValueError, match=r"^border must be one of \('truncate', 'reflect'\), got 'zero'$"):
        GBufferRegressionDenoiser(border="zero")


@pytest.mark.parametrize("fn", [cross_bilateral_denoise, gbuffer_regression_denoise])
def test_gbuffer_impl_taps_never_builds_a_table(fn, monkeypatch):
    """impl='taps' applies taps computed on the fly (memory O(C H W), no (2r+1)^2 table);
    'auto' (within budget) and 'cached' apply a table."""
    import torchir.modules.cross_bilateral as cb

    seen = []
    apply = cb.apply_taps
    monkeypatch.setattr(cb, "apply_taps", lambda y, taps: seen.append(taps.table is not None) or apply(y, taps))
    noisy, guide = rand(1, 3, 4, 5, seed=59), soft_gbuffers(1, 4, 5, 60)
    outs = [fn(noisy, guide, radius=1, impl=impl) for impl in ("taps", "auto", "cached")]
    assert seen == [False, True, True]
    assert (outs[1] - outs[0]).abs().max() < 1e-12 and (outs[2] - outs[0]).abs().max() < 1e-12

def test_reflect_padding_is_numpys_and_unpad_is_its_adjoint():
    """``mirror_index`` is numpy's ``mode="reflect"`` (reflected again when r >= n, a single
    pixel repeated), and ``unpad_window`` is the exact adjoint of ``pad_window`` for both
    borders: ``<pad(x), y> == <x, unpad(y)>``, odd sizes and windows larger than the image."""
    import numpy as np

    from torchir.modules._windows import mirror_index, pad_window, unpad_window

    for n in range(1, 7):
        for r in range(8):
            assert mirror_index(n, r) == np.pad(np.arange(n), r, mode="reflect").tolist(), (n, r)
    for (H, W), r in [((3, 4), 1), ((5, 2), 3), ((1, 3), 2), ((4, 4), 0), ((2, 7), 5)]:
        x = rand(2, 3, H, W, seed=H * 10 + W)
        y = rand(2, 3, H + 2 * r, W + 2 * r, seed=r)
        for border in ("truncate", "reflect"):
            padded = pad_window(x, r, border)
            assert padded.shape == y.shape
            if border == "reflect":
                rows, cols = mirror_index(H, r), mirror_index(W, r)
                assert torch.equal(padded, x[..., rows, :][..., cols])
            else:
                outside = padded.clone()
                outside[..., r : r + H, r : r + W] = 0
                assert torch.equal(padded[..., r : r + H, r : r + W], x) and not outside.any()
            back = unpad_window(y, r, border)
            assert back.shape == x.shape
            assert abs(float((padded * y).sum() - (x * back).sum())) < 1e-12, (H, W, r, border)


@pytest.mark.parametrize("cls", [CrossBilateralDenoiser, GBufferRegressionDenoiser])
def test_gbuffer_reflect_backward_is_the_transpose(cls):
    """border="reflect": the backward is the exact transpose of the forward (gradcheck, float64),
    also when the window is larger than the image (pixels reflected twice)."""
    for (H, W), r in [((4, 5), 1), ((2, 3), 2)]:
        noisy = (rand(1, 2, H, W, seed=61) + 0.5).requires_grad_()
        guide = soft_gbuffers(1, H, W, 62)
        den = cls(radius=r, sigma_albedo=0.6, sigma_normal=1.0, sigma_depth=0.5, border="reflect")
        for impl in ("auto", "taps"):
            den.impl = impl
            assert torch.autograd.gradcheck(lambda y: den(y, None, guide), (noisy,))


# ------------------------------------------------------ target-aware: options, cache, checks
def test_target_aware_defaults_clamp_and_shapes():
    """Defaults: radius 15 (a 40-row image tells 15 from 16), clamp at 0 (function and module),
    check_finite on; the module's defaults are the function's. The brute-force reference keeps
    the (C, H, W) layout and weighs per channel with C = 4."""
    import inspect

    defaults = {k: p.default for k, p in inspect.signature(target_aware_denoise).parameters.items() if p.default is not inspect.Parameter.empty}
    den = TargetAwareDenoiser()
    for name in ("radius", "bandwidth", "order", "weight_mode", "var_floor", "clamp_min", "impl", "max_cache_bytes", "check_finite"):
        assert getattr(den, name) == defaults[name], name
    assert defaults["radius"] == 15 and defaults["check_finite"] is True and defaults["clamp_min"] == 0.0
    target, noisy = rand(1, 1, 40, 2, seed=70), rand(1, 1, 40, 2, seed=71) - 0.7
    ref = target_aware_denoise_reference(noisy, target, radius=15, clamp_min=None)
    assert (ref - target_aware_denoise_reference(noisy, target, radius=16, clamp_min=None)).abs().max() > 1e-6
    assert (target_aware_denoise(noisy, target, clamp_min=None, var_floor=1e-12) - ref).abs().max() < 1e-8
    assert (target_aware_denoise_reference(noisy, target, clamp_min=None) - ref).abs().max() < 1e-12
    assert (ref < 0).any()
    for out in (target_aware_denoise(noisy, target, radius=2), den(noisy, target), TargetAwareDenoiser(radius=2)(noisy, target)):
        assert (out >= 0).all()
    torch.testing.assert_close(TargetAwareDenoiser(radius=2)(noisy, target), target_aware_denoise(noisy, target, radius=2, clamp_min=None).clamp_min(0), rtol=0, atol=0)
    bad = noisy.clone()
    bad[0, 0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"^noisy has 1 NaN/Inf value\(s\)"):
        den(bad, target)
    with pytest.raises(ValueError, match=r"^noisy has 1 NaN/Inf value\(s\)"):
        den.propagated_variance(bad, target)
    n3, t3 = rand(4, 3, 3, seed=72), rand(4, 3, 3, seed=73)
    ref3 = target_aware_denoise_reference(n3, t3, radius=1, weight_mode="per_channel")
    assert ref3.shape == (4, 3, 3)
    assert (target_aware_denoise(n3, t3, radius=1, weight_mode="per_channel", var_floor=1e-12) - ref3).abs().max() < 1e-8
    assert den.propagated_variance(torch.ones(4, 3, 3, dtype=D), t3).shape == (4, 3, 3)


def test_target_aware_input_errors():
    noisy, target = rand(2, 3, 4, 5, seed=74), rand(2, 3, 4, 5, seed=75)
    mask = torch.ones(4, 5, dtype=torch.bool)
    minus_one = target.clone()
    minus_one[1, 2, 3, 4] = -1.0  # log(1 + I) is undefined from -1 on, the end included
    cases = [
        (lambda: target_aware_denoise(noisy, target.tolist()), TypeError, "^target must be a torch.Tensor, got list$"),
        (lambda: target_aware_denoise(noisy, (target * 10).long()), TypeError, "^target must be a floating-point tensor, got torch.int64$"),
        (lambda: target_aware_denoise(noisy, rand(3, 3, 4, 5)), ValueError, r"^noisy \(2, 3, 4, 5\) and target \(3, 3, 4, 5\) differ: expected equal \(C,H,W\) and a target batch of 1 or 2$"),
        (lambda: target_aware_denoise(noisy, minus_one), ValueError, r"^target has values <= -1: the weights use log\(1 \+ I\), which is undefined there$"),
        (lambda: target_aware_denoise(noisy, target, mask=mask.double()), TypeError, r"^mask must be a bool tensor \(True = pixel takes part in the regressions\)$"),
        (lambda: target_aware_denoise(noisy, target, mask=mask[:, :4]), ValueError, r"^mask: expected \(H,W\), \(1,1,H,W\) or \(B,1,H,W\) with H,W = 4,5, got \(4, 4\)$"),
        (lambda: target_aware_denoise(noisy, target, mask=mask.expand(1, 2, 4, 5)), ValueError, r"got \(1, 2, 4, 5\)$"),
        (lambda: target_aware_denoise(noisy, target, mask=mask.expand(3, 1, 4, 5)), ValueError, r"got \(3, 1, 4, 5\)$"),
        (lambda: target_aware_denoise(noisy, target, mask=mask.to("meta")), ValueError, "^mask is on meta but noisy is on cpu$"),
        (lambda: TargetAwareDenoiser(radius=1)(noisy, target, views=[0]), ValueError, "^views has 1 ids for a batch of 2 images$"),
        (lambda: TargetAwareDenoiser().set_target(target.tolist()), TypeError, "^target must be a torch.Tensor, got list$"),
        (lambda: TargetAwareDenoiser().smoother_weights(target.tolist()), TypeError, "^target must be a torch.Tensor, got list$"),
        (lambda: target_aware_denoise_reference(noisy.tolist(), target), TypeError, "^noisy must be a torch.Tensor, got list$"),
        (lambda: target_aware_denoise_reference(noisy, target.tolist()), TypeError, "^target must be a torch.Tensor, got list$"),
    ]
    for call, error, match in cases:
        with pytest.raises(error, match=match):
            call()
    with pytest.warns(UserWarning, match="^target requires grad: the denoiser treats it as a constant; no gradient flows to it$") as record:
        target_aware_denoise(noisy, target.clone().requires_grad_(), radius=1)
    _assert_warned_here(record)
    from torchir.modules.target_aware import check_mask

    m = check_mask(mask, noisy)
    assert m.shape == (1, 1, 4, 5) and m.dtype == D
    for shaped in (mask.view(1, 1, 4, 5), mask.expand(2, 1, 4, 5)):  # (1,1,H,W) and (B,1,H,W) masks are accepted
        assert torch.equal(target_aware_denoise(noisy, target, radius=1, mask=shaped), target_aware_denoise(noisy, target, radius=1, mask=mask))
    shared = target_aware_denoise(noisy, target[:1], radius=1)  # a batch-1 target is shared
    assert torch.equal(shared, target_aware_denoise(noisy, target[:1].expand(2, -1, -1, -1), radius=1))


def test_target_aware_module_masks_views_and_cache():
    """The module with a mask equals the function; the cached taps are reused only for the same
    target and mask (a new or dropped mask rebuilds); set_target fills the same cache entry."""
    target, noisy = rand(1, 3, 6, 7, seed=76), rand(1, 3, 6, 7, seed=77)
    m1 = torch.ones(6, 7, dtype=torch.bool)
    m1[1:3, 2:5] = False
    m2 = torch.ones(6, 7, dtype=torch.bool)
    m2[4:, :2] = False
    den = TargetAwareDenoiser(radius=2, clamp_min=None)
    key = (None, (1, 3, 6, 7), D, noisy.device)
    for mask in (None, m1, m1, m2, None, m2):
        out = den(noisy, target, mask=mask)
        assert torch.equal(out, target_aware_denoise(noisy, target, radius=2, clamp_min=None, mask=mask)), mask
    taps = den._cache[key][2]
    den(noisy, target, mask=m2)
    assert den._cache[key][2] is taps  # same target and mask: reused
    lw = den.smoother_weights(target, mask=m1)
    masked = (lw * neighbours(noisy, 2)).sum(2)
    assert (masked - target_aware_denoise(noisy, target, radius=2, clamp_min=None, mask=m1)).abs().max() < 1e-12
    pre = TargetAwareDenoiser(radius=2, clamp_min=None)
    pre.set_target(target[0], mask=m1, views=["a"], dtype=D)
    (entry,) = pre._cache.values()
    out = pre(noisy, target, views=["a"], mask=m1)
    assert len(pre._cache) == 1 and next(iter(pre._cache.values()))[2] is entry[2]
    assert torch.equal(out, target_aware_denoise(noisy, target, radius=2, clamp_min=None, mask=m1))
    var = rand(1, 3, 6, 7, seed=78)
    pv = TargetAwareDenoiser(radius=2)
    pv.propagated_variance(var, target, views=["v"])
    assert [k[0] for k in pv._cache] == [("v",)]


def test_target_aware_cache_budget_lru_and_entry_limit():
    """The table cache holds what fits max_cache_bytes (table bytes = K^2 B C H W * itemsize),
    evicting the least recently used first; impl='taps' keeps every view's taps; at most 64
    entries, oldest out first; impl='cached' over budget names the module."""
    target, noisy = rand(1, 3, 4, 5, seed=79), rand(1, 3, 4, 5, seed=80)
    need = 5 * 5 * 1 * 3 * 4 * 5 * 8
    den = TargetAwareDenoiser(radius=2, max_cache_bytes=2 * need)
    den(noisy, target, views=[0])
    assert den._cache_bytes() == need
    den(noisy, target, views=[1])
    assert den._cache_bytes() == 2 * need and [k[0] for k in den._cache] == [(0,), (1,)]
    den(noisy, target, views=[0])  # touch 0: 1 is now the least recently used
    den(noisy, target, views=[2])
    assert [k[0] for k in den._cache] == [(0,), (2,)] and den._cache_bytes() == 2 * need
    one = TargetAwareDenoiser(radius=2, max_cache_bytes=need)
    one(noisy, target, views=[0]), one(noisy, target, views=[1])
    assert [k[0] for k in one._cache] == [(1,)] and one._cache_bytes() == need
    taps_only = TargetAwareDenoiser(radius=2, impl="taps", max_cache_bytes=0)
    taps_only(noisy, target, views=[0]), taps_only(noisy, target, views=[1])
    assert [k[0] for k in taps_only._cache] == [(0,), (1,)] and taps_only._cache_bytes() == 0
    with pytest.raises(ValueError, match="^TargetAwareDenoiser: impl='cached' needs"):
        TargetAwareDenoiser(radius=2, impl="cached", max_cache_bytes=need - 1)(noisy, target)
    many = TargetAwareDenoiser(radius=0)
    small_t, small_n = rand(1, 1, 2, 2, seed=81), rand(1, 1, 2, 2, seed=82)
    for v in range(65):
        many(small_n, small_t, views=[v])
    assert [k[0] for k in many._cache] == [(v,) for v in range(1, 65)]
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        two = TargetAwareDenoiser(radius=2, impl="cached")(noisy, target)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(two, TargetAwareDenoiser(radius=2, impl="cached")(noisy, target))


def test_target_aware_dtypes_budgets_and_messages():
    """Moments in float64 whatever the target's dtype; tables in the noisy's dtype (budgets and
    cache bytes count its itemsize); the clamp passes gradient at equality (1[f^ >= clamp_min]);
    zeros are not "negative"; 4-D inputs stay 4-D; budget messages give sizes in GiB."""
    target, noisy = rand(1, 3, 4, 5, seed=83), rand(1, 3, 4, 5, seed=84)
    torch.testing.assert_close(target_aware_denoise(noisy, target.float(), radius=2), target_aware_denoise(noisy, target.float().double(), radius=2), rtol=1e-12, atol=1e-14)
    need64 = 25 * 3 * 4 * 5 * 8
    with pytest.raises(ValueError, match="^target_aware_denoise: impl='cached' needs"):
        target_aware_denoise(noisy, target, radius=2, impl="cached", max_cache_bytes=need64 - 1)
    den32 = TargetAwareDenoiser(radius=2)
    den32(noisy.float(), target.float())
    assert den32._cache_bytes() == need64 // 2
    pre = TargetAwareDenoiser(radius=2)
    pre.set_target(target, dtype=torch.float32)  # float64 target, float32 renders
    (entry,) = pre._cache.values()
    pre(noisy.float(), target)
    assert len(pre._cache) == 1 and next(iter(pre._cache.values()))[2] is entry[2]
    assert TargetAwareDenoiser(radius=1).smoother_weights(target, dtype=torch.float32).dtype == torch.float32
    small, big = rand(1, 3, 4, 5, seed=85), rand(1, 3, 4, 10, seed=86)
    s = 9 * 3 * 4 * 5 * 8
    lru = TargetAwareDenoiser(radius=1, max_cache_bytes=2 * s)
    lru(small, small, views=[0]), lru(small, small, views=[1]), lru(big, big, views=[2])  # the big table needs both out
    assert [k[0] for k in lru._cache] == [(2,)] and lru._cache_bytes() == 2 * s
    zero = torch.zeros(1, 3, 4, 5, dtype=D, requires_grad=True)
    out = target_aware_denoise(zero, target, radius=1)  # exactly at the clamp
    (g,) = torch.autograd.grad(out.sum(), zero)
    assert torch.equal(out, torch.zeros_like(out)) and (g > 0).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        target_aware_denoise(noisy, torch.zeros_like(target), radius=1)  # black is not negative
    with pytest.warns(UserWarning, match=r"^target has negative values: the weights clamp them at 0 \(log\(1 \+ max\(I, 0\)\)\)$") as record:
        target_aware_denoise(noisy, target - 0.5, radius=1)
    _assert_warned_here(record)  # the caller's line, not the denoiser's internals
    four, noisy4 = rand(1, 4, 2, 5, seed=87), rand(1, 4, 2, 5, seed=90)  # rgb weights: first 3 of 4 channels, whatever H
    kw = dict(radius=1, bandwidth=1.0, clamp_min=None)  # wide enough that neighbours weigh
    assert (target_aware_denoise(noisy4, four, var_floor=1e-12, **kw) - target_aware_denoise_reference(noisy4, four, **kw)).abs().max() < 1e-8
    assert target_aware_denoise_reference(noisy, target, radius=1).shape == (1, 3, 4, 5)
    assert TargetAwareDenoiser(radius=1).propagated_variance(noisy, target).shape == (1, 3, 4, 5)
    with pytest.raises(TypeError, match="^noisy must be a torch.Tensor, got list$"):
        target_aware_denoise(noisy.tolist(), target)
    with pytest.raises(ValueError, match="^radius must be an int >= 0, got 1.5$"):
        target_aware_denoise(noisy, target, radius=1.5)
    with pytest.raises(ValueError, match="^max_cache_bytes must be >= 0, got -1$"):
        target_aware_denoise(noisy, target, max_cache_bytes=-1)
    t64, n64 = rand(1, 3, 64, 64, seed=88), rand(1, 3, 64, 64, seed=89)  # 225 * 3 * 64^2 * 8 B = 0.0206 GiB
    with pytest.raises(ValueError, match=r"^target_aware_denoise: impl='cached' needs 0.02 GiB for the tap table \(15x15 window, 64x64 image\), over max_cache_bytes=0.01 GiB"):
        target_aware_denoise(n64, t64, radius=7, impl="cached", max_cache_bytes=10 * 2**20)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        y = noisy.clone().requires_grad_()
        target_aware_denoise(y, target, radius=1, impl="taps").sum().backward()
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)
