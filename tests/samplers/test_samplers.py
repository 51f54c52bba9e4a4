"""Pixel samplers without a renderer (spec adaptive-sampling §6.1): pmf validity, draws,
unbiasedness with known moments, multi-resolution, refresh schedule, extremes."""
from __future__ import annotations

import math

import pytest
import torch

from torchir.samplers import (
    SAMPLERS,
    AdaptivePixelSampler,
    LossPixelSampler,
    PixelBatch,
    UniformPixelSampler,
    _pmf,
)

H, W = 16, 12


@pytest.fixture(autouse=True)
def _on_the_host():
    """The samplers keep their pmf, draws and weights on the host (torchir.samplers.pixel); so
    does this file, on any machine (on a GPU, tests/conftest.py makes the device the default)."""
    with torch.device("cpu"):
        yield


def _sampler(cls=AdaptivePixelSampler, views=1, **kw):
    return cls(**{"resolution": (H, W), "views": views, "budget": 64, **kw})


# ------------------------------------------------------------------------------------ pmf
@pytest.mark.parametrize("multires", ["equal", "paper"])
def test_pmf_is_valid_and_floored(multires):
    g = torch.Generator(device="cpu").manual_seed(0)
    s = _sampler(views=2, multires=multires, alpha=0.1)
    p1 = [torch.rand(2, 8, 6, generator=g), torch.rand(2, 4, 3, generator=g)]
    p2 = [torch.rand(2, 8, 6, generator=g).float(), torch.rand(2, 4, 3, generator=g)]
    pmf = s.update_from_maps(p1, p2)
    m = 2 * H * W
    assert pmf.shape == (2, H, W) and pmf.dtype == torch.float64
    assert abs(float(s.pdf.sum()) - 1.0) < 1e-12
    assert float(s.pdf.min()) >= 0.1 / m * (1 - 1e-9)


def test_multires_modes_weight_levels_as_specified():
    # Level 0 puts all mass on the left half, level 1 on the right half.
    p1_fine, p1_coarse = torch.zeros(1, 32, 32), torch.zeros(1, 16, 16)
    p1_fine[..., :16], p1_coarse[..., 8:] = 1.0, 1.0
    ones = [torch.ones(1, 32, 32), torch.ones(1, 16, 16)]
    with pytest.warns(UserWarning, match="alpha=0"):
        equal = _sampler(multires="equal", alpha=0.0, sigma=0.0, resolution=(32, 32))
        paper = _sampler(multires="paper", alpha=0.0, sigma=0.0, resolution=(32, 32))
    for s in (equal, paper):
        s.update_from_maps([p1_fine, p1_coarse], ones)
    left = lambda s: float(s.pdf_image()[..., :16].sum())
    # equal: w = (1/2, 1/2); paper: w ∝ (1, 4) -> 1/5 on the fine level. Bilinear upsampling
    # gives the coarse level's first left column p1 = 1/4, so q = sqrt(1/4): it leaks
    # 0.5 / 16.5 of that level's mass across the centre.
    leak = 0.5 / 16.5
    assert left(equal) == pytest.approx(0.5 + 0.5 * leak, abs=1e-3)
    assert left(paper) == pytest.approx(0.2 + 0.8 * leak, abs=1e-3)
    assert left(equal) > left(paper) + 0.2


def test_single_level_equals_explicit_computation():
    g = torch.Generator(device="cpu").manual_seed(1)
    p1, p2 = torch.rand(1, H, W, generator=g), torch.rand(1, H, W, generator=g)
    s = _sampler(alpha=0.25, sigma=0.0, levels=0)
    s.update_from_maps(p1, p2)
    q = (p1.double() * p2.double()).sqrt()
    expected = 0.75 * q / q.sum() + 0.25 / (H * W)
    torch.testing.assert_close(s.pdf_image(), expected, rtol=1e-12, atol=1e-15)
    # E6: predicted gain m sum a / (sum sqrt a)^2 with a = p1 p2
    gain = H * W * float(q.square().sum()) / float(q.sum()) ** 2
    assert s.diagnostics()["predicted_gain"] == pytest.approx(gain, rel=1e-9)
    assert gain > 1.05  # the maps are not flat: the check has something to compare


@pytest.mark.parametrize("which", ["p1", "p2"])
def test_all_zero_factor_falls_back_to_uniform(which):
    maps = {"p1": torch.rand(1, H, W), "p2": torch.rand(1, H, W)}
    maps[which] = torch.zeros(1, H, W)
    s = _sampler()
    s.update_from_maps(maps["p1"], maps["p2"])
    torch.testing.assert_close(s.pdf, torch.full((H * W,), 1.0 / (H * W), dtype=torch.float64), rtol=1e-12, atol=0)
    assert torch.isfinite(s.sample().weight).all()


def test_nan_maps_warn_and_fall_back_never_nan_weights():
    p1 = torch.rand(1, H, W)
    p1[0, 3, 3] = float("nan")
    s = _sampler()
    with pytest.warns(UserWarning, match="NaN/Inf"):
        s.update_from_maps(p1, torch.rand(1, H, W))
    # the NaN level falls back to uniform: p1 is NaN there, so the whole pmf is uniform
    torch.testing.assert_close(s.pdf, torch.full((H * W,), 1.0 / (H * W), dtype=torch.float64), rtol=1e-12, atol=0)
    assert s.diagnostics()["uniform_levels"] >= 1
    batch = s.sample()
    torch.testing.assert_close(batch.weight, torch.full((64,), 1.0 / 64), rtol=1e-6, atol=0)


def test_one_hot_pixel_mass():
    p1 = torch.zeros(1, H, W)
    p1[0, 5, 7] = 1.0
    s = _sampler(alpha=0.1, sigma=0.0)
    s.update_from_maps(p1, torch.ones(1, H, W))
    m = H * W
    assert float(s.pdf_image()[0, 5, 7]) == pytest.approx(0.9 + 0.1 / m, rel=1e-12)
    # with the default blur the hot pixel keeps the blur kernel's centre share
    blurred = _sampler(alpha=0.1)
    blurred.update_from_maps(p1, torch.ones(1, H, W))
    share = float(blurred.pdf_image()[0, 5, 7] - 0.1 / m) / 0.9
    assert 0.05 < share < 0.5


