"""LOI loss (paper 003), its blur and the multi-scale baselines (spec loi-loss.md, section 6.1)."""
from __future__ import annotations

import warnings

import pytest
import torch

from torchir.modules import (
    LOSSES,
    GaussianPyramidLoss,
    LOILoss,
    MultiScaleL1Loss,
    MultiScaleL2Loss,
    gaussian_pyramid_loss,
    loi_loss,
    multiscale_l1_loss,
    multiscale_l2_loss,
)
from torchir.modules._blur import MIN_SCALE, blur, blur_adjoint, cell_means, gaussian_matrix

from tests.helpers import DEVICE, assert_warned_at

D64 = torch.float64


def _rand(*shape, seed=0, lo=0.0, hi=1.0, dtype=torch.float32):
    g = torch.Generator(device=DEVICE).manual_seed(seed)
    return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=dtype)


def _disk(cx: torch.Tensor, n: int = 64, r: float = 4.0, value: float = 0.8, cy: float | None = None) -> torch.Tensor:
    """(1, 1, n, n) anti-aliased grey disk at (cx, cy), differentiable in cx."""
    cy = n / 2 if cy is None else cy
    yy, xx = torch.meshgrid(torch.arange(n, dtype=D64) + 0.5, torch.arange(n, dtype=D64) + 0.5, indexing="ij")
    d = ((xx - cx) ** 2 + (yy - cy) ** 2).sqrt()
    return (value * torch.sigmoid((r - d) * 4.0)).view(1, 1, n, n)


def _assert_warned_here(record) -> None:
    assert_warned_at(record, __file__)


# ------------------------------------------------------------------------------------ blur
def test_blur_matrix_rows_sum_to_one_and_handle_huge_kernels():
    for n, s in [(1, 3.0), (7, 0.5), (32, 45.0), (5, 1000.0)]:
        m = gaussian_matrix(n, s, dtype=D64)
        assert m.shape == (n, n)
        assert torch.allclose(m.sum(1), torch.ones(n, dtype=D64), atol=1e-12)
    x = _rand(2, 3, 32, 20)
    y = blur(x, 45.0)  # kornia's reflect padding raises here (radius >= image size)
    assert y.shape == x.shape and torch.isfinite(y).all()
    assert torch.equal(blur(x, 0.0), x)


def test_blur_matches_kornia_in_the_interior():
    kornia = pytest.importorskip("kornia")
    x = _rand(1, 2, 48, 48, dtype=D64)
    ours = blur(x, 2.0)
    ref = kornia.filters.gaussian_blur2d(x, (13, 13), (2.0, 2.0), border_type="reflect")
    assert torch.allclose(ours[..., 8:-8, 8:-8], ref[..., 8:-8, 8:-8], atol=1e-6)


def test_blur_adjoint_is_the_transpose():
    x, g = _rand(1, 1, 9, 6, dtype=D64), _rand(1, 1, 9, 6, seed=1, dtype=D64)
    assert torch.allclose((blur(x, 2.0) * g).sum(), (x * blur_adjoint(g, 2.0)).sum(), rtol=1e-12)


def test_blur_matrix_defaults_identity_and_device():
    """The documented defaults: ``truncate=3`` (zero beyond ``ceil(3 sigma)``), float32 on the
    CPU; ``sigma < MIN_SCALE`` is the exact identity in the requested dtype; the matrices are
    built on the requested device (``meta`` stands in for a second device)."""
    m = gaussian_matrix(12, 1.0)
    assert m.dtype == torch.float32 and m.device == torch.device("cpu")
    assert (m[0, :4] > 0).all() and (m[0, 4:] == 0).all()  # radius ceil(3 * 1) = 3
    for dtype in (torch.float32, D64):
        eye = gaussian_matrix(5, MIN_SCALE / 2, dtype=dtype)
        assert eye.dtype == dtype and torch.equal(eye, torch.eye(5, dtype=dtype, device="cpu"))
    for sigma in (0.0, 1.0):
        assert gaussian_matrix(5, sigma, dtype=D64, device="meta").device.type == "meta"


def test_cell_means_are_cell_averages_of_the_blur_rows():
    """``R`` row ``c`` is the mean of :func:`gaussian_matrix`'s rows in cell ``c`` (the last cell
    short), ``P`` the 0/1 membership; defaults ``truncate=3``, float32, CPU; any device."""
    n, s, cell = 12, 1.0, 5
    g = gaussian_matrix(n, s, 3.0, dtype=D64)
    expected = torch.stack([g[0:5].mean(0), g[5:10].mean(0), g[10:12].mean(0)])
    membership = torch.zeros(3, n, device="cpu")  # cell_means builds on the CPU by default
    membership[0, :5], membership[1, 5:10], membership[2, 10:] = 1, 1, 1
    r, p = cell_means(n, s, cell)
    assert r.dtype == p.dtype == torch.float32 and r.device == p.device == torch.device("cpu")
    torch.testing.assert_close(r.double(), expected, rtol=0, atol=1e-7)
    assert torch.equal(p, membership)
    assert all(t.device.type == "meta" for t in cell_means(n, s, cell, device="meta"))


# ---------------------------------------------------------------------- histograms (6.1.1, .10)
@pytest.mark.parametrize("sigma", [0, 1, 5, 45])
@pytest.mark.parametrize("alpha", [0, 1, 5, 45])
def test_histograms_sum_to_one_everywhere(sigma, alpha):
    img = _rand(1, 3, 32, 32, lo=-0.5, hi=1.5)
    img[0, 0, :4] = 50.0  # far outside the range, on the border rows
    h = LOILoss().histograms(img, sigma, alpha)
    assert h.shape == (1, 3, 16, 32, 32)  # K + 1 = (8 + 2*3 + 1) + 1 bins
    assert (h >= -1e-6).all()
    assert torch.allclose(h.sum(2), torch.ones(1, 3, 32, 32), atol=1e-5)


def test_cdfs_shape_and_monotone():
    c = LOILoss(beta=0.25, border="renormalize").cdfs(_rand(2, 1, 5, 7), 1, 2)
    assert c.shape == (2, 1, 4 + 6 + 1, 5, 7)
    assert (c.diff(dim=2) >= -1e-7).all()


# ------------------------------------------------------------------------- values (6.1.2-5)
def test_identity_and_symmetry():
    x, y = _rand(2, 3, 24, 20), _rand(2, 3, 24, 20, seed=1)
    xg = x.clone().requires_grad_()
    loss = loi_loss(xg, x)
    loss.backward()
    assert loss.item() == 0.0 and torch.count_nonzero(xg.grad) == 0
    assert torch.allclose(loi_loss(x, y), loi_loss(y, x), rtol=1e-6)


@pytest.mark.parametrize(("a", "b"), [(0.2, 0.5), (0.0, 0.05), (0.9, 0.1), (1.0, 0.0)])
def test_constant_images_give_n_terms_times_difference(a, b):
    loss = LOILoss(border="renormalize")
    x, y = torch.full((1, 3, 12, 17), a), torch.full((1, 3, 12, 17), b)
    assert loss.n_terms == 8
    assert loss(x, y).item() == pytest.approx(8 * abs(a - b), rel=1e-4, abs=1e-6)


@pytest.mark.parametrize("offset", [0.1, 0.45, 0.8])
@pytest.mark.parametrize("d", [0.01, 0.05, 0.15])
def test_shift_invariance_of_constant_images(offset, d):
    x, y = torch.full((1, 1, 8, 8), offset, dtype=D64), torch.full((1, 1, 8, 8), offset + d, dtype=D64)
    assert loi_loss(x, y, alphas=(3,), sigmas=(1,), border="renormalize").item() == pytest.approx(d, abs=1e-6)


@pytest.mark.parametrize("sigma", [0, 1, 5])
def test_alpha_zero_is_multiscale_l1(sigma):
    x, y = _rand(2, 3, 20, 17, lo=0.1, hi=0.9, dtype=D64), _rand(2, 3, 20, 17, seed=1, lo=0.1, hi=0.9, dtype=D64)
    oracle = (blur(x, sigma) - blur(y, sigma)).abs().mean()
    got = loi_loss(x, y, alphas=(0,), sigmas=(sigma,), border="renormalize")
    assert got.item() == pytest.approx(oracle.item(), rel=1e-4)
    assert multiscale_l1_loss(x, y, sigmas=(sigma,)).item() == pytest.approx(oracle.item(), rel=1e-12)


