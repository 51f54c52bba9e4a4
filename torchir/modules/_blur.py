"""Separable Gaussian blur as two small matrix products, for any kernel size.

``blur(x, sigma) = M_H @ x @ M_W^T`` where ``M_n`` is the ``n x n`` matrix of a Gaussian of
standard deviation ``sigma`` (pixels), truncated at ``ceil(truncate * sigma)`` and capped at
``n - 1``, with every row normalised to sum 1. Row normalisation *is* the border-renormalised
("normalized convolution") blur, so mass is preserved at the borders, and it works for kernels
larger than the image (kornia's reflect padding raises there). The matrices are cached per
(size, sigma, truncate, dtype, device). Narrow kernels (float32, CPU) run as banded products,
``2 (2 r + 1)`` multiply-adds per pixel (``_banded``); wide ones as dense products,
``H + W`` per pixel.

Example:
    >>> x = torch.rand(2, 3, 8, 5)
    >>> blur(x, 45.0).shape               # sigma far larger than the image: fine
    torch.Size([2, 3, 8, 5])
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from ._banded import sandwich, sandwich_adjoint

__all__ = ["blur", "blur_adjoint", "cell_means", "gaussian_matrix", "MIN_SCALE"]

MIN_SCALE = 1e-3  # scales below this (pixels) are treated as 0: identity


@lru_cache(maxsize=64)
def _gaussian_matrix(n: int, sigma: float, truncate: float, dtype: torch.dtype, device: str) -> torch.Tensor:
    radius = min(math.ceil(truncate * sigma), n - 1)
    i = torch.arange(n, dtype=torch.float64, device="cpu")
    d = i[:, None] - i[None, :]
    m = torch.exp(-0.5 * (d / sigma) ** 2) * (d.abs() <= radius)
    m = m / m.sum(dim=1, keepdim=True)  # rows sum to 1: border renormalisation of the truncated kernel
    return m.to(dtype=dtype, device=device)


def gaussian_matrix(n: int, sigma: float, truncate: float = 3.0, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """The ``(n, n)`` row-normalised, truncated Gaussian blur matrix (identity for ``sigma < 1e-3``)."""
    if sigma < MIN_SCALE:
        return torch.eye(n, dtype=dtype, device=device)
    return _gaussian_matrix(int(n), float(sigma), float(truncate), dtype, str(torch.device(device)))


def blur(x: torch.Tensor, sigma: float, truncate: float = 3.0) -> torch.Tensor:
    """Blur the last two dimensions of ``x`` with a border-renormalised Gaussian.

    Args:
        x: ``(..., H, W)`` float tensor.
        sigma: standard deviation in pixels; ``< 1e-3`` returns ``x`` unchanged.
        truncate: kernel radius in standard deviations (capped at the image size).

    Returns:
        ``(..., H, W)``; differentiable (the matrices are constants).
    """
    if sigma < MIN_SCALE:
        return x
    h, w = x.shape[-2:]
    mh = gaussian_matrix(h, sigma, truncate, x.dtype, x.device)
    mw = gaussian_matrix(w, sigma, truncate, x.dtype, x.device)
    return sandwich(mh, x, mw)


def blur_adjoint(g: torch.Tensor, sigma: float, truncate: float = 3.0) -> torch.Tensor:
    """The transpose of :func:`blur` (``M_H^T @ g @ M_W``), for hand-written backward passes."""
    if sigma < MIN_SCALE:
        return g
    h, w = g.shape[-2:]
    mh = gaussian_matrix(h, sigma, truncate, g.dtype, g.device)
    mw = gaussian_matrix(w, sigma, truncate, g.dtype, g.device)
    return sandwich_adjoint(mh, g, mw)


@lru_cache(maxsize=64)
def _cell_matrices(n: int, sigma: float, cell: int, truncate: float, dtype: torch.dtype, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    cells = torch.arange(n, device="cpu") // cell
    indicator = (cells[None, :] == torch.arange(-(-n // cell), device="cpu")[:, None]).to(torch.float64)  # (nc, n)
    mean_rows = indicator @ _gaussian_matrix(n, sigma, truncate, torch.float64, "cpu") / indicator.sum(1, keepdim=True)
    return mean_rows.to(dtype=dtype, device=device), indicator.to(dtype=dtype, device=device)


def cell_means(n: int, sigma: float, cell: int, truncate: float = 3.0, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Blur, then average over cells of ``cell`` samples, as one ``(ceil(n / cell), n)`` matrix.

    Returns ``(R, P)``: row ``c`` of ``R`` is the mean of the rows of :func:`gaussian_matrix` that
    fall in cell ``c`` (so ``R_H @ x @ R_W^T`` is the exact per-cell mean of ``blur(x)``, at
    ``ceil(n / cell) / n`` of the dense cost), and ``P`` is the 0/1 cell membership matrix."""
    return _cell_matrices(int(n), float(sigma), int(cell), float(truncate), dtype, str(torch.device(device)))