def test_bad_maps_raise():
    s = _sampler(views=2)
    with pytest.raises(ValueError, match=r"\(2, h, w\)"):
        s.update_from_maps(torch.rand(1, H, W), torch.rand(1, H, W))
    with pytest.raises(ValueError, match="level"):
        s.update_from_maps([torch.rand(2, 4, 4)], [torch.rand(2, 4, 4), torch.rand(2, 2, 2)])
    with pytest.raises(TypeError, match="p1 must be a torch tensor, got list"):
        s.update_from_maps([[1.0]], None)


# ---------------------------------------------------------------------------- budgets
def test_budgets():
    m = H * W
    assert _sampler(budget=1).sample().index.shape == (1,)
    assert _sampler(budget=0.1).budget == round(0.1 * m)
    assert _sampler(budget=1e-6).budget == 1
    big = _sampler(budget=3 * m)
    assert big.sample().index.shape == (3 * m,)  # with replacement
    for bad in (0, -3):
        with pytest.raises(ValueError, match="budget"):
            _sampler(budget=bad)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="budget"):
            _sampler(budget=bad)
    with pytest.raises(TypeError, match="budget"):
        _sampler(budget=True)


def test_construction_errors():
    with pytest.raises(ValueError, match="scene, or resolution"):
        AdaptivePixelSampler(budget=4)
    with pytest.raises(ValueError, match="alpha"):
        _sampler(alpha=1.5)
    with pytest.raises(ValueError, match="refresh_every"):
        _sampler(refresh_every=0)
    with pytest.raises(ValueError, match="multires"):
        _sampler(multires="sum")
    assert _sampler(update_every=7).refresh_every == 7  # DESIGN.md's name
    with pytest.warns(UserWarning, match="alpha=0"):
        _sampler(alpha=0.0)


def test_registry():
    assert SAMPLERS["uniform"] is UniformPixelSampler and SAMPLERS["adaptive"] is AdaptivePixelSampler
    assert SAMPLERS["loss"] is LossPixelSampler


# ------------------------------------------------------------------------------ draws
def test_chi_square_of_draws():
    g = torch.Generator(device="cpu").manual_seed(3)
    pmf = torch.rand(1000, generator=g, dtype=torch.float64) ** 3 + 1e-3
    pmf /= pmf.sum()
    cdf = _pmf.cumulative(pmf)
    n = 1_000_000
    index, prob = _pmf.draw(cdf, n, torch.Generator(device="cpu").manual_seed(4))
    torch.testing.assert_close(prob, pmf[index], rtol=1e-9, atol=1e-15)  # weights use the realised pmf
    counts = torch.bincount(index, minlength=1000).double()
    expected = n * pmf
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    # 999 degrees of freedom: p-value > 1e-3 <=> chi2 < 1153 (Wilson-Hilferty)
    dof = 999
    z = ((chi2 / dof) ** (1 / 3) - (1 - 2 / (9 * dof))) / math.sqrt(2 / (9 * dof))
    assert z < 3.09, chi2


def test_draw_reads_the_same_probabilities_from_the_precomputed_pdf():
    g = torch.Generator(device="cpu").manual_seed(7)
    pmf = torch.rand(5000, generator=g, dtype=torch.float64) ** 4 + 1e-9
    pmf[0] = pmf.sum() / 10  # entry 0 (no left neighbour in the CDF) is drawn too
    cdf = _pmf.cumulative(pmf / pmf.sum())
    pdf = torch.diff(cdf, prepend=cdf.new_zeros(1))  # as PixelSampler keeps it
    index, prob = _pmf.draw(cdf, 50_000, torch.Generator(device="cpu").manual_seed(1))
    index_pdf, prob_pdf = _pmf.draw(cdf, 50_000, torch.Generator(device="cpu").manual_seed(1), pdf)
    assert torch.equal(index_pdf, index) and torch.equal(prob_pdf, prob)  # bit for bit, entry 0 included
    assert bool((index == 0).any())
    s = _sampler(seed=2, budget=300)
    s.update_from_maps(torch.rand(1, H, W, generator=g))
    batch = s.sample()
    assert torch.equal(batch.weight, (1.0 / (300 * H * W * s.pdf[batch.index])).float())


def test_huge_image_beyond_multinomial_limit():
    s = UniformPixelSampler(resolution=(4096, 8192), views=1, budget=10)  # 2^25 pixels
    batch = s.sample()
    assert int(batch.index.max()) < 2**25 and batch.index.dtype == torch.int64
    torch.testing.assert_close(batch.weight, torch.full((10,), 1 / 10.0))


def test_same_seed_same_indices_and_state_round_trip():
    a, b = _sampler(seed=5), _sampler(seed=5)
    p1 = torch.rand(1, H, W, generator=torch.Generator(device="cpu").manual_seed(0))
    a.update_from_maps(p1, torch.ones(1, H, W))
    b.update_from_maps(p1, torch.ones(1, H, W))
    assert torch.equal(a.sample().index, b.sample().index)
    state = a.state_dict()
    after = a.sample()
    c = _sampler(seed=99)
    c.load_state_dict(state)
    again = c.sample()
    assert torch.equal(after.index, again.index) and torch.equal(after.weight, again.weight)
    with pytest.raises(ValueError, match="strategy|sampler"):
        UniformPixelSampler(resolution=(H, W), budget=4).load_state_dict(state)