def test_paper_literal_tail_zero():
    x, y = _rand(1, 2, 12, 12, lo=0.2, hi=0.8), _rand(1, 2, 12, 12, seed=1, lo=0.2, hi=0.8)
    tailed, literal = loi_loss(x, y, tail=3, border="renormalize"), loi_loss(x, y, tail=0, border="renormalize")
    assert literal.item() == pytest.approx(tailed.item(), rel=0.01)
    edge = loi_loss(torch.zeros(1, 1, 4, 4), torch.full((1, 1, 4, 4), 0.05), alphas=(0,), sigmas=(0,), tail=0)
    assert edge.item() < 0.045  # under-counts near the ends of the range (spec 6.1.13)


@pytest.mark.parametrize(
    ("h", "w", "alphas", "value_range"),
    [(24, 20, (0, 1, 2, 6), (0.0, 1.0)), (20, 24, (0, 1), (-0.5, 1.5))],
)
def test_pad_border_crop_is_exact(h, w, alphas, value_range):
    """border="pad" evaluates small-alpha terms on a cropped canvas: it must equal the plain
    renormalised loss on explicitly padded images (padded with ``lo``, rescaled to the unpadded
    pixel count), tall or wide, whether some term needs the whole canvas or none does."""
    m = 12  # pad_frac 0.5 * max(H, W)
    x = _rand(1, 2, h, w, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 2, h, w, seed=1, lo=0.05, hi=0.95, dtype=D64)
    opts = dict(alphas=alphas, sigmas=(0, 1), beta=0.25, value_range=value_range)
    got = loi_loss(x, y, border="pad", pad_frac=0.5, **opts)
    pad = lambda t: torch.nn.functional.pad(t, (m, m, m, m), value=value_range[0])  # noqa: E731
    ref = loi_loss(pad(x), pad(y), border="renormalize", **opts) * ((h + 2 * m) * (w + 2 * m) / (h * w))
    assert got.item() == pytest.approx(ref.item(), rel=1e-12)
    (g_got,) = torch.autograd.grad(got, x)
    (g_ref,) = torch.autograd.grad(ref, x)
    assert torch.allclose(g_got, g_ref, rtol=1e-10, atol=1e-14)
    # terms() crops every term, weighted or not, on its own canvas
    terms = LOILoss(border="pad", pad_frac=0.5, weights=[[1.0] * (len(alphas) - 1) + [0.0]] * 2, **opts).terms(x, y)
    assert sum(terms.values()).item() == pytest.approx(got.item(), rel=1e-12)


def test_cell_fraction_is_exact_on_constants_and_close_on_a_disk():
    x, y = torch.full((1, 3, 30, 26), 0.3), torch.full((1, 3, 30, 26), 0.7)
    cells = LOILoss(cell_fraction=1.0, border="renormalize")
    assert cells(x, y).item() == pytest.approx(8 * 0.4, rel=1e-4)  # a constant field has exact cell means
    target = _disk(torch.tensor(20.0, dtype=D64))
    cx = torch.tensor(36.0, dtype=D64, requires_grad=True)
    exact = loi_loss(_disk(cx), target, exact=True)
    (g_exact,) = torch.autograd.grad(exact, cx)
    for fraction in (0.25, 0.5):
        approx = loi_loss(_disk(cx), target, cell_fraction=fraction)
        (g_approx,) = torch.autograd.grad(approx, cx)
        assert approx.item() == pytest.approx(exact.item(), rel=0.02)
        assert g_approx.item() == pytest.approx(g_exact.item(), rel=0.05)  # same direction and size
    assert loi_loss(_disk(cx), target, cell_fraction=0.0).item() == exact.item()


def test_cell_fraction_gradcheck_float64():
    x = _rand(1, 1, 14, 11, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 1, 14, 11, seed=1, lo=0.05, hi=0.95, dtype=D64)
    mask = _rand(1, 1, 14, 11, seed=2, dtype=D64) + 0.1
    for low_memory in (False, True):
        f = lambda t: loi_loss(t, y, alphas=(1, 3), sigmas=(0, 1), beta=0.25, cell_fraction=1.0, low_memory=low_memory, mask=mask)  # noqa: E731
        assert torch.autograd.gradcheck(f, (x,))


# --------------------------------------------------------------- gradients (6.1.6-8)
def test_displaced_disk_l2_flat_loi_points_to_target():
    target = _disk(torch.tensor(20.0, dtype=D64))
    cx = torch.tensor(36.0, dtype=D64, requires_grad=True)  # 16 px away: no overlap
    (g_l2,) = torch.autograd.grad((_disk(cx) - target).square().mean(), cx)
    (g_loi,) = torch.autograd.grad(loi_loss(_disk(cx), target), cx)
    assert abs(g_l2.item()) < 1e-6
    assert g_loi.item() > 1e-4  # positive: decreasing cx (towards 20) lowers the loss


@pytest.mark.parametrize("exact, offset", [(True, 0.0), (False, 0.3)])
def test_displaced_disk_sweep_sign_monotone_and_finite_differences(exact, offset):
    # the default (cells for alpha 15 and 45) has kinks where a cell sits on the disk's symmetry
    # axis (measured at x = 34: a 0.27 % one-sided difference at every h), so it is swept off
    # integer positions; there its gradient equals central differences like the exact loss's
    n, tx = 96, 20.0
    target = _disk(torch.tensor(tx, dtype=D64), n=n)
    loss_fn = LOILoss(exact=exact)
    values = []
    for start in range(22, 77, 6):
        cx = torch.tensor(start + offset, dtype=D64, requires_grad=True)
        loss = loss_fn(_disk(cx, n=n), target)
        (g,) = torch.autograd.grad(loss, cx)
        assert g.item() > 0, f"wrong sign at x={start}"
        values.append(loss.item())
        h = 1e-3
        with torch.no_grad():
            fd = (loss_fn(_disk(cx + h, n=n), target) - loss_fn(_disk(cx - h, n=n), target)) / (2 * h)
        assert g.item() == pytest.approx(fd.item(), rel=1e-3)
    assert all(a < b for a, b in zip(values, values[1:])), "loss must grow with the distance"
    assert loss_fn.cache_hits >= len(values)  # the fixed target was processed once


@pytest.mark.parametrize("low_memory", [False, True])
@pytest.mark.parametrize("border", ["renormalize", "pad"])
def test_gradcheck_float64(low_memory, border):
    x = _rand(1, 2, 8, 8, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 2, 8, 8, seed=1, lo=0.05, hi=0.95, dtype=D64)
    mask = _rand(1, 1, 8, 8, seed=2, dtype=D64) + 0.1
    f = lambda t: loi_loss(t, y, alphas=(0, 1, 3), sigmas=(0, 1), beta=0.25, border=border, low_memory=low_memory, mask=mask, reduction="none")  # noqa: E731
    assert torch.autograd.gradcheck(f, (x,))


@pytest.mark.parametrize("low_memory", [False, True])
def test_gradcheck_float64_with_uneven_term_weights(low_memory):
    """The hand-written backward scales each term by its weight: with uniform weights a
    backward that dropped them would still pass gradcheck, so these differ per term (one is
    zero, which drops the term from the fused forward)."""
    x = _rand(1, 2, 8, 8, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 2, 8, 8, seed=1, lo=0.05, hi=0.95, dtype=D64)
    weights = [[0.3, 2.5, 0.0], [1.7, 0.05, 4.0]]
    f = lambda t: loi_loss(t, y, alphas=(0, 1, 3), sigmas=(0, 1), beta=0.25, weights=weights, low_memory=low_memory, reduction="none")  # noqa: E731
    assert torch.autograd.gradcheck(f, (x,))


