"""The native banded product behind the LOI blurs: same values as the dense product, fallbacks."""
from __future__ import annotations

import gc
import os
import shutil

import pytest
import torch

from torchir.modules import LOILoss, _banded
from torchir.modules._banded import ENV_CACHE, ENV_NATIVE, native_available, native_products, sandwich, sandwich_adjoint
from torchir.modules._blur import blur, cell_means, gaussian_matrix

has_compiler = shutil.which(os.environ.get("CC", "cc")) is not None


@pytest.fixture
def dense_only():
    """Every product takes the dense path (as without a compiler)."""
    with native_products(False):
        yield


def _support_matrix(canvas: int, support: int, sigma: float, cell: int = 1) -> torch.Tensor:
    """``(ceil(canvas / cell), support)``: a blur on a canvas (per pixel or cell means), as the
    LOI terms use it, restricted to the columns of a centred support."""
    rows = gaussian_matrix(canvas, sigma) if cell == 1 else cell_means(canvas, sigma, cell)[0]
    off = (canvas - support) // 2
    return rows[:, off : off + support].contiguous()


@pytest.mark.skipif(not has_compiler, reason="no C compiler on this machine")
def test_native_kernel_compiles_where_a_compiler_exists():
    assert native_available()


# (canvas H, support H, canvas W, support W, sigma, cell): Gaussian rows, cell means, sizes
# that are not multiples of the kernel's 8/32 blocks
SHAPES = [
    (40, 34, 40, 34, 1.0, 1),
    (47, 29, 53, 35, 2.5, 1),
    (30, 24, 37, 30, 1.5, 2),
    (64, 40, 64, 40, 3.0, 3),
    (20, 20, 3, 3, 0.7, 1),
    (70, 64, 70, 64, 5.0, 1),
]


@pytest.mark.parametrize("hp, h, wp, w, sigma, cell", SHAPES)
def test_sandwich_and_adjoint_equal_the_dense_products(hp, h, wp, w, sigma, cell):
    torch.manual_seed(0)
    mh, mw = _support_matrix(hp, h, sigma, cell), _support_matrix(wp, w, sigma, cell)
    x = torch.randn(2, 3, h, w)
    y = sandwich(mh, x, mw)
    ref = mh.double() @ x.double() @ mw.double().T
    assert y.shape == (2, 3, mh.shape[0], mw.shape[0]) and y.dtype == torch.float32
    torch.testing.assert_close(y.double(), ref, rtol=0, atol=1e-6 * float(ref.abs().max()))
    g = torch.randn(2, 3, mh.shape[0], mw.shape[0])
    adj = sandwich_adjoint(mh, g, mw)
    ref = mh.double().T @ g.double() @ mw.double()
    assert adj.shape == x.shape
    torch.testing.assert_close(adj.double(), ref, rtol=0, atol=1e-6 * float(ref.abs().max()))


@pytest.mark.skipif(not has_compiler, reason="no C compiler on this machine")
def test_narrow_matrices_take_the_native_path_and_wide_ones_the_dense(monkeypatch):
    calls = []
    real = _banded._apply_t
    monkeypatch.setattr(_banded, "_apply_t", lambda x, band, lib: calls.append(band.length) or real(x, band, lib))
    x = torch.rand(1, 64, 64)
    sandwich(gaussian_matrix(64, 1.0), x, gaussian_matrix(64, 1.0))
    assert calls == [7, 7]
    sandwich(gaussian_matrix(64, 20.0), x, gaussian_matrix(64, 20.0))  # band of 61 > 32: dense
    sandwich(gaussian_matrix(64, 1.0).double(), x.double(), gaussian_matrix(64, 1.0).double())  # float64: dense
    with native_products(False):
        sandwich(gaussian_matrix(64, 1.0), x, gaussian_matrix(64, 1.0))
    assert calls == [7, 7]
    sandwich(gaussian_matrix(64, 1.0), x, gaussian_matrix(64, 1.0))  # on again after the block
    assert calls == [7, 7, 7, 7]


