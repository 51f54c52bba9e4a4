"""Multi-scale RGB baselines for the LOI loss: Gaussian pyramid (GP) and multi-scale L1/L2.

``gaussian_pyramid_loss``: the classic image pyramid (the "GP" baseline of Mehta et al. 2025):
level 0 is the image, level ``l + 1`` is level ``l`` blurred by ``sigma`` and subsampled by 2;
the loss sums the mean squared (``p=2``) or absolute (``p=1``) difference of every level.
``multiscale_l1_loss`` / ``multiscale_l2_loss``: full-resolution blur stacks, the mean L1/L2
difference of both images blurred by each of ``sigmas`` (pixels), summed over the scales. The
L1 stack is exactly the LOI loss with ``alphas=(0,)`` for values in range (the W1 distance of
two equal-width Gaussians is the distance of their means), the "sigma-space only" ablation; the
L2 stack is the "MSE of blurred images" variant of the GP baseline.

All blurs are border-renormalised and handle kernels larger than the image.

Example:
    >>> x, y = torch.rand(2, 3, 32, 32, requires_grad=True), torch.rand(2, 3, 32, 32)
    >>> GaussianPyramidLoss(levels=4)(x, y).backward()
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from ._blur import blur
from .loi import TRANSFORMS, Transform, _as_batch, _scales

__all__ = [
    "gaussian_pyramid_loss",
    "multiscale_l1_loss",
    "multiscale_l2_loss",
    "GaussianPyramidLoss",
    "MultiScaleL1Loss",
    "MultiScaleL2Loss",
]

_REDUCTIONS = ("mean", "sum", "none")


def _pair(rendered: torch.Tensor, target: torch.Tensor, transform: Transform, reduction: str) -> tuple[torch.Tensor, torch.Tensor]:
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")
    r, t = _as_batch("rendered", rendered), _as_batch("target", target)
    if r.shape != t.shape:
        raise ValueError(f"rendered and target shapes differ: {tuple(r.shape)} vs {tuple(t.shape)}")
    dtype = torch.promote_types(r.dtype, t.dtype)
    r, t = r.to(dtype), t.detach().to(dtype)
    if transform is None or transform == "identity":
        return r, t
    if transform == "clamp":
        return r.clamp(0, 1), t.clamp(0, 1)
    if isinstance(transform, str):
        if transform not in TRANSFORMS:
            raise ValueError(f"transform must be one of {sorted(TRANSFORMS)} or a callable, got {transform!r}")
        transform = TRANSFORMS[transform]
    return transform(r), transform(t)


def _distance(a: torch.Tensor, b: torch.Tensor, p: int) -> torch.Tensor:
    """Per batch item ``mean |a - b|^p``, ``(B,)``."""
    d = (a - b).abs() if p == 1 else (a - b).square()
    return d.flatten(1).mean(1)


def _reduce(x: torch.Tensor, reduction: str) -> torch.Tensor:
    return x.mean() if reduction == "mean" else x.sum() if reduction == "sum" else x


def _check_p(p: int) -> int:
    if p not in (1, 2):
        raise ValueError(f"p must be 1 or 2, got {p!r}")
    return p


def gaussian_pyramid_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    levels: int | None = None,
    sigma: float = 1.0,
    p: int = 2,
    transform: Transform = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Sum over pyramid levels of the mean ``|rendered_l - target_l|^p``.

    Args:
        levels: number of levels incl. the full-resolution one; ``None``: down to ~4 px.
        sigma: blur (pixels) before each 2x subsampling.
        p: 2 (MSE, the paper's GP) or 1.
        transform: intensity map applied first (as in :func:`~torchir.modules.loi_loss`).
        reduction: ``"mean"``/``"sum"`` over the batch or ``"none"`` for ``(B,)``.

    Shape:
        ``(B, C, H, W)`` or ``(C, H, W)`` -> scalar (or ``(B,)``).
    """
    _check_p(p)
    r, t = _pair(rendered, target, transform, reduction)
    if levels is None:
        levels = 1 + max(0, int(math.log2(max(1, min(r.shape[-2:]) // 4))))
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
        raise ValueError(f"levels must be an int >= 1, got {levels!r}")
    total = _distance(r, t, p)
    for _ in range(levels - 1):
        if min(r.shape[-2:]) < 2:
            break
        r, t = blur(r, sigma)[..., ::2, ::2], blur(t, sigma)[..., ::2, ::2]
        total = total + _distance(r, t, p)
    return _reduce(total, reduction)


def _multiscale(rendered, target, sigmas, p, transform, truncate, reduction) -> torch.Tensor:
    sigmas = _scales("sigmas", sigmas)
    r, t = _pair(rendered, target, transform, reduction)
    return _reduce(sum(_distance(blur(r, s, truncate), blur(t, s, truncate), p) for s in sigmas), reduction)


def multiscale_l1_loss(
    rendered: torch.Tensor, target: torch.Tensor, sigmas: Sequence[float] = (0, 1, 5, 15, 45),
    transform: Transform = None, truncate: float = 3.0, reduction: str = "mean",
) -> torch.Tensor:
    """``sum_sigma mean |G_sigma * rendered - G_sigma * target|`` (= LOI with ``alphas=(0,)``)."""
    return _multiscale(rendered, target, sigmas, 1, transform, truncate, reduction)


def multiscale_l2_loss(
    rendered: torch.Tensor, target: torch.Tensor, sigmas: Sequence[float] = (0, 1, 5, 15, 45),
    transform: Transform = None, truncate: float = 3.0, reduction: str = "mean",
) -> torch.Tensor:
    """``sum_sigma mean (G_sigma * rendered - G_sigma * target)^2``."""
    return _multiscale(rendered, target, sigmas, 2, transform, truncate, reduction)


class GaussianPyramidLoss(nn.Module):
    """Module twin of :func:`gaussian_pyramid_loss`."""

    pixelwise = False  # blurs couple pixels: not usable with pixel sampling

    def __init__(self, levels: int | None = None, sigma: float = 1.0, p: int = 2, transform: Transform = None, reduction: str = "mean") -> None:
        super().__init__()
        self.levels, self.sigma, self.p, self.transform, self.reduction = levels, float(sigma), _check_p(p), transform, reduction

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return gaussian_pyramid_loss(rendered, target, self.levels, self.sigma, self.p, self.transform, self.reduction)

    def extra_repr(self) -> str:
        return f"levels={self.levels}, sigma={self.sigma}, p={self.p}, transform={self.transform!r}, reduction={self.reduction!r}"


class MultiScaleL1Loss(nn.Module):
    """Module twin of :func:`multiscale_l1_loss`."""

    pixelwise = False
    p = 1

    def __init__(self, sigmas: Sequence[float] = (0, 1, 5, 15, 45), transform: Transform = None, truncate: float = 3.0, reduction: str = "mean") -> None:
        super().__init__()
        self.sigmas, self.transform, self.truncate, self.reduction = _scales("sigmas", sigmas), transform, float(truncate), reduction

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return _multiscale(rendered, target, self.sigmas, self.p, self.transform, self.truncate, self.reduction)

    def extra_repr(self) -> str:
        return f"sigmas={self.sigmas}, transform={self.transform!r}, reduction={self.reduction!r}"


class MultiScaleL2Loss(MultiScaleL1Loss):
    """Module twin of :func:`multiscale_l2_loss`."""

    p = 2