def test_term_weights_scale_value_and_gradient_per_term():
    """E8: the total is ``sum w(sigma, alpha) E(sigma, alpha)``; by linearity so is its
    gradient, each term's gradient taken alone (weight 1 on it, 0 elsewhere)."""
    x = _rand(1, 3, 12, 10, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 3, 12, 10, seed=1, lo=0.05, hi=0.95, dtype=D64)
    alphas, sigmas = (0, 2), (0, 1)
    weights = torch.tensor([[0.5, 3.0], [2.0, 0.25]], dtype=D64)
    m = LOILoss(alphas=alphas, sigmas=sigmas, weights=weights.tolist(), border="renormalize")
    total = m(x, y)
    (g_total,) = torch.autograd.grad(total, x)
    terms = m.terms(x.detach(), y)
    expected_value, expected_grad = 0.0, torch.zeros_like(x)
    for i, s in enumerate(sigmas):
        for j, a in enumerate(alphas):
            one = [[float(i == k and j == l) for l in range(len(alphas))] for k in range(len(sigmas))]
            value = loi_loss(x, y, alphas=alphas, sigmas=sigmas, weights=one, border="renormalize")
            assert value.item() == pytest.approx(terms[(float(s), float(a))].item(), rel=1e-12)
            expected_value += weights[i, j].item() * value.item()
            expected_grad += weights[i, j] * torch.autograd.grad(value, x)[0]
    assert total.item() == pytest.approx(expected_value, rel=1e-12)
    torch.testing.assert_close(g_total, expected_grad, rtol=1e-10, atol=1e-14)


def test_low_memory_matches_autograd_and_estimates_less_memory():
    x = _rand(2, 3, 16, 12, seed=3).requires_grad_()
    y = _rand(2, 3, 16, 12, seed=4)
    ref, lm = LOILoss(), LOILoss(low_memory=True)
    (g_ref,) = torch.autograd.grad(ref(x, y), x)
    v = lm(x, y)
    (g_lm,) = torch.autograd.grad(v, x)
    assert v.item() == pytest.approx(ref(x, y).item(), rel=1e-6)
    assert torch.allclose(g_ref, g_lm, rtol=1e-4, atol=1e-9)
    assert lm.memory_estimate((2, 3, 256, 256)) < ref.memory_estimate((2, 3, 256, 256))
    # estimate: 4 bytes * (2 + 4) * 2 sigmas * B C K Hp Wp (+ cached target) for the default
    assert ref.memory_estimate((1, 3, 64, 64)) == 4 * (6 * 2 + 2) * 3 * 15 * 96 * 96


# ----------------------------------------------------------------- batch, reduction, caching
def test_batch_and_reduction():
    x, y = _rand(2, 3, 10, 14), _rand(2, 3, 10, 14, seed=1)
    singles = torch.stack([loi_loss(x[i], y[i]) for i in range(2)])
    per = loi_loss(x, y, reduction="none")
    assert per.shape == (2,)
    assert torch.allclose(per, singles, rtol=1e-5)
    assert loi_loss(x, y).item() == pytest.approx(singles.mean().item(), rel=1e-5)
    assert loi_loss(x, y, reduction="sum").item() == pytest.approx(singles.sum().item(), rel=1e-5)


def test_module_equals_function_and_terms_sum_to_total():
    x, y = _rand(1, 3, 16, 16), _rand(1, 3, 16, 16, seed=1)
    m = LOILoss.preset("disks", border="renormalize")
    assert m.alphas == (1.0, 5.0, 15.0) and m.sigmas == (1.0, 5.0, 15.0, 45.0)
    total = m(x, y)
    assert total.item() == pytest.approx(loi_loss(x, y, alphas=(1, 5, 15), sigmas=(1, 5, 15, 45), border="renormalize").item(), rel=1e-6)
    terms = m.terms(x, y)
    assert set(terms) == {(s, a) for s in (1.0, 5.0, 15.0, 45.0) for a in (1.0, 5.0, 15.0)}
    assert sum(terms.values()).item() == pytest.approx(total.item(), rel=1e-5)
    assert "alphas=(1.0, 5.0, 15.0)" in repr(m)
    assert LOILoss.preset("raster").beta == 0.03125 and LOILoss.preset("pathtracing").alphas == (1, 5, 15, 45)
    with pytest.raises(ValueError, match="unknown LOI preset"):
        LOILoss.preset("nope")


def test_target_cache_hits_and_invalidation():
    x = _rand(1, 3, 12, 12).requires_grad_()
    y = _rand(1, 3, 12, 12, seed=1)
    cached, plain = LOILoss(), LOILoss(cache_target=False)
    v1 = cached(x, y)
    (g1,) = torch.autograd.grad(v1, x)
    v2 = cached(x, y)
    (g2,) = torch.autograd.grad(v2, x)
    assert cached.cache_hits == 1
    (g_plain,) = torch.autograd.grad(plain(x, y), x)
    assert v1.item() == v2.item() and torch.equal(g1, g2) and torch.allclose(g1, g_plain)
    cached(x, y.clone())  # equal content: still a hit
    assert cached.cache_hits == 2
    y.add_(0.1)  # in-place change: must recompute
    assert cached(x, y).item() == pytest.approx(plain(x, y).item(), rel=1e-6)
    assert cached.cache_hits == 2
    cached.set_scales(alphas=(0, 2))
    assert cached.n_terms == 4 and len(cached._cache) == 0


def test_relative_scales_follow_the_resolution():
    x, y = _rand(1, 1, 32, 40), _rand(1, 1, 32, 40, seed=1)
    rel = loi_loss(x, y, alphas=(0.25,), sigmas=(1 / 32,), relative=True)
    px = loi_loss(x, y, alphas=(8,), sigmas=(1,))
    assert rel.item() == pytest.approx(px.item(), rel=1e-6)


def test_float32_float64_agree_and_half_is_upcast():
    x, y = _rand(1, 3, 16, 16, dtype=D64), _rand(1, 3, 16, 16, seed=1, dtype=D64)
    v64 = loi_loss(x, y)
    assert v64.dtype == D64
    assert loi_loss(x.float(), y.float()).item() == pytest.approx(v64.item(), rel=1e-4)
    assert loi_loss(x.half(), y.half()).dtype == torch.float32
    # mixed: both are promoted to float64 before anything else
    mixed = loi_loss(x.float(), y)
    assert mixed.dtype == D64 and mixed.item() == pytest.approx(loi_loss(x.float().double(), y).item(), rel=1e-12)
    mixed = loi_loss(x, y.float())
    assert mixed.dtype == D64 and mixed.item() == pytest.approx(loi_loss(x, y.float().double()).item(), rel=1e-12)


def test_mask_weights_pixels():
    x, y = _rand(1, 1, 8, 8), _rand(1, 1, 8, 8, seed=1)
    mask = torch.zeros(1, 1, 8, 8)
    mask[..., :, :4] = 1
    y2 = y.clone()
    y2[..., :, 4:] = 0.0  # changes only masked-out pixels
    kw = dict(alphas=(0,), sigmas=(0,), border="renormalize")
    assert loi_loss(x, y, mask=mask, **kw).item() == pytest.approx(loi_loss(x, y2, mask=mask, **kw).item(), rel=1e-6)
    assert loi_loss(x, y, mask=torch.ones(1, 1, 8, 8)).item() == pytest.approx(loi_loss(x, y).item(), rel=1e-6)
    with pytest.raises(ValueError, match="zero everywhere"):
        loi_loss(x, y, mask=torch.zeros(1, 1, 8, 8))
    with pytest.raises(ValueError, match="mask must be"):
        loi_loss(x, y, mask=torch.ones(1, 1, 4, 4))