def test_sandwich_gradients_match_the_dense_product_and_allow_double_backward():
    torch.manual_seed(1)
    mh, mw = _support_matrix(30, 24, 1.5), _support_matrix(26, 20, 1.5)
    x = torch.randn(2, 24, 20, requires_grad=True)
    w = torch.randn(2, 30, 26)
    (g,) = torch.autograd.grad((sandwich(mh, x, mw) * w).sum(), x)
    torch.testing.assert_close(g, mh.T @ w @ mw, rtol=1e-5, atol=1e-6)
    # the backward under create_graph stays differentiable (dense), e.g. for gradient penalties
    (g2,) = torch.autograd.grad((sandwich(mh, x, mw) ** 2).sum(), x, create_graph=True)
    (h,) = torch.autograd.grad(g2.sum(), x)
    ref = 2 * mh.T @ mh @ torch.ones_like(x) @ mw.T @ mw
    torch.testing.assert_close(h, ref, rtol=1e-4, atol=1e-5)
    xd = torch.randn(1, 24, 20, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: sandwich(mh.double(), t, mw.double()), (xd,))


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (2, 0, 4)])
def test_degenerate_shapes(shape):
    h, w = shape[-2:]
    mh, mw = gaussian_matrix(h, 1.0), gaussian_matrix(w, 1.0)
    x = torch.rand(*shape)
    torch.testing.assert_close(sandwich(mh, x, mw), mh @ x @ mw.T)


def test_band_forms_are_released_with_their_matrix():
    m = _support_matrix(40, 30, 1.0).clone()
    sandwich(m, torch.rand(30, 30), m)
    key = id(m)
    assert key in _banded._bands
    del m
    gc.collect()
    assert key not in _banded._bands


def test_loi_native_equals_dense():
    torch.manual_seed(2)
    target, start = torch.rand(1, 3, 48, 48), torch.rand(1, 3, 48, 48)
    results = []
    for native in (True, False):
        with native_products(native):
            x = start.clone().requires_grad_(True)
            loss = LOILoss(transform="reinhard")(x, target)
            loss.backward()
        results.append((loss.detach(), x.grad))
    (v1, g1), (v0, g0) = results
    torch.testing.assert_close(v1, v0, rtol=1e-5, atol=0)
    assert float((g1 - g0).norm() / g0.norm()) < 1e-5


def test_blur_is_the_same_with_and_without_the_native_path(dense_only):
    x = torch.rand(2, 3, 33, 41)
    ref = gaussian_matrix(33, 2.0) @ x @ gaussian_matrix(41, 2.0).T
    torch.testing.assert_close(blur(x, 2.0), ref)


def test_a_failing_compiler_warns_once_and_falls_back(monkeypatch, tmp_path):
    monkeypatch.setattr(_banded, "_library", None)
    monkeypatch.setattr(_banded, "_unavailable", None)
    monkeypatch.setenv(ENV_CACHE, str(tmp_path))
    monkeypatch.setenv("CC", "false")  # a "compiler" that always fails
    m, x = gaussian_matrix(32, 1.0), torch.rand(32, 32)
    with pytest.warns(UserWarning, match="no native banded blur .*falls back to dense matrix products"):
        y = sandwich(m, x, m)
    torch.testing.assert_close(y, m @ x @ m.T)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sandwich(m, x, m)  # no second warning
    assert not native_available()


def test_native_off_by_environment(monkeypatch):
    monkeypatch.setattr(_banded, "_library", None)
    monkeypatch.setattr(_banded, "_unavailable", None)
    monkeypatch.setenv(ENV_NATIVE, "0")
    assert not native_available()


@pytest.mark.skipif(not has_compiler, reason="no C compiler on this machine")
def test_compiled_kernel_is_cached_per_user(monkeypatch, tmp_path):
    monkeypatch.setattr(_banded, "_library", None)
    monkeypatch.setattr(_banded, "_unavailable", None)
    monkeypatch.setenv(ENV_CACHE, str(tmp_path))
    assert native_available()
    (built,) = (tmp_path / "kernels").glob("banded-*.so")
    stamp = built.stat().st_mtime_ns
    monkeypatch.setattr(_banded, "_library", None)
    assert native_available() and built.stat().st_mtime_ns == stamp  # reused, not rebuilt
