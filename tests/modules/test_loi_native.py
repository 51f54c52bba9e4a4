"""The LOI loss's fused native kernel (``_loi_native``): the same loss and gradient as the torch
path, exact zeros where the images agree, and the pooled aperture stages of the cell terms."""
from __future__ import annotations

import os
import shutil

import pytest
import torch

from torchir.modules import LOILoss, _loi_native
from torchir.modules._banded import native_products
from torchir.modules._blur import cell_means
from torchir.modules._loi_terms import _operator

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None, reason="no C compiler on this machine")


def _loss_and_grad(loss: LOILoss, x: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, native: bool = True):
    with native_products(native):
        x = x.clone().requires_grad_(True)
        v = loss(x, target, mask)
        v.sum().backward()
    return v.detach(), x.grad


CONFIGS = {
    "default": dict(transform="reinhard"),
    "exact": dict(transform="reinhard", exact=True),
    "alpha and sigma 0": dict(alphas=(0, 2), sigmas=(0, 1)),
    "renormalize": dict(border="renormalize"),
    "luminance": dict(channels="luminance"),
    "zero weights": dict(alphas=(1, 5, 15), sigmas=(1, 5), weights=[[1, 0, 2], [0, 3, 0]]),
    "per item": dict(reduction="none", low_memory=True),
    "relative": dict(alphas=(0.05, 0.3), sigmas=(0.02,), relative=True),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_fused_kernel_equals_the_torch_path(name):
    torch.manual_seed(3)
    shape = (2, 3, 37, 53) if name == "per item" else (1, 3, 48, 40)
    x, target = torch.rand(shape) * 1.5, torch.rand(shape) * 1.5
    loss = LOILoss(**CONFIGS[name])
    v1, g1 = _loss_and_grad(loss, x, target)
    v0, g0 = _loss_and_grad(loss, x, target, native=False)
    torch.testing.assert_close(v1, v0, rtol=2e-6, atol=0)  # float32 sums of ~1e5 terms
    assert float((g1 - g0).norm() / g0.norm()) < 1e-5


def test_fused_kernel_is_used_for_float32_and_not_for_float64(monkeypatch):
    calls = []  # (dtype, whether the kernel computed the term)
    real = _loi_native.sigma_term

    def spy(*a, **k):
        result = real(*a, **k)
        calls.append((a[0].dtype, result is not None))
        return result

    monkeypatch.setattr(_loi_native, "sigma_term", spy)
    x, target = torch.rand(1, 3, 24, 24), torch.rand(1, 3, 24, 24)
    _loss_and_grad(LOILoss(), x, target)
    assert calls == [(torch.float32, True)] * 2  # one call per inner scale
    calls.clear()
    v64, g64 = _loss_and_grad(LOILoss(), x.double(), target.double())
    assert not any(used for _, used in calls) and g64.dtype == torch.float64  # the torch path
    v32, _ = _loss_and_grad(LOILoss(), x, target)
    torch.testing.assert_close(v32.double(), v64, rtol=1e-5, atol=0)


def test_a_mask_weights_the_same_pixels():
    torch.manual_seed(4)
    x, target = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    mask = (torch.rand(2, 1, 32, 32) > 0.3).float()
    loss = LOILoss(transform="reinhard", reduction="none")
    (v1, g1), (v0, g0) = _loss_and_grad(loss, x, target, mask), _loss_and_grad(loss, x, target, mask, native=False)
    torch.testing.assert_close(v1, v0, rtol=2e-6, atol=0)
    assert float((g1 - g0).norm() / g0.norm()) < 1e-5


@pytest.mark.parametrize("value", [0.0, 0.37, 1e4])
def test_equal_images_give_exactly_zero_loss_and_gradient(value):
    """Zero, mid and huge radiance: the reference's CDFs come from the kernel's own Phi, so every
    difference is exactly 0 (with a different Phi, rounding-level differences gave the sign of
    ``A D`` at random: 2.3 % of the image gradient on glossy_highlight)."""
    img = torch.full((1, 3, 20, 28), value)
    img[..., 5:9, 7:20] = value * 0.5 + 0.1  # structure, so the blurs are not trivially constant
    loss = LOILoss(transform="reinhard")
    v, g = _loss_and_grad(loss, img, img.clone())
    assert float(v) == 0.0
    assert torch.count_nonzero(g) == 0


def test_no_gradient_requested_gives_the_same_value():
    torch.manual_seed(5)
    x, target = torch.rand(1, 3, 30, 30), torch.rand(1, 3, 30, 30)
    loss = LOILoss()
    with torch.no_grad():
        v = loss(x, target)
    v1, _ = _loss_and_grad(loss, x, target)
    assert float(v) == float(v1)


def test_one_pixel_image():
    x, target = torch.rand(1, 3, 1, 1), torch.rand(1, 3, 1, 1)
    (v1, g1), (v0, g0) = _loss_and_grad(LOILoss(), x, target), _loss_and_grad(LOILoss(), x, target, native=False)
    torch.testing.assert_close(v1, v0, rtol=2e-6, atol=0)
    torch.testing.assert_close(g1, g0, rtol=1e-4, atol=1e-9)


@pytest.mark.parametrize("n, support, alpha, cell, pool", [(96, 70, 15.0, 2, 2), (120, 84, 45.0, 6, 6), (50, 50, 9.0, 4, 4), (120, 84, 45.0, 11, 6)])
def test_pooled_cell_operator_is_exact_for_inputs_constant_within_cells(n, support, alpha, cell, pool):
    """``pool > 1``: a box mean over ``pool``-sample cells, then the blur on those cells, equals
    the per-cell means of the full blur whenever the input is constant within each pool cell."""
    offset = (n - support) // 2
    pool_rows, coarse = _operator(n, alpha, cell, pool, offset, support, 3.0, torch.float64, "cpu")
    rows = cell_means(n, alpha, cell, 3.0, torch.float64)[0][:, offset : offset + support]
    cells = (torch.arange(offset, offset + support) // pool) - offset // pool
    x = torch.randn(int(cells[-1]) + 1, 3, dtype=torch.float64)[cells]  # (support, 3), constant per cell
    torch.testing.assert_close(coarse @ (pool_rows @ x), rows @ x, rtol=1e-12, atol=1e-12)
    y = torch.randn(support, 3, dtype=torch.float64)  # not constant: an approximation, not the same
    assert float((coarse @ (pool_rows @ y) - rows @ y).abs().max()) > 1e-9
    assert pool_rows.shape[1] == support and coarse.shape == (rows.shape[0], pool_rows.shape[0])


def test_results_are_bitwise_reproducible():
    """Planes go to threads dynamically; every plane's share is summed in a fixed order after."""
    torch.manual_seed(6)
    x, target = torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)
    loss = LOILoss(transform="reinhard")
    runs = [_loss_and_grad(loss, x, target) for _ in range(4)]
    for v, g in runs[1:]:
        assert torch.equal(v, runs[0][0]) and torch.equal(g, runs[0][1])