# ------------------------------------------------------------------------ extremes (6.1.9)
def test_extremes_are_finite():
    for x, y in [
        (torch.zeros(1, 3, 1, 1), torch.ones(1, 3, 1, 1)),  # 1x1
        (torch.zeros(1, 1, 3, 50), torch.full((1, 1, 3, 50), 0.5)),  # non-square, thin
        (torch.full((1, 3, 8, 8), 1e6), torch.zeros(1, 3, 8, 8)),  # fireflies
    ]:
        xg = x.clone().requires_grad_()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loss = loi_loss(xg, y, alphas=(0, 1, 100), sigmas=(0, 100))
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(xg.grad).all()
    # Known values. Constant images give n_terms * |a - b| (renormalised borders), however
    # small or thin; fireflies far beyond the range and its tail saturate: the loss no longer
    # depends on how far (1e6 and 50 give the same value) and the gradient is exactly zero.
    kw = dict(alphas=(0, 1, 100), sigmas=(0, 100), border="renormalize")
    assert loi_loss(torch.zeros(1, 3, 1, 1), torch.ones(1, 3, 1, 1), **kw).item() == pytest.approx(6.0, rel=1e-4)
    assert loi_loss(torch.zeros(1, 1, 3, 50), torch.full((1, 1, 3, 50), 0.5), **kw).item() == pytest.approx(3.0, rel=1e-4)
    values = []
    for v in (1e6, 50.0):
        xg = torch.full((1, 3, 8, 8), v, requires_grad=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loss = loi_loss(xg, torch.zeros(1, 3, 8, 8), **kw)
        loss.backward()
        assert torch.count_nonzero(xg.grad) == 0
        values.append(loss.item())
    assert values[0] == values[1] > 6 * 1.0  # beyond the whole range: more than a full-range step


def test_out_of_range_saturates_and_warns_once():
    kw = dict(border="renormalize", alphas=(0,), sigmas=(0,))
    in_range = loi_loss(torch.full((1, 1, 4, 4), 0.5), torch.full((1, 1, 4, 4), 1.0), **kw).item()
    m = LOILoss(**kw)
    with pytest.warns(UserWarning, match="beyond value_range"):
        far = m(torch.full((1, 1, 4, 4), 1.5), torch.full((1, 1, 4, 4), 2.0)).item()
    assert far < 0.1 * in_range
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m(torch.full((1, 1, 4, 4), 1.5), torch.full((1, 1, 4, 4), 2.0))  # once per module
        tm = loi_loss(torch.full((1, 1, 4, 4), 1.5), torch.full((1, 1, 4, 4), 2.0), transform="reinhard", **kw).item()
    assert tm == pytest.approx(2.0 / 3.0 - 1.5 / 2.5, rel=1e-3)  # Reinhard keeps HDR differences


@pytest.mark.parametrize("transform", ["identity", "clamp", "reinhard", "log1p", torch.sqrt])
def test_transforms(transform):
    x, y = _rand(1, 3, 8, 8, hi=3.0).requires_grad_(), _rand(1, 3, 8, 8, seed=1, hi=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loss = loi_loss(x, y, transform=transform)
    loss.backward()
    assert loss.item() > 0 and torch.isfinite(x.grad).all()
    # E0: the transform is applied to both images before anything else
    tau = {"identity": lambda t: t, "clamp": lambda t: t.clamp(0, 1), "reinhard": lambda t: t / (1 + t), "log1p": torch.log1p}.get(transform, transform)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = loi_loss(tau(x.detach()), tau(y), transform="identity")
    assert loss.item() == pytest.approx(plain.item(), rel=1e-5)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("which", ["rendered", "target"])
def test_non_finite_input_names_the_tensor(bad, which):
    x, y = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
    (x if which == "rendered" else y)[0, 0, 1, 1] = bad
    with pytest.raises(ValueError, match=f"{which} has 1 non-finite"):
        loi_loss(x, y)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        (dict(beta=0.0), ValueError, "beta must be > 0"),
        (dict(beta=-1.0), ValueError, "beta must be > 0"),
        (dict(alphas=(1, -2)), ValueError, "alphas must be finite and >= 0"),
        (dict(sigmas=()), ValueError, "sigmas must not be empty"),
        (dict(reduction="avg"), ValueError, "reduction must be one of"),
        (dict(border="reflect"), ValueError, "border must be one of"),
        (dict(transform="gamma"), ValueError, "transform must be one of"),
        (dict(value_range=(1, 0)), ValueError, "value_range"),
        (dict(tail=-1), ValueError, "tail must be"),
        (dict(weights=[[1, 2]]), ValueError, "weights must have shape"),
        (dict(channels="rgb"), ValueError, "channels must be one of"),
        (dict(cell_fraction=1.5), ValueError, "cell_fraction must be in"),
        (dict(cell_fraction=True), ValueError, "cell_fraction must be in"),
        (dict(exact=True, cell_fraction=0.5), ValueError, r"^exact=True evaluates every pixel: cell_fraction must be 0 or None, got 0.5$"),
        (dict(exact=1), TypeError, r"^exact must be a bool, got 1$"),
        (dict(alphas=None), TypeError, r"^alphas must be a sequence of numbers, got None$"),
        (dict(sigmas=(1, -2)), ValueError, r"^sigmas must be finite and >= 0, got \(1.0, -2.0\)$"),
        (dict(weights=[[1, -2]], alphas=(1, 2), sigmas=(1,)), ValueError, "^weights must be finite and >= 0$"),
        (dict(weights=[[1, float("nan")]], alphas=(1, 2), sigmas=(1,)), ValueError, "^weights must be finite and >= 0$"),
        (dict(value_range=(0.5, 0.5)), ValueError, r"^value_range must be finite \(lo, hi\) with lo < hi, got \(0.5, 0.5\)$"),
        (dict(tail=True), ValueError, "^tail must be an int >= 0, got True$"),
        (dict(tail=2.0), ValueError, "^tail must be an int >= 0, got 2.0$"),
        (dict(transform=42), TypeError, "^transform must be a name or a callable, got int$"),
        (dict(pad_frac=4.5), ValueError, r"^pad_frac must be in \[0, 4\], got 4.5$"),
        (dict(pad_frac=-0.1), ValueError, r"^pad_frac must be in \[0, 4\], got -0.1$"),
        (dict(truncate=0), ValueError, "^truncate must be > 0, got 0$"),
        (dict(cache_target=-1), ValueError, "^cache_target must be a bool or an int >= 0, got -1$"),
        (dict(cache_target="2"), ValueError, "^cache_target must be a bool or an int >= 0, got '2'$"),
    ],
)
def test_bad_options(kwargs, error, match):
    with pytest.raises(error, match=match):
        LOILoss(**kwargs)