def test_view_restriction_and_global_indices():
    s = _sampler(views=3, budget=500)
    batch = s.sample(views=[2])
    assert bool(((batch.index // (H * W)) == 2).all())
    # a uniform pmf restricted to one view: p_V = 1 / (H W), so w = 1 / (N m_V p_V) = 1 / N
    torch.testing.assert_close(batch.weight, torch.full((500,), 1.0 / 500), rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match=r"views must be a non-empty subset of range\(3\)"):
        s.sample(views=[3])
    with pytest.raises(ValueError, match=r"views must be a non-empty subset of range\(3\)"):
        s.sample(views=[])


def test_view_subset_weights_are_the_conditional_pmf():
    """``w_n = 1 / (N m_V p_V[j_n])`` with ``m_V`` the subset's pixel count and ``p_V`` the pmf
    conditioned on the subset's pixels, computed here independently of ``sample``."""
    g = torch.Generator(device="cpu").manual_seed(5)
    s = _sampler(views=3, budget=200)
    s.update_from_maps(torch.rand(3, H, W, generator=g), torch.rand(3, H, W, generator=g))
    subset = [0, 2]
    batch = s.sample(views=[2, 0, 2])  # order and repeats do not matter
    view = batch.index // (H * W)
    assert set(view.tolist()) == set(subset)
    conditional = s.pdf_image()[subset].reshape(-1)
    conditional = conditional / conditional.sum()
    local = torch.searchsorted(torch.tensor(subset), view) * H * W + batch.index % (H * W)
    expected = 1.0 / (200 * len(subset) * H * W * conditional[local])
    torch.testing.assert_close(batch.weight.double(), expected, rtol=1e-5, atol=0)


def test_view_subset_estimate_is_unbiased_for_the_subset_mean():
    """The mean over the subset's pixels, as a full render of that view batch gives. With the
    per-draw standard error ``se`` of the 4000 independent estimates, a 4 se bound has a false
    alarm rate ~6e-5; the estimate's spread here is ~1 % of the mean while weights built from
    all 3 views' pixel count (or the subset pmf left unnormalised) are off by a factor 2/3
    (or 3/2): caught at > 30 se."""
    g = torch.Generator(device="cpu").manual_seed(6)
    losses = torch.rand(3 * H * W, generator=g, dtype=torch.float64) ** 2
    s = UniformPixelSampler(resolution=(H, W), views=3, budget=32, seed=2)
    s_adaptive = AdaptivePixelSampler(resolution=(H, W), views=3, budget=32, seed=2)
    s_adaptive.update_from_maps(torch.rand(3, H, W, generator=g), torch.rand(3, H, W, generator=g))
    subset = [0, 1]
    truth = float(losses.reshape(3, -1)[subset].mean())
    for sampler in (s, s_adaptive):
        est = []
        for _ in range(4000):
            batch = sampler.sample(views=subset)
            est.append(float((batch.weight.double() * losses[batch.index]).sum()))
        est = torch.tensor(est, dtype=torch.float64)
        se = float(est.std()) / math.sqrt(est.numel())
        assert se < 0.02 * truth  # power: a factor 2/3 or 3/2 error is > 15 se away
        assert abs(float(est.mean()) - truth) < 4 * se, (float(est.mean()), truth, se)


# ---------------------------------------------------------------------- unbiasedness
def _estimate(sampler: AdaptivePixelSampler, losses: torch.Tensor, draws: int) -> torch.Tensor:
    values = []
    for _ in range(draws):
        batch = sampler.sample()
        values.append(float((batch.weight.double() * losses[batch.index]).sum()))
    return torch.tensor(values, dtype=torch.float64)


@pytest.mark.parametrize("cls", [UniformPixelSampler, AdaptivePixelSampler])
def test_weighted_sum_is_unbiased_for_the_mean(cls):
    g = torch.Generator(device="cpu").manual_seed(11)
    losses = torch.rand(2 * H * W, generator=g, dtype=torch.float64) ** 4
    s = cls(resolution=(H, W), views=2, budget=32, seed=1)
    s.update_from_maps(torch.rand(2, H, W, generator=g), torch.rand(2, H, W, generator=g))
    est = _estimate(s, losses, 4000)
    se = float(est.std()) / math.sqrt(est.numel())
    assert abs(float(est.mean()) - float(losses.mean())) < 4 * se


def test_synthetic_gradient_estimator_unbiased_and_variance_matches_theory():
    """Pixels with known per-pixel moments (spec §6.1 item 6): ⟨∂L/∂I_j⟩ ~ N(a_j, sa_j²),
    ⟨dI_j/dθ⟩ ~ N(b_j, sb_j²) with m_θ = 5, independent; the single-draw estimator's mean and
    trace variance follow E3/E5/E8."""
    g = torch.Generator(device="cpu").manual_seed(2)
    m, k = H * W, 5
    a, sa = torch.randn(m, generator=g, dtype=torch.float64), 0.5 * torch.rand(m, generator=g, dtype=torch.float64)
    b = torch.randn(m, k, generator=g, dtype=torch.float64) * torch.logspace(-1, 1, m, dtype=torch.float64)[:, None]
    sb = 0.3 * torch.rand(m, k, generator=g, dtype=torch.float64)
    exact = (a[:, None] * b).sum(0) / m  # gradient of the mean loss
    p1, p2 = a**2 + sa**2, (b**2 + sb**2).sum(1)
    with pytest.warns(UserWarning, match="alpha=0"):
        s = AdaptivePixelSampler(resolution=(H, W), views=1, budget=1, alpha=0.0, sigma=0.0, levels=0, seed=3)
    s.update_from_maps((p1.reshape(1, H, W)), p2.reshape(1, H, W))
    draws = 20000
    batch = [s.sample() for _ in range(draws)]
    index = torch.cat([bt.index for bt in batch])
    weight = torch.cat([bt.weight for bt in batch]).double()
    noise = torch.Generator(device="cpu").manual_seed(4)
    adj = a[index] + sa[index] * torch.randn(draws, generator=noise, dtype=torch.float64)
    der = b[index] + sb[index] * torch.randn(draws, k, generator=noise, dtype=torch.float64)
    grads = weight[:, None] * adj[:, None] * der  # (draws, k)
    se = grads.std(0) / math.sqrt(draws)
    assert bool(((grads.mean(0) - exact).abs() < 4 * se).all())
    # E5/E8: trace of the second moment = sum_j p1_j p2_j / (m^2 p_j)
    p = s.pdf
    second = float((p1 * p2 / p).sum()) / m**2
    predicted = second - float(exact.square().sum())
    empirical = float(grads.var(0).sum())
    assert abs(empirical / predicted - 1) < 0.05


def test_variance_ordering_oracle_eq5_uniform():
    g = torch.Generator(device="cpu").manual_seed(8)
    m = H * W
    a = torch.randn(m, generator=g, dtype=torch.float64)
    b = torch.logspace(-1, 1, m, dtype=torch.float64)[torch.randperm(m, generator=g)]  # p2 varies 100x
    p1, p2 = a**2, b**2

    def trace_second_moment(sampler):
        return float((p1 * p2 / sampler.pdf).sum())

    with pytest.warns(UserWarning, match="alpha=0"):
        oracle = AdaptivePixelSampler(resolution=(H, W), budget=1, alpha=0.0, sigma=0.0, levels=0)
        eq5 = LossPixelSampler(resolution=(H, W), budget=1, alpha=0.0, sigma=0.0, levels=0)
    oracle.update_from_maps(p1.reshape(1, H, W), p2.reshape(1, H, W))
    eq5.update_from_maps(p1.reshape(1, H, W))
    uniform = UniformPixelSampler(resolution=(H, W), budget=1)
    assert trace_second_moment(oracle) < trace_second_moment(eq5) < trace_second_moment(uniform)


def test_zero_adjoint_gives_exactly_zero_gradient():
    """A zero loss adjoint everywhere (a converged pixel set) gives the uniform pmf, hence
    finite weights 1 / N, hence an exactly zero estimate (0 * Inf would be NaN)."""
    s = _sampler()
    s.update_from_maps(torch.zeros(1, H, W), torch.rand(1, H, W))
    batch = s.sample()
    torch.testing.assert_close(batch.weight, torch.full((64,), 1.0 / 64), rtol=1e-6, atol=0)
    assert float((batch.weight * torch.zeros(H * W)[batch.index]).sum()) == 0.0
    assert s.diagnostics()["predicted_gain"] == 1.0


# --------------------------------------------------------------------------- schedule
def test_refresh_schedule_and_reshape():
    s = AdaptivePixelSampler(resolution=(H, W), budget=4, refresh_every=20)
    params = {"tex": torch.zeros(4, 4, 3)}
    runs = []
    for step in range(61):
        if s.due(step, params):
            runs.append(step)
            s.last_update, s._signature = step, s._signature_of(params, None)  # what update() records
    assert runs == [0, 20, 40, 60]
    assert not s.due(60, params) and not s.due(61, params)  # just refreshed
    assert s.due(61, {"tex": torch.zeros(8, 8, 3)})  # re-gridded texture: refresh at once
    assert s.due(59, params)  # a step before the last refresh (a resumed or rewound run)
    two = AdaptivePixelSampler(resolution=(H, W), views=2, budget=4, refresh_every=20)
    two.last_update, two._signature = 0, two._signature_of(params, [0, 1])
    assert not two.due(1, params, [0, 1]) and not two.due(1, params)  # None means every view
    assert two.due(1, params, [1])  # another view set: its targets differ
    assert not UniformPixelSampler(resolution=(H, W), budget=4).due(0, params)


def test_stage1_grids():
    from torchir.samplers.pixel import _stage1_grids

    assert _stage1_grids((128, 128), 4, 32, 4) == [(32, 32), (16, 16), (8, 8), (4, 4)]
    assert _stage1_grids((64, 64), 4, 32, 4)[0] == (32, 32)
    assert _stage1_grids((16, 16), 4, 32, 4) == [(16, 16), (8, 8), (4, 4)]
    assert _stage1_grids((16, 16), 4, 32, 0) == [(16, 16)]
    assert _stage1_grids((1, 1), 4, 32, 4) == [(1, 1)]
    assert _stage1_grids((40, 96), 4, 32, 1) == [(32, 77), (16, 38)]


def test_pixel_batch_fields():
    s = UniformPixelSampler(resolution=(H, W), views=2, budget=3)
    batch = s.sample()
    assert isinstance(batch, PixelBatch) and batch.weight.dtype == torch.float32 and batch.index.dtype == torch.int64
    assert batch.index.shape == batch.weight.shape == (3,)
    assert bool(((batch.index >= 0) & (batch.index < 2 * H * W)).all())
    torch.testing.assert_close(batch.weight, torch.full((3,), 1.0 / 3))  # 1 / (N m p), p = 1 / m
    d = s.diagnostics()
    assert d["ess_fraction"] == pytest.approx(1.0) and d["max_weight_ratio"] == pytest.approx(1.0)


# ------------------------------------------------------------------------ pmf internals (_pmf)
def _gauss_1d(sigma: float, r: int) -> torch.Tensor:
    k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float64).square() / (2 * sigma**2))
    return k / k.sum()


@pytest.mark.parametrize(("sigma", "radius"), [(0.3, 1), (1.0, 2), (1.6, 4)])
def test_denoise_blur_radius_is_max_1_ceil_2_sigma(sigma, radius):
    """A5: a Gaussian of ``sigma`` low-res pixels on a ``2 max(1, ceil(2 sigma)) + 1`` window:
    a delta in the middle becomes the normalised separable kernel, zero beyond its radius."""
    x = torch.zeros(1, 11, 11, dtype=torch.float64)
    x[0, 5, 5] = 1.0
    out = _pmf.denoise_upsample(x, (11, 11), sigma)
    expected = torch.zeros(11, 11, dtype=torch.float64)
    k = _gauss_1d(sigma, radius)
    expected[5 - radius : 6 + radius, 5 - radius : 6 + radius] = k[:, None] * k[None, :]
    torch.testing.assert_close(out[0], expected, rtol=1e-5, atol=1e-7)
    assert torch.count_nonzero(out[0][expected == 0]) == 0  # exactly: no taps beyond the radius


def test_denoise_border_replicates_and_thin_maps_are_not_blurred():
    x = torch.zeros(1, 6, 6, dtype=torch.float64)
    x[0, 0, 0] = 1.0  # corner: replicate keeps the (r + 1)^2 - 1 outside taps on the corner pixel
    k = _gauss_1d(1.0, 2)
    corner = float(k[:3].sum() ** 2)
    assert _pmf.denoise_upsample(x, (6, 6), 1.0)[0, 0, 0].item() == pytest.approx(corner, rel=1e-5)
    row = torch.rand(1, 1, 5, dtype=torch.float64)  # one pixel high: no blur at all
    torch.testing.assert_close(_pmf.denoise_upsample(row, (1, 5), 1.0), row, rtol=0, atol=0)
    two = torch.rand(1, 2, 5, dtype=torch.float64)  # two pixels high: blurred
    assert not torch.allclose(_pmf.denoise_upsample(two, (2, 5), 1.0), two)


def test_upsampling_is_half_pixel_bilinear():
    """``align_corners=False``: [a, b] -> [a, (3a + b)/4, (a + 3b)/4, b]; negatives clamp to 0."""
    x = torch.tensor([[[1.0, 3.0]]], dtype=torch.float64)
    torch.testing.assert_close(_pmf.denoise_upsample(x, (1, 4), 0.0), torch.tensor([[[1.0, 1.5, 2.5, 3.0]]], dtype=torch.float64))
    assert _pmf.denoise_upsample(-x, (1, 4), 0.0).abs().sum() == 0


def test_pmf_defaults_views_and_2d_maps():
    """Documented defaults (alpha 0.1, equal levels, sigma 1); views from p1's first axis, a
    2-D map is one view."""
    g = torch.Generator(device="cpu").manual_seed(0)
    p1, p2 = torch.rand(2, 4, 3, generator=g), torch.rand(2, 4, 3, generator=g)
    pmf, _ = _pmf.pmf_from_maps(p1, p2, (8, 6))
    explicit, _ = _pmf.pmf_from_maps(p1, p2, (8, 6), alpha=0.1, multires="equal", sigma=1.0)
    assert pmf.shape == (2, 8, 6) and torch.equal(pmf, explicit)
    assert not torch.allclose(pmf, _pmf.pmf_from_maps(p1, p2, (8, 6), sigma=2.0)[0])
    single, _ = _pmf.pmf_from_maps(p1[0], p2[0], (8, 6))
    torch.testing.assert_close(single, _pmf.pmf_from_maps(p1[:1], p2[:1], (8, 6))[0], rtol=0, atol=0)
    assert single.shape == (1, 8, 6)
    full, _ = _pmf.pmf_from_maps(p1, None, (8, 6), alpha=1.0)  # alpha = 1: the uniform pmf
    torch.testing.assert_close(full, torch.full((2, 8, 6), 1 / 96, dtype=torch.float64), rtol=1e-12, atol=0)


def test_fallback_level_mixes_in_as_uniform_and_is_counted():
    """A zero level contributes the uniform pmf with its level weight: with levels (q, 0),
    ``p = (1 - alpha) (q / sum q + 1/m) / 2 + alpha / m``; ``uniform_levels`` counts them."""
    g = torch.Generator(device="cpu").manual_seed(1)
    q = torch.rand(1, 4, 4, generator=g, dtype=torch.float64)
    pmf, stats = _pmf.pmf_from_maps([q, torch.zeros(1, 2, 2)], None, (4, 4), alpha=0.2, sigma=0.0)
    level = q.sqrt() / q.sqrt().sum()
    torch.testing.assert_close(pmf, 0.8 * (level + 1 / 16) / 2 + 0.2 / 16, rtol=1e-12, atol=0)
    assert stats["uniform_levels"] == 1.0
    assert _pmf.pmf_from_maps([q, q[:, :2, :2]], None, (4, 4))[1]["uniform_levels"] == 0.0
    assert _pmf.pmf_from_maps([q * 0, q[:, :2, :2] * 0], None, (4, 4))[1]["uniform_levels"] == 2.0


def test_pmf_argument_errors_name_the_argument():
    ok = torch.rand(1, 4, 4)
    for kwargs, match in [
        (dict(alpha=1.5), r"^alpha must be in \[0, 1\], got 1.5$"),
        (dict(multires="sum"), r"^multires must be 'equal' or 'paper', got 'sum'$"),
    ]:
        with pytest.raises(ValueError, match=match):
            _pmf.pmf_from_maps(ok, ok, (4, 4), **kwargs)
    with pytest.raises(ValueError, match="^p1 has no levels$"):
        _pmf.pmf_from_maps([], None, (4, 4))
    with pytest.raises(ValueError, match=r"^p2 must be \(1, h, w\) \(one map per view\), got \(2, 4, 4\)$"):
        _pmf.pmf_from_maps(ok, torch.rand(2, 4, 4), (4, 4))
    for which in ("p1", "p2"):
        maps = {"p1": ok, "p2": ok.clone()}
        maps[which] = torch.full((1, 4, 4), float("inf"))
        with pytest.warns(UserWarning, match=f"^{which} has NaN/Inf entries: this level falls back to the uniform pmf$"):
            _pmf.pmf_from_maps(maps["p1"], maps["p2"], (4, 4))


def test_cumulative_is_float64_and_draws_invert_it():
    """Inverse-CDF draws from float64 uniforms of the generator (checked with bisect)."""
    import bisect

    pmf = torch.rand(50, generator=torch.Generator(device="cpu").manual_seed(2)) ** 4  # float32 in, float64 out
    cdf = _pmf.cumulative(pmf)
    assert cdf.dtype == torch.float64 and cdf[-1].item() == 1.0
    index, _ = _pmf.draw(cdf, 2000, torch.Generator(device="cpu").manual_seed(3))
    u = torch.rand(2000, generator=torch.Generator(device="cpu").manual_seed(3), dtype=torch.float64)
    expected = [bisect.bisect_right(cdf.tolist(), v) for v in u.tolist()]
    assert index.tolist() == expected


# ------------------------------------------------------- construction, state, schedule (issue 19)
class _Scene:
    """What the sampler's constructor reads of a scene: film sizes and the sensor count."""

    def __init__(self, sizes):
        self.sizes = list(sizes)
        self.sensor_count = len(self.sizes)
        self.resolution = self.sizes[0]

    def sensor_resolution(self, view):
        return self.sizes[view]


def test_scene_sets_resolution_and_views_and_must_agree():
    s = AdaptivePixelSampler(_Scene([(H, W)] * 3), budget=4)
    assert (s.resolution, s.views, s.pixel_count) == ((H, W), 3, 3 * H * W)
    same = AdaptivePixelSampler(_Scene([(H, W)] * 3), budget=4, resolution=(H, W), views=3)
    assert (same.resolution, same.views) == ((H, W), 3)
    with pytest.raises(ValueError, match=r"^pixel samplers need every sensor at one film size, the scene has \[\(12, 16\), \(16, 12\)\]$"):
        AdaptivePixelSampler(_Scene([(H, W), (W, H)]), budget=4)
    with pytest.raises(ValueError, match=r"^resolution \(8, 8\) differs from the scene's \(16, 12\)$"):
        AdaptivePixelSampler(_Scene([(H, W)]), budget=4, resolution=(8, 8))
    with pytest.raises(ValueError, match=r"^views=2 differs from the scene's 1 sensor\(s\)$"):
        AdaptivePixelSampler(_Scene([(H, W)]), budget=4, views=2)
    with pytest.raises(ValueError, match=r"^give a scene, or resolution=\(H, W\) \(and views\) for torch-only use$"):
        AdaptivePixelSampler(budget=4, views=2)


def test_constructor_defaults_and_argument_messages():
    s = UniformPixelSampler(resolution=8)  # an int is a square film; one view by default
    assert (s.resolution, s.views, s.pixel_count) == ((8, 8), 1, 64)
    # the documented defaults (signature and docstring)
    explicit = UniformPixelSampler(
        None, 0.05, 20, 4, 0.1, 0, (8, 8), 1, scale=4, min_side=32, stage1_spp=4, multires="equal", sigma=1.0, fd_step=1e-2
    )
    fields = ("budget", "refresh_every", "levels", "alpha", "seed", "scale", "min_side", "stage1_spp", "multires", "sigma", "fd_step")
    assert {f: getattr(s, f) for f in fields} == {f: getattr(explicit, f) for f in fields}
    assert torch.equal(s.sample().index, explicit.sample().index)  # the generator is seeded with seed=0
    torch.testing.assert_close(s.pdf, torch.full((64,), 1 / 64, dtype=torch.float64), rtol=1e-12, atol=0)
    assert UniformPixelSampler(resolution=(1, 1)).pixel_count == 1  # the smallest film is valid
    # boundary values that are valid
    _sampler(refresh_every=1, stage1_spp=1, scale=1, min_side=1, levels=0, alpha=1.0, sigma=0.0)
    for kwargs, match in [
        (dict(resolution=(0, W)), r"^resolution and views must be >= 1, got \(0, 12\) and 1$"),
        (dict(resolution=(H, 0)), r"^resolution and views must be >= 1, got \(16, 0\) and 1$"),
        (dict(views=0), r"^resolution and views must be >= 1, got \(16, 12\) and 0$"),
        (dict(refresh_every=True), r"^refresh_every must be an int >= 1, got True$"),
        (dict(refresh_every=2.0), r"^refresh_every must be an int >= 1, got 2.0$"),
        (dict(stage1_spp=0), r"^stage1_spp must be an int >= 1, got 0$"),
        (dict(scale=0), r"^scale must be an int >= 1, got 0$"),
        (dict(min_side=0), r"^min_side must be an int >= 1, got 0$"),
        (dict(levels=-1), r"^levels must be an int >= 0, got -1$"),
        (dict(levels=1.0), r"^levels must be an int >= 0, got 1.0$"),
        (dict(alpha=-0.1), r"^alpha must be in \[0, 1\], got -0.1$"),
        (dict(alpha=1.5), r"^alpha must be in \[0, 1\], got 1.5$"),
        (dict(multires="sum"), r"^multires must be 'equal' or 'paper', got 'sum'$"),
        (dict(fd_step=0.0), r"^fd_step must be > 0 and sigma >= 0, got 0.0 and 1.0$"),
        (dict(sigma=-1.0), r"^fd_step must be > 0 and sigma >= 0, got 0.01 and -1.0$"),
    ]:
        with pytest.raises(ValueError, match=match):
            _sampler(**kwargs)


def test_budget_messages_and_boundaries():
    m = H * W
    assert _sampler(budget=1.0).budget == m and _sampler(budget=1).budget == 1
    assert _sampler(budget=0.5).budget == m // 2
    with pytest.raises(TypeError, match=r"^budget must be an int \(pixel draws\) or a float in \(0, 1\] \(fraction of pixels\), got str$"):
        _sampler(budget="8")
    with pytest.raises(ValueError, match=r"^a fractional budget must be in \(0, 1\], got 1.5; give an int for more draws than pixels$"):
        _sampler(budget=1.5)
    with pytest.raises(ValueError, match=r"^a fractional budget must be in \(0, 1\], got 0.0;"):
        _sampler(budget=0.0)
    with pytest.raises(ValueError, match=r"^budget must be >= 1 pixel draw, got 0$"):
        _sampler(budget=0)


def test_alpha_zero_warns_only_for_stage1_samplers_and_at_the_caller():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        UniformPixelSampler(resolution=(H, W), budget=4, alpha=0.0)  # its pmf is uniform anyway
        LossPixelSampler(resolution=(H, W), budget=4, alpha=0.5)
    for cls in (LossPixelSampler, AdaptivePixelSampler):
        with pytest.warns(UserWarning, match=r"^alpha=0: pixels the Stage-1 pmf misses are never drawn") as record:
            cls(resolution=(H, W), budget=4, alpha=0.0)
        # stacklevel=2: attributed to the constructor's caller, not to pixel.py (not compared with
        # __file__: under mutmut a trampoline frame sits between the test and the constructor)
        assert not record[0].filename.endswith("pixel.py")


def test_strategy_names_are_the_registry_names_and_state_checks_them():
    for name in ("uniform", "loss", "adaptive"):
        assert SAMPLERS[name].strategy == name
        assert _sampler(SAMPLERS[name]).state_dict()["strategy"] == name
    state = _sampler(AdaptivePixelSampler).state_dict()
    with pytest.raises(ValueError, match=r"^state of a 'adaptive' sampler, this one is 'uniform'$"):
        _sampler(UniformPixelSampler).load_state_dict(state)
    state["pmf"] = torch.full((2, H, W), 1 / (2 * H * W), dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^state pmf has shape \(2, 16, 12\), this sampler \(1, 16, 12\)$"):
        _sampler(AdaptivePixelSampler).load_state_dict(state)


def test_state_round_trip_restores_pmf_schedule_and_stats():
    params = {"b": torch.zeros(3), "a": torch.zeros(2, 2)}
    g = torch.Generator(device="cpu").manual_seed(7)
    a = _sampler(views=2, refresh_every=5)
    a.update_from_maps(torch.rand(2, H, W, generator=g), torch.rand(2, H, W, generator=g))
    a.sample()
    a.last_update, a.refreshes, a._signature = 3, 2, a._signature_of(params, None)  # what update() records
    state = a.state_dict()
    state["pmf"] = state["pmf"].float()  # a float32 pmf (e.g. from a checkpoint) is taken as float64
    b = _sampler(views=2, refresh_every=5, seed=1)
    b.load_state_dict(state)
    assert b.pdf.dtype == torch.float64
    torch.testing.assert_close(b.pdf, a.pdf, rtol=1e-6, atol=0)
    assert (b.last_update, b.refreshes) == (3, 2) and b.diagnostics() == a.diagnostics()
    for step in (4, 7, 8, 2):  # 3 + 5 = 8 is due, and so is a step before the last refresh
        assert b.due(step, params) == a.due(step, params) == (step >= 8 or step < 3)
    assert not b.due(4, params) and b.due(4, {"a": torch.zeros(3, 3)})  # the signature came back
    # the state is a copy: sampling on does not change a saved state
    before = state["pmf"].clone()
    a.update_from_maps(torch.rand(2, H, W, generator=g))
    assert torch.equal(state["pmf"], before)


def test_update_without_stage1_only_records_the_schedule():
    s = UniformPixelSampler(resolution=(H, W), budget=4)
    assert (s.last_update, s.refreshes, s.diagnostics()) == (None, 0, {"predicted_gain": 1.0})
    s.update(step=3)  # no scene, no targets: the uniform sampler has no Stage 1
    s.update({"x": torch.zeros(2, requires_grad=True)}, step=5)
    assert (s.last_update, s.refreshes) == (5, 2)
    s.update()  # step 0 by default
    assert (s.last_update, s.refreshes) == (0, 3)
    s.update({"x": torch.zeros(2, requires_grad=True)}, step=5)
    assert s._signature == s._signature_of({"x": torch.zeros(2)}, None)
    torch.testing.assert_close(s.pdf, torch.full((H * W,), 1 / (H * W), dtype=torch.float64), rtol=1e-12, atol=0)
    with pytest.raises(RuntimeError, match=r"^AdaptivePixelSampler.update needs a scene; use update_from_maps for torch-only use$"):
        _sampler().update(step=0)


def test_due_ignores_param_order_and_missing_params():
    s = AdaptivePixelSampler(resolution=(H, W), views=2, budget=4, refresh_every=3)
    assert s.due(0) and s.due(5, {"x": torch.zeros(1)})  # never refreshed
    params = {"a": torch.zeros(2), "b": torch.zeros(3, 1)}
    s.last_update, s._signature = 10, s._signature_of(params, None)
    assert not s.due(10) and not s.due(12)  # no params given: only the schedule decides
    assert s.due(13) and s.due(9)
    assert not s.due(11, {"b": torch.ones(3, 1), "a": torch.ones(2)})  # same shapes, other order
    assert not s.due(11, params, [0, 1])
    assert s.due(11, {"a": torch.zeros(2)}) and s.due(11, params, [1, 0])  # a param gone; views reordered


def test_sample_view_argument_errors_and_all_views_path():
    s = _sampler(views=3, budget=300)
    for bad in ([-1], [0, 3], [-1, 1]):
        with pytest.raises(ValueError, match=r"^views must be a non-empty subset of range\(3\), got \[" ):
            s.sample(views=bad)
    batch = s.sample(views=[0])
    assert bool((batch.index < H * W).all()) and int(batch.index.min()) >= 0
    # every view, given explicitly, is the unrestricted draw: same generator stream, same batch
    a, b = _sampler(views=3, seed=4), _sampler(views=3, seed=4)
    p1 = torch.rand(3, H, W, generator=torch.Generator(device="cpu").manual_seed(3))
    a.update_from_maps(p1)
    b.update_from_maps(p1)
    x, y = a.sample(), b.sample(views=[2, 1, 0])
    assert torch.equal(x.index, y.index) and torch.equal(x.weight, y.weight)
    # restricted draws also come from the sampler's generator: same seed, same batch
    x, y = a.sample(views=[1, 2]), b.sample(views=[2, 1])
    assert torch.equal(x.index, y.index) and torch.equal(x.weight, y.weight)


def test_weights_enumerate_to_the_mean_for_a_constructed_pmf():
    """Unbiasedness by enumeration, no sampling error: every pixel's weight is a function of
    its index, ``w(j) = 1 / (N m p_j)``, so ``E[sum_n w_n f_{j_n}] = N sum_j p_j w(j) f_j``;
    with the weights observed on a batch that hits every pixel this must equal ``mean f``."""
    v, n = 2, 20000  # p_j >= alpha / m = 0.3 / 384: P(a pixel is missed) <= (1 - 7.8e-4)^20000 < 2e-7
    s = _sampler(views=v, budget=n, alpha=0.3, sigma=0.0, levels=0)
    p1 = torch.zeros(v, H, W)
    p1[0, :4, :6], p1[1, 10:, 3:] = 1.0, 9.0  # two hot blocks, sqrt: 1 and 3
    s.update_from_maps(p1)
    m = v * H * W
    q = p1.double().sqrt()
    expected = 0.7 * q / q.sum() + 0.3 / m
    torch.testing.assert_close(s.pdf_image(), expected, rtol=1e-12, atol=0)
    batch = s.sample()
    w = torch.zeros(m, dtype=torch.float64)
    w[batch.index] = batch.weight.double()
    assert bool((w > 0).all())
    torch.testing.assert_close(w, 1.0 / (n * m * expected.reshape(-1)), rtol=1e-6, atol=0)
    f = torch.rand(m, generator=torch.Generator(device="cpu").manual_seed(9), dtype=torch.float64)
    assert float(n * (s.pdf * w * f).sum()) == pytest.approx(float(f.mean()), rel=1e-6)
    # the batch diagnostics are those of its weights: (sum w)^2 / (N sum w^2), and N max w
    d, bw = s.diagnostics(), batch.weight.double()
    assert d["ess_fraction"] == pytest.approx(float(bw.sum() ** 2 / bw.square().sum()) / n, rel=1e-6)
    assert d["max_weight_ratio"] == pytest.approx(n * float(bw.max()), rel=1e-6)
    assert d["ess_fraction"] < 0.9 and d["max_weight_ratio"] == pytest.approx(1 / (m * float(expected.min())), rel=1e-6)


def test_rademacher_directions():
    from torchir.samplers.pixel import _rademacher

    t = _rademacher(torch.zeros(40, 50, dtype=torch.float64), torch.Generator(device="cpu").manual_seed(0))
    assert t.shape == (40, 50) and t.dtype == torch.float32
    assert set(t.unique().tolist()) == {-1.0, 1.0}
    # mean of 2000 fair signs: sd 1 / sqrt(2000) = 0.022, 5 sd = 0.11
    assert abs(float(t.mean())) < 0.11
    # drawn from the given generator (reproducible with the sampler's seed, not torch's global one)
    again = _rademacher(torch.zeros(40, 50), torch.Generator(device="cpu").manual_seed(0))
    assert torch.equal(t, again)


def test_repr_names_the_configuration():
    s = LossPixelSampler(resolution=(H, W), views=2, budget=7, refresh_every=5, levels=3, alpha=0.25, seed=9)
    assert repr(s) == "LossPixelSampler(budget=7, views=2, resolution=(16, 12), refresh_every=5, levels=3, alpha=0.25, seed=9)"


# ------------------------------------------------------------------- several processes
def _ranks(world: int, budget: int, **kw) -> list[AdaptivePixelSampler]:
    g = torch.Generator(device="cpu").manual_seed(21)
    p1, p2 = torch.rand(world, H, W, generator=g), torch.rand(world, H, W, generator=g)
    samplers = []
    for rank in range(world):
        s = _sampler(views=world, budget=budget, seed=5, **kw)
        s.update_from_maps(p1, p2)
        s.distribute(rank, world)
        samplers.append(s)
    return samplers


def test_distribute_checks_rank_world_and_budget():
    s = _sampler(budget=3)
    with pytest.raises(ValueError, match=r"^world must be an int >= 1, got 0$"):
        s.distribute(0, 0)
    with pytest.raises(ValueError, match=r"^rank must be an int in \[0, 2\), got 2$"):
        s.distribute(2, 2)
    with pytest.raises(ValueError, match=r"^rank must be an int in \[0, 2\), got True$"):
        s.distribute(True, 2)
    with pytest.raises(ValueError, match=r"^budget 3 is smaller than the 4 processes: every process needs at least one pixel draw$"):
        s.distribute(0, 4)
    assert (s.rank, s.world, s.share) == (0, 1, 3)  # a refused call changes nothing
    s.distribute(2, 3)
    assert (s.rank, s.world, s.share) == (2, 3, 1)


@pytest.mark.parametrize("budget", [3, 7, 64])
def test_processes_share_the_budget(budget):
    samplers = _ranks(3, budget)
    shares = [s.share for s in samplers]
    assert sum(shares) == budget and max(shares) - min(shares) <= 1 and shares == sorted(shares, reverse=True)
    for rank, s in enumerate(samplers):
        batch = s.sample([rank])
        assert batch.index.numel() == shares[rank]
        assert bool(((batch.index // (H * W)) == rank).all())  # only this process's view


def test_processes_draw_their_own_pixels_and_resume_their_stream():
    """Each process has its own draws (one process's pixel layout is not repeated in the other
    views), a single process keeps the sampler's generator, and a resumed process continues."""
    a, b = _ranks(2, 64)
    first_a, first_b = a.sample([0]), b.sample([1])
    assert not torch.equal(first_a.index, first_b.index - H * W)
    again = _ranks(2, 64)[0]
    assert torch.equal(again.sample([0]).index, first_a.index)  # a function of (seed, rank, call)
    state = a.state_dict()
    following = a.sample([0])
    resumed = _ranks(2, 64)[0]
    resumed.load_state_dict(state)
    assert resumed.draw_calls == 1 and torch.equal(resumed.sample([0]).index, following.index)
    single = _sampler(views=2, budget=64, seed=5)
    reference = _sampler(views=2, budget=64, seed=5)
    single.distribute(0, 1)
    assert torch.equal(single.sample().index, reference.sample().index)  # one process: unchanged


def test_averaged_process_estimates_are_unbiased_for_the_mean_over_all_views():
    """What DDP computes: the mean over processes of each one's weighted sum over its views."""
    g = torch.Generator(device="cpu").manual_seed(12)
    losses = torch.rand(2 * H * W, generator=g, dtype=torch.float64) ** 4
    samplers = _ranks(2, 33)  # 17 + 16 draws
    est = []
    for _ in range(3000):
        per_process = []
        for rank, s in enumerate(samplers):
            batch = s.sample([rank])
            per_process.append(float((batch.weight.double() * losses[batch.index]).sum()))
        est.append(sum(per_process) / 2)
    est = torch.tensor(est, dtype=torch.float64)
    se = float(est.std()) / math.sqrt(est.numel())
    assert abs(float(est.mean()) - float(losses.mean())) < 4 * se


def test_stage1_of_a_distributed_sampler_needs_torch_distributed():
    s = _sampler(budget=4)
    s.scene = object()  # never reached: the check comes before any render
    s.distribute(1, 2)
    with pytest.raises(RuntimeError, match=r"^a sampler distributed over several processes needs torch.distributed initialised \(DDP\)$"):
        s.update({}, torch.zeros(1, 3, H, W))