def test_option_boundaries_are_accepted():
    """The closed ends of each range are valid; scales below MIN_SCALE px are 0; the weights
    keep their float64 values; beta = 1/128 is not yet "small"."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = LOILoss(alphas=(MIN_SCALE / 10, MIN_SCALE, 1), sigmas=(0,), pad_frac=4, truncate=0.5, beta=1 / 128, weights=[[0.1, 0.2, 0.3]])
    assert m.alphas == (0.0, MIN_SCALE, 1.0) and m.pad_frac == 4.0 and m.truncate == 0.5
    assert m.weights == ((0.1, 0.2, 0.3),)
    x, y = _rand(1, 1, 6, 6), _rand(1, 1, 6, 6, seed=1)
    assert loi_loss(x, y, pad_frac=0).item() == pytest.approx(loi_loss(x, y, border="renormalize").item(), rel=1e-6)
    assert LOILoss(cache_target=0).cache_size == 0 and LOILoss(cache_target=True).cache_size == 1


@pytest.mark.parametrize(("beta", "value_range", "tail"), [(1.0, (0.0, 1.0), 0), (0.75, (0.0, 1.0), 2), (0.1, (0.5, 1.5), 1), (0.125, (0.5, 1.0), 3)])
def test_bin_edges_span_the_range(beta, value_range, tail):
    """E3: ``K = N + 2T + 1`` edges ``lo + j beta``, ``N = max(1, round((hi - lo) / beta))``:
    a point mass at ``v`` has local CDF ``Phi((e_j - v) / beta)`` at each edge."""
    lo, hi = value_range
    n = max(1, round((hi - lo) / beta))
    edges = lo + torch.arange(-tail, n + tail + 1, dtype=D64) * beta
    v = torch.full((1, 1, 3, 3), 0.6, dtype=D64)
    c = LOILoss(beta=beta, value_range=value_range, tail=tail).cdfs(v, 0, 0)
    assert c.shape == (1, 1, n + 2 * tail + 1, 3, 3)
    torch.testing.assert_close(c[0, 0, :, 1, 1], torch.special.ndtr((edges - 0.6) / beta), rtol=1e-14, atol=1e-15)


def test_small_beta_warns_from_both_twins():
    for make in (lambda: LOILoss(beta=0.001), lambda: loi_loss(torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2, 2), beta=0.001)):
        with pytest.warns(UserWarning, match=r"^beta=0.001 < 1/128: many bins"):
            make()


def test_unknown_attribute_is_the_modules_error():
    with pytest.raises(AttributeError, match="^'LOILoss' object has no attribute 'nope'$"):
        LOILoss().nope


def test_bad_images():
    x = torch.rand(1, 3, 8, 8)
    with pytest.raises(ValueError, match="shapes differ"):
        loi_loss(x, torch.rand(1, 3, 8, 9))
    with pytest.raises(ValueError, match=r"Mitsuba's \(H, W, C\) layout"):
        loi_loss(torch.rand(16, 16, 3), torch.rand(16, 16, 3))
    with pytest.raises(ValueError, match=r"Mitsuba's \(H, W, C\) layout"):
        loi_loss(torch.rand(2, 16, 16, 4), torch.rand(2, 16, 16, 4))
    with pytest.raises(ValueError, match=r"\(C, H, W\) or \(B, C, H, W\)"):
        loi_loss(torch.rand(8, 8), torch.rand(8, 8))
    with pytest.raises(TypeError, match="floating-point"):
        loi_loss(torch.ones(1, 3, 8, 8, dtype=torch.uint8), torch.ones(1, 3, 8, 8, dtype=torch.uint8))
    with pytest.raises(TypeError, match="^rendered must be a torch.Tensor, got ndarray$"):
        loi_loss(x.cpu().numpy(), x)
    with pytest.raises(ValueError, match=r"^rendered is empty \(shape \(1, 3, 0, 4\)\)$"):
        loi_loss(torch.rand(1, 3, 0, 4), torch.rand(1, 3, 0, 4))
    with pytest.raises(ValueError, match=r"^rendered has shape \(5, 8, 3\), which looks like Mitsuba's"):
        loi_loss(torch.rand(5, 8, 3), torch.rand(5, 8, 3))
    # a 4-channel image 3 pixels wide and a single pixel are images, not layouts or empties
    assert loi_loss(torch.rand(4, 8, 3), torch.rand(4, 8, 3), reduction="none").shape == (1,)
    assert loi_loss(torch.zeros(1, 1, 1), torch.ones(1, 1, 1), alphas=(0,), sigmas=(0,)).item() > 0
    with pytest.warns(UserWarning, match="beta=0.001"):
        LOILoss(beta=0.001)


def test_luminance_channels():
    x, y = _rand(1, 3, 8, 8), _rand(1, 3, 8, 8, seed=1)
    lum = lambda t: (t * torch.tensor([0.2126, 0.7152, 0.0722]).view(1, 3, 1, 1)).sum(1, keepdim=True)  # noqa: E731, Rec. 709
    assert loi_loss(x, y, channels="luminance").item() == pytest.approx(loi_loss(lum(x), lum(y)).item(), rel=1e-5)
    with pytest.raises(ValueError, match="needs 3 channels, got 2$"):
        loi_loss(x[:, :2], y[:, :2], channels="luminance")


# ------------------------------------------------------------------------------ baselines
def test_baselines_registry_and_values():
    assert LOSSES["loi"] is LOILoss and LOSSES["gp"] is GaussianPyramidLoss
    assert LOSSES["multiscale_l1"] is MultiScaleL1Loss and LOSSES["multiscale_l2"] is MultiScaleL2Loss
    for cls in (LOILoss, GaussianPyramidLoss, MultiScaleL1Loss, MultiScaleL2Loss):
        assert cls.pixelwise is False
    x, y = _rand(2, 3, 16, 12, dtype=D64), _rand(2, 3, 16, 12, seed=1, dtype=D64)
    assert multiscale_l2_loss(x, y, sigmas=(0, 2)).item() == pytest.approx(
        ((x - y).square().mean() + (blur(x, 2) - blur(y, 2)).square().mean()).item(), rel=1e-12
    )
    # pyramid: level 1 is the sigma=1 blur subsampled by 2
    l1 = (blur(x, 1.0)[..., ::2, ::2] - blur(y, 1.0)[..., ::2, ::2]).square().mean()
    assert gaussian_pyramid_loss(x, y, levels=2).item() == pytest.approx(((x - y).square().mean() + l1).item(), rel=1e-12)
    assert GaussianPyramidLoss(reduction="none")(x, y).shape == (2,)
    assert GaussianPyramidLoss()(torch.zeros(1, 3, 1, 1), torch.ones(1, 3, 1, 1)).item() == pytest.approx(1.0)
    xg = x.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: gaussian_pyramid_loss(t, y, levels=3) + multiscale_l1_loss(t, y, sigmas=(1,)), (xg,))
    with pytest.raises(ValueError, match="p must be 1 or 2"):
        GaussianPyramidLoss(p=3)
    with pytest.raises(ValueError, match="non-finite"):
        MultiScaleL2Loss()(x, torch.full_like(x, float("nan")))


def _pyramid_oracle(x, y, levels, p=2, sigma=1.0):
    """Sum over levels of mean |x_l - y_l|^p, level l + 1 = level l blurred by sigma and
    subsampled by 2, stopping once a side is below 2 px."""
    total = 0.0
    for level in range(levels):
        if level:
            if min(x.shape[-2:]) < 2:
                break
            x, y = blur(x, sigma)[..., ::2, ::2], blur(y, sigma)[..., ::2, ::2]
        total = total + (x - y).abs().pow(p).flatten(1).mean(1)
    return total


def test_pyramid_levels_default_depth_and_tiny_images():
    """``levels=None`` goes down to ~4 px: ``1 + floor(log2(min(H, W) // 4))`` levels (1 below
    8 px); a level is added while both sides are >= 2 px (a 2 px side still halves), so asking
    for more levels than fit gives the deepest pyramid; p=1 sums mean absolute differences."""
    for shape, levels in [((1, 3, 32, 48), 4), ((1, 3, 16, 12), 2), ((1, 3, 7, 9), 1), ((1, 1, 9, 8), 2)]:
        x, y = _rand(*shape, dtype=D64), _rand(*shape, seed=1, dtype=D64)
        assert gaussian_pyramid_loss(x, y).item() == pytest.approx(_pyramid_oracle(x, y, levels).item(), rel=1e-12), shape
        assert gaussian_pyramid_loss(x, y).item() != pytest.approx(_pyramid_oracle(x, y, levels + 1).item(), rel=1e-6), shape
    x, y = _rand(2, 1, 2, 5, dtype=D64), _rand(2, 1, 2, 5, seed=1, dtype=D64)  # 2 -> 1 px, then stop
    deepest = gaussian_pyramid_loss(x, y, levels=10, reduction="none")
    torch.testing.assert_close(deepest, _pyramid_oracle(x, y, 2), rtol=1e-12, atol=0)
    assert deepest[0].item() != pytest.approx((x - y)[0].square().mean().item(), rel=1e-6)
    x, y = _rand(1, 1, 8, 8, dtype=D64), _rand(1, 1, 8, 8, seed=1, dtype=D64)  # one channel: not a "side"
    assert gaussian_pyramid_loss(x, y, levels=2, p=1).item() == pytest.approx(_pyramid_oracle(x, y, 2, p=1).item(), rel=1e-12)
    assert GaussianPyramidLoss(levels=1, p=1)(x, y).item() == pytest.approx((x - y).abs().mean().item(), rel=1e-12)


def test_baseline_transforms_reductions_and_module_twins():
    """The transform is applied to both images first (``"clamp"``: to [0, 1]); ``"sum"`` sums
    the per-item values; mixed dtypes are promoted before the blurs; the modules equal their
    functions, defaults included (pyramid sigma 1, truncate 3)."""
    x, y = _rand(2, 3, 12, 10, lo=-0.5, hi=2.0, dtype=D64), _rand(2, 3, 12, 10, seed=1, lo=-0.5, hi=2.0, dtype=D64)
    tau = {"identity": lambda t: t, "clamp": lambda t: t.clamp(0, 1), "reinhard": lambda t: t / (1 + t.abs()), torch.sqrt: lambda t: t.sqrt()}
    for transform, f in tau.items():
        a, b = (x.abs(), y.abs()) if transform is torch.sqrt else (x, y)
        for fn, module in [(gaussian_pyramid_loss, GaussianPyramidLoss), (multiscale_l1_loss, MultiScaleL1Loss), (multiscale_l2_loss, MultiScaleL2Loss)]:
            plain = fn(f(a), f(b)).item()
            assert fn(a, b, transform=transform).item() == pytest.approx(plain, rel=1e-12), (fn, transform)
            assert module(transform=transform)(a, b).item() == pytest.approx(plain, rel=1e-12), (module, transform)
    assert gaussian_pyramid_loss(x, y, transform="clamp").item() != pytest.approx(gaussian_pyramid_loss(x, y).item(), rel=1e-6)
    kw = dict(sigmas=(0, 1), truncate=1.0)
    for fn, module, p in [(multiscale_l1_loss, MultiScaleL1Loss, 1), (multiscale_l2_loss, MultiScaleL2Loss, 2)]:
        per = fn(x, y, reduction="none", **kw)
        oracle = sum((blur(x, s, 1.0) - blur(y, s, 1.0)).abs().pow(p).flatten(1).mean(1) for s in (0, 1))
        torch.testing.assert_close(per, oracle, rtol=1e-12, atol=0)
        assert fn(x, y, reduction="sum", **kw).item() == pytest.approx(per.sum().item(), rel=1e-12)
        assert module(reduction="sum", **kw)(x, y).item() == pytest.approx(per.sum().item(), rel=1e-12)
        assert module()(x, y).item() == pytest.approx(fn(x, y, truncate=3.0).item(), rel=1e-12)
        assert module()(x, y).item() != pytest.approx(fn(x, y, truncate=4.0).item(), rel=1e-6)
    per = gaussian_pyramid_loss(x, y, levels=2, reduction="none")
    assert gaussian_pyramid_loss(x, y, levels=2, reduction="sum").item() == pytest.approx(per.sum().item(), rel=1e-12)
    assert GaussianPyramidLoss(levels=2, reduction="sum")(x, y).item() == pytest.approx(per.sum().item(), rel=1e-12)
    assert GaussianPyramidLoss(levels=2)(x, y).item() == pytest.approx(_pyramid_oracle(x, y, 2).mean().item(), rel=1e-12)
    assert GaussianPyramidLoss()(x, y).item() == pytest.approx(gaussian_pyramid_loss(x, y, sigma=1.0).item(), rel=1e-12)
    assert GaussianPyramidLoss(sigma=2.0)(x, y).item() != pytest.approx(GaussianPyramidLoss()(x, y).item(), rel=1e-6)
    for fn in (gaussian_pyramid_loss, multiscale_l1_loss, multiscale_l2_loss):
        for a, b in ((x.float(), y), (x, y.float())):  # both promoted to float64 before anything else
            mixed = fn(a, b)
            assert mixed.dtype == D64 and mixed.item() == pytest.approx(fn(a.double(), b.double()).item(), rel=1e-12)


def test_baseline_argument_errors():
    x = _rand(1, 3, 8, 8)
    cases = [
        (lambda: gaussian_pyramid_loss(x, x, reduction="avg"), ValueError, r"^reduction must be one of \('mean', 'sum', 'none'\), got 'avg'$"),
        (lambda: multiscale_l1_loss(x, x[..., :7]), ValueError, r"^rendered and target shapes differ: \(1, 3, 8, 8\) vs \(1, 3, 8, 7\)$"),
        (lambda: multiscale_l2_loss(x.cpu().numpy(), x), TypeError, "^rendered must be a torch.Tensor, got ndarray$"),
        (lambda: gaussian_pyramid_loss(x, x.cpu().numpy()), TypeError, "^target must be a torch.Tensor, got ndarray$"),
        (lambda: gaussian_pyramid_loss(x, x, transform="gamma"), ValueError, r"^transform must be one of \['clamp', 'identity', 'log1p', 'reinhard'\] or a callable, got 'gamma'$"),
        (lambda: gaussian_pyramid_loss(x, x, levels=0), ValueError, "^levels must be an int >= 1, got 0$"),
        (lambda: gaussian_pyramid_loss(x, x, levels=True), ValueError, "^levels must be an int >= 1, got True$"),
        (lambda: gaussian_pyramid_loss(x, x, levels=2.0), ValueError, r"^levels must be an int >= 1, got 2.0$"),
        (lambda: gaussian_pyramid_loss(x, x, p=1.5), ValueError, "^p must be 1 or 2, got 1.5$"),
        (lambda: multiscale_l1_loss(x, x, sigmas=(1, -1)), ValueError, r"^sigmas must be finite and >= 0, got \(1.0, -1.0\)$"),
        (lambda: MultiScaleL2Loss(sigmas=(-1,)), ValueError, r"^sigmas must be finite and >= 0, got \(-1.0,\)$"),
    ]
    for call, error, match in cases:
        with pytest.raises(error, match=match):
            call()


# ---------------------------------------------------------------------- Mitsuba smoke (6.1.14)
def test_mitsuba_smoke_loi_backward_through_render(cbox, red):
    from torchir.functions import render

    with torch.no_grad():
        target = render(cbox, {"red.reflectance.value": torch.tensor([0.1, 0.7, 0.2])}, spp=4, seed=10)
    img = render(cbox, {"red.reflectance.value": red}, spp=4, seed=1)
    loss = LOILoss(transform="reinhard")(img, target)
    loss.backward()
    # The target wall is less red and much greener and bluer than the current one: descending
    # the gradient must lower R and raise G and B.
    assert torch.isfinite(red.grad).all()
    assert red.grad[0] > 0 and red.grad[1] < 0 and red.grad[2] < 0, red.grad
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        LOILoss()(img.permute(1, 2, 0), target.permute(1, 2, 0))


# ------------------------------------------------------------------- options and inspection
def _saved_per_sigma(loss: torch.Tensor) -> list[int]:
    """How many tensors each fused sigma term keeps for backward."""
    seen, stack, out = set(), [loss.grad_fn], []
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        if type(node).__name__ == "_SigmaTermBackward":
            out.append(len(node.saved_tensors))
        stack += [f for f, _ in node.next_functions]
    return out


def test_function_and_module_defaults_agree():
    """The twins share their defaults (the module is the function plus caching): equal values
    with and without a mask, the documented ``pad_frac = 0.25`` margin, and the fast path
    (``low_memory=False`` keeps u, D and the blurred differences, 4 + 2 + |alphas| tensors)."""
    x, y = _rand(1, 2, 12, 10, lo=-0.2, hi=1.2, dtype=D64).requires_grad_(), _rand(1, 2, 12, 10, seed=1, dtype=D64)
    mask = _rand(1, 1, 12, 10, seed=2, dtype=D64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f, m = loi_loss(x, y), LOILoss()(x, y)
        assert f.item() == pytest.approx(m.item(), rel=1e-12)
        assert f.item() == pytest.approx(loi_loss(x, y, pad_frac=0.25).item(), rel=1e-12)
        assert f.item() != pytest.approx(loi_loss(x, y, pad_frac=0.5).item(), rel=1e-6)
        masked = loi_loss(x, y, mask=mask)
        assert LOILoss()(x, y, mask).item() == pytest.approx(masked.item(), rel=1e-12)
        assert masked.item() != pytest.approx(f.item(), rel=1e-6)
        assert _saved_per_sigma(f) == _saved_per_sigma(m) == [4 + 2 + 4] * 2
        assert _saved_per_sigma(loi_loss(x, y, low_memory=True)) == [4] * 2
    assert LOILoss().cfg == LOILoss.preset("pathtracing").cfg  # the default scales are the preset's


def test_set_scales_equals_a_fresh_module():
    """``set_scales`` gives the loss of a module built with those scales (others kept)."""
    x, y = _rand(1, 1, 10, 10, dtype=D64), _rand(1, 1, 10, 10, seed=1, dtype=D64)
    m = LOILoss(alphas=(1, 3), sigmas=(0,), border="renormalize")
    m(x, y)
    m.set_scales(sigmas=(0, 2), weights=[[1.0, 0.5], [2.0, 0.0]])
    assert m.alphas == (1.0, 3.0) and m.sigmas == (0.0, 2.0) and len(m._cache) == 0
    fresh = LOILoss(alphas=(1, 3), sigmas=(0, 2), weights=[[1.0, 0.5], [2.0, 0.0]], border="renormalize")
    assert m(x, y).item() == pytest.approx(fresh(x, y).item(), rel=1e-12)
    m.set_scales(alphas=(2,))  # weights reset to 1
    assert m.cfg == LOILoss(alphas=(2,), sigmas=(0, 2), border="renormalize").cfg
    with pytest.raises(ValueError, match="^alphas must be finite and >= 0"):
        m.set_scales(alphas=(-1,))
    with pytest.raises(ValueError, match=r"^sigmas must be finite and >= 0"):
        m.set_scales(sigmas=(-1,))
    with pytest.raises(ValueError, match=r"weights must have shape \(len\(sigmas\), len\(alphas\)\) = \(2, 1\)"):
        m.set_scales(weights=[[1.0, 1.0]])


@pytest.mark.parametrize("border", ["pad", "renormalize"])
def test_cdfs_are_blurred_point_cdfs(border):
    """E6: ``A_alpha * Phi((e_j - J_sigma) / beta)`` with the loss's transform, margin (the
    image padded with ``lo`` then cropped) and (relative) scales."""
    img = _rand(2, 1, 12, 9, hi=3.0, dtype=D64)
    opts = dict(beta=0.25, tail=1, border=border, pad_frac=0.5, transform="reinhard", value_range=(0.1, 1.1), truncate=1.0)
    m = LOILoss(**opts)
    pad = 6 if border == "pad" else 0
    j = torch.nn.functional.pad(img / (1 + img), (pad,) * 4, value=0.1)
    edges = 0.1 + torch.arange(-1, 6, dtype=D64) * 0.25
    z = torch.special.ndtr((edges.view(1, 1, -1, 1, 1) - blur(j, 1.5, 1.0).unsqueeze(2)) / 0.25)
    expected = blur(z, 2.0, 1.0)[..., pad : pad + 12, pad : pad + 9]
    torch.testing.assert_close(m.cdfs(img, 1.5, 2.0), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(m.cdfs(img[0], 1.5, 2.0), expected[:1], rtol=1e-12, atol=1e-12)
    rel = LOILoss(relative=True, **opts)
    torch.testing.assert_close(rel.cdfs(img, 1.5 / 9, 2.0 / 9), expected, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"^sigma must be finite and >= 0, got \(-1.0,\)$"):
        m.cdfs(img, -1.0, 2.0)
    with pytest.raises(ValueError, match=r"^alpha must be finite and >= 0, got \(-2.0,\)$"):
        m.cdfs(img, 1.0, -2.0)
    with pytest.raises(TypeError, match="^img must be a torch.Tensor, got ndarray$"):
        m.cdfs(img.cpu().numpy(), 1.0, 2.0)


def test_memory_estimate_scales_with_its_factors():
    """Bytes ~ B C' K Hp Wp x (tensors kept): (C, H, W) is one batch item, luminance has one
    channel, float64 doubles it, renormalised borders have no margin, low_memory keeps 5 + |sigmas|."""
    m = LOILoss()
    est = m.memory_estimate((2, 3, 40, 24))
    assert m.memory_estimate((3, 40, 24)) * 2 == est
    assert m.memory_estimate((2, 3, 40, 24), torch.float64) == 2 * est
    assert LOILoss(channels="luminance").memory_estimate((2, 3, 40, 24)) * 3 == est
    assert LOILoss(border="renormalize").memory_estimate((2, 3, 40, 24)) * 60 * 44 == est * 40 * 24
    assert LOILoss(low_memory=True).memory_estimate((2, 3, 40, 24)) * (6 * 2 + 2) == est * (5 + 2)


def test_memory_warning_once_above_2_gib_unless_low_memory():
    x, y = _rand(1, 1, 6, 6), _rand(1, 1, 6, 6, seed=1)
    calls = []
    for low_memory, est, warns in [(False, 2**31 + 1, True), (False, 2**31, False), (True, 2**40, False)]:
        m = LOILoss(alphas=(1,), sigmas=(0,), low_memory=low_memory)
        m.memory_estimate = lambda shape, dtype, est=est: calls.append((shape, dtype)) or est  # noqa: E731
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            m(x, y)
            m(x, y)  # at most once per module
        msgs = [str(w.message) for w in caught]
        if warns:
            assert len(msgs) == 1 and msgs[0].startswith("LOI loss needs ~2.0 GiB for autograd at (1, 1, 6, 6)"), msgs
            assert msgs[0].endswith("consider low_memory=True")
        else:
            assert msgs == []
    assert calls[0] == ((1, 1, 6, 6), torch.float32)


def test_mask_shapes_and_checks():
    """A mask is (B|1, 1|C, H, W) or (1|C, H, W), broadcast over the batch; per-channel masks
    weight channels; bad masks are refused with the reason."""
    x, y = _rand(2, 3, 8, 8, dtype=D64), _rand(2, 3, 8, 8, seed=1, dtype=D64)
    kw = dict(alphas=(0, 2), sigmas=(0,), border="renormalize", reduction="none")
    single = _rand(1, 1, 8, 8, seed=2) + 0.1  # float32 mask for float64 images
    ref = loi_loss(x, y, mask=single.to(D64).expand(2, 3, 8, 8), **kw)
    for mask in (single, single[0], single.expand(2, 1, 8, 8), single.expand(1, 3, 8, 8), single.expand(1, 3, 8, 8)[0]):
        torch.testing.assert_close(loi_loss(x, y, mask=mask, **kw), ref, rtol=1e-12, atol=0)
    per_channel = torch.zeros(1, 3, 8, 8)
    per_channel[:, 1] = 1  # normalised by its channel mean's sum: the mean over green alone
    only_g = loi_loss(x[:, 1:2], y[:, 1:2], **kw)
    torch.testing.assert_close(loi_loss(x, y, mask=per_channel, **kw), only_g, rtol=1e-12, atol=0)
    bad = [
        (torch.ones(8, 8).tolist(), TypeError, "mask must be a torch.Tensor, got list"),
        (torch.ones(8, 8), ValueError, r"mask must be \(B, 1, H, W\) or \(B, C, H, W\) for images \(2, 3, 8, 8\), got \(8, 8\)"),
        (torch.ones(3, 1, 8, 8), ValueError, r"got \(3, 1, 8, 8\)"),
        (torch.ones(1, 2, 8, 8), ValueError, r"got \(1, 2, 8, 8\)"),
        (torch.ones(1, 1, 8, 7), ValueError, r"got \(1, 1, 8, 7\)"),
        (torch.full((1, 1, 8, 8), -0.5), ValueError, "^mask must be finite and >= 0$"),
        (torch.full((1, 1, 8, 8), float("nan")), ValueError, "^mask must be finite and >= 0$"),
        (torch.stack([torch.ones(1, 8, 8), torch.zeros(1, 8, 8)]), ValueError, "^mask is zero everywhere for some batch item: nothing to compare$"),
    ]
    for mask, error, match in bad:
        with pytest.raises(error, match=match):
            loi_loss(x, y, mask=mask, **kw)
    with pytest.raises(ValueError, match="mask has 3 channels but the compared images have 1"):
        loi_loss(x, y, mask=torch.ones(1, 3, 8, 8), channels="luminance", **kw)


def test_mask_per_batch_item():
    """Each batch item is weighted by its own mask, normalised by its own sum."""
    x, y = _rand(2, 1, 8, 8, dtype=D64), _rand(2, 1, 8, 8, seed=1, dtype=D64)
    mask = torch.stack([_rand(1, 8, 8, seed=2, dtype=D64), 5 * _rand(1, 8, 8, seed=3, dtype=D64).square()])
    kw = dict(alphas=(0, 2), sigmas=(1,), reduction="none")
    got = loi_loss(x, y, mask=mask, **kw)
    singles = torch.cat([loi_loss(x[i : i + 1], y[i : i + 1], mask=mask[i : i + 1], **kw) for i in range(2)])
    torch.testing.assert_close(got, singles, rtol=1e-12, atol=0)
    m = LOILoss(**kw)
    assert sum(m.terms(x, y, mask).values()).item() == pytest.approx(got.mean().item(), rel=1e-12)


@pytest.mark.parametrize("cell_fraction", [0.0, 1.0])
def test_truncate_reaches_every_blur(cell_fraction):
    """With a short kernel (``truncate=1``) value and gradient equal plain autograd through
    E1-E7 built from the same truncated blurs (cells: their exact means, float32 included)."""
    x = _rand(1, 2, 12, 11, lo=0.05, hi=0.95, dtype=D64).requires_grad_()
    y = _rand(1, 2, 12, 11, seed=1, lo=0.05, hi=0.95, dtype=D64)
    s, a, beta, tr = 1.5, 2.0, 0.25, 1.0
    edges = torch.arange(-3, 8, dtype=D64) * beta
    cdf = lambda t: torch.special.ndtr((edges.view(1, 1, -1, 1, 1) - blur(t, s, tr).unsqueeze(2)) / beta)  # noqa: E731
    d = cdf(x) - cdf(y)
    if cell_fraction:
        rh, ih = cell_means(12, a, 2, tr, D64, DEVICE)
        rw, iw = cell_means(11, a, 2, tr, D64, DEVICE)
        out, weights = rh @ d @ rw.T, ih.sum(1)[:, None] * iw.sum(1)[None, :] / (12 * 11)
    else:
        out, weights = blur(d, a, tr), torch.full((12, 11), 1 / (12 * 11), dtype=D64)
    oracle = (out.abs().sum(2) * beta * weights).sum() / 2
    opts = dict(alphas=(a,), sigmas=(s,), beta=beta, border="renormalize", truncate=tr, cell_fraction=cell_fraction)
    got = loi_loss(x, y, **opts)
    assert got.item() == pytest.approx(oracle.item(), rel=1e-12)
    (g_got,), (g_ref,) = torch.autograd.grad(got, x), torch.autograd.grad(oracle, x)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-9, atol=1e-14)
    assert LOILoss(**opts).terms(x, y)[(s, a)].item() == pytest.approx(oracle.item(), rel=1e-12)
    x32 = x.detach().float().requires_grad_()
    got32 = loi_loss(x32, y.float(), **opts)
    (g32,) = torch.autograd.grad(got32, x32)
    assert got32.dtype == torch.float32 and torch.allclose(g32.double(), g_ref, rtol=1e-3, atol=1e-7)


def test_default_is_cells_of_the_fast_fraction_and_exact_is_every_pixel():
    """The default evaluates alpha >= 1 / FAST_CELL_FRACTION px on cells (the documented 0.15),
    ``exact=True`` every pixel (= ``cell_fraction=0``); both twins agree; small alphas are exact
    either way; and the default stays within 1 % of the exact loss and gradient on a smooth field."""
    from torchir.modules.loi import FAST_CELL_FRACTION

    assert FAST_CELL_FRACTION == 0.15
    target = _disk(torch.tensor(20.0, dtype=D64), n=96)
    cx = torch.tensor(36.3, dtype=D64, requires_grad=True)
    default, exact = loi_loss(_disk(cx, n=96), target), loi_loss(_disk(cx, n=96), target, exact=True)
    assert default.item() == loi_loss(_disk(cx, n=96), target, cell_fraction=0.15).item()
    assert exact.item() == loi_loss(_disk(cx, n=96), target, cell_fraction=0.0).item()
    assert default.item() != exact.item()  # alpha 15 and 45 on 2 and 6 px cells
    assert LOILoss()(_disk(cx, n=96), target).item() == pytest.approx(default.item(), rel=1e-12)
    assert LOILoss(exact=True)(_disk(cx, n=96), target).item() == pytest.approx(exact.item(), rel=1e-12)
    assert default.item() == pytest.approx(exact.item(), rel=0.01)
    (g_default,), (g_exact,) = torch.autograd.grad(default, cx), torch.autograd.grad(exact, cx)
    assert g_default.item() == pytest.approx(g_exact.item(), rel=0.01)
    small = dict(alphas=(1, 5), sigmas=(0, 1))  # 0.15 * 5 < 2: every pixel
    x, y = _rand(1, 2, 20, 18, lo=0.1, hi=0.9, dtype=D64), _rand(1, 2, 20, 18, seed=1, lo=0.1, hi=0.9, dtype=D64)
    assert loi_loss(x, y, **small).item() == loi_loss(x, y, exact=True, **small).item()
    assert "cell_fraction=0.15 (cells)" in repr(LOILoss()) and "cell_fraction=0.0 (exact)" in repr(LOILoss(exact=True))


def test_cell_fraction_changes_the_loss_in_both_twins():
    target = _disk(torch.tensor(20.0, dtype=D64))
    cx = torch.tensor(36.0, dtype=D64)
    exact, approx = loi_loss(_disk(cx), target), loi_loss(_disk(cx), target, cell_fraction=0.5)
    assert approx.item() != pytest.approx(exact.item(), rel=1e-6)  # cells approximate: not the exact loss
    assert LOILoss(cell_fraction=0.5)(_disk(cx), target).item() == pytest.approx(approx.item(), rel=1e-12)


def test_target_cache_is_lru_keyed_on_tensor_shape_and_dtype():
    """Hits need an equal target of the same shape and dtype; a new tensor is compared by
    content, never trusted by its version counter; the least recently used entry goes first."""
    x = _rand(1, 1, 8, 8)
    a, b, c = (_rand(1, 1, 8, 8, seed=k) for k in (1, 2, 3))
    m = LOILoss(alphas=(1,), sigmas=(0,), cache_target=2)
    plain = LOILoss(alphas=(1,), sigmas=(0,), cache_target=0)
    for target, hits in [(a, 0), (b, 0), (b, 1), (a, 2), (c, 2), (a, 3), (b, 3)]:
        assert m(x, target).item() == pytest.approx(plain(x, target).item(), rel=1e-6)
        assert m.cache_hits == hits, target
    fresh = _rand(1, 1, 8, 8, seed=4)  # version 0, like the cached ones: content decides
    assert m(x, fresh).item() == pytest.approx(plain(x, fresh).item(), rel=1e-6) and m.cache_hits == 3
    one = LOILoss(alphas=(1,), sigmas=(0,))
    one(x.double(), a)  # float64 target CDFs
    one(x, a)  # float32 ones: a different key
    assert one.cache_hits == 0
    one(x, a)
    assert one.cache_hits == 1
    two, small = LOILoss(alphas=(1,), sigmas=(0,), cache_target=2), _rand(1, 1, 6, 6, seed=5)
    two(x, a), two(small, small), two(small, small)  # the lookup passes over the 8x8 entry
    assert two.cache_hits == 1


def test_out_of_range_warning_threshold_and_message():
    """Warns when more than 1 % of an image lies beyond ``value_range +- 3 beta``, naming the
    image and the share; once per module and image, whether from forward or terms."""
    kw = dict(alphas=(0,), sigmas=(0,), beta=0.125)
    inside = torch.full((1, 1, 4, 4), 0.5)
    for edge in (-0.375, 1.375, 0.0, 1.0):  # exactly +-3 beta beyond the range: not yet outside
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            loi_loss(torch.full((1, 1, 4, 4), edge), inside, **kw)
    far = inside.clone()
    far[..., 0, :] = 1.4  # 3.2 beta beyond hi, on 4 of 16 pixels
    m = LOILoss(**kw)
    with pytest.warns(UserWarning, match=r"^LOI loss: 25.0% of target's values lie beyond value_range \(0.0, 1.0\) \+- 3 beta"):
        m(inside, far)
    with pytest.warns(UserWarning, match=r"^LOI loss: 25.0% of rendered's values"):
        m.terms(far, inside)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m(far, far)
        m.terms(far, far)


def test_warnings_point_at_the_callers_line():
    """Every LOI warning names the user's call site (this file), whether it comes from the
    function, the module's ``__call__`` (through torch's ``nn.Module``), ``terms``, ``preset``
    or the constructor, not a line inside torchir or torch."""
    inside, far = torch.full((1, 1, 4, 4), 0.5), torch.full((1, 1, 4, 4), 3.0)
    kw = dict(alphas=(0,), sigmas=(0,))
    big = LOILoss(**kw)
    big.memory_estimate = lambda shape, dtype: 2**32  # noqa: E731
    calls = [
        ("beyond value_range", lambda: loi_loss(inside, far, **kw)),
        ("beyond value_range", lambda: LOILoss(**kw)(inside, far)),
        ("beyond value_range", lambda: LOILoss(**kw).terms(far, inside)),
        ("consider low_memory=True", lambda: big(inside, inside)),
        ("beta=0.001", lambda: LOILoss(beta=0.001)),
        ("beta=0.001", lambda: LOILoss.preset("disks", beta=0.001)),
        ("beta=0.001", lambda: loi_loss(inside, inside, beta=0.001, **kw)),
    ]
    for match, call in calls:
        with pytest.warns(UserWarning, match=match) as record:
            call()
        _assert_warned_here(record)
