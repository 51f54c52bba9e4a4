"""Per-pixel image losses for inverse rendering: L1, L2 and relative L2.

All take ``(B, C, H, W)`` (or ``(C, H, W)``) images and reduce with ``reduction`` in
``{"mean", "sum", "none"}``. The relative L2 loss divides by the target's squared value (plus
``eps``) so that dark and bright regions weigh alike, as is usual for HDR renders.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["l1_loss", "l2_loss", "relative_l2_loss", "L1Loss", "L2Loss", "RelativeL2Loss", "PIXEL_LOSSES"]

_REDUCTIONS = ("mean", "sum", "none")


def _check(rendered: torch.Tensor, target: torch.Tensor, reduction: str) -> None:
    if not isinstance(rendered, torch.Tensor) or not isinstance(target, torch.Tensor):
        raise TypeError("rendered and target must be torch tensors")
    if rendered.shape != target.shape:
        raise ValueError(f"rendered and target shapes differ: {tuple(rendered.shape)} vs {tuple(target.shape)}")
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")


def _reduce(x: torch.Tensor, reduction: str) -> torch.Tensor:
    return x.mean() if reduction == "mean" else x.sum() if reduction == "sum" else x


def l1_loss(rendered: torch.Tensor, target: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """``|rendered - target|``, reduced."""
    _check(rendered, target, reduction)
    return _reduce((rendered - target).abs(), reduction)


def l2_loss(rendered: torch.Tensor, target: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """``(rendered - target)^2``, reduced."""
    _check(rendered, target, reduction)
    return _reduce((rendered - target).square(), reduction)


def relative_l2_loss(rendered: torch.Tensor, target: torch.Tensor, eps: float = 1e-2, reduction: str = "mean") -> torch.Tensor:
    """``(rendered - target)^2 / (target^2 + eps)``, reduced.

    The weight ``1 / (target^2 + eps)`` is a constant (``target`` detached there), so
    ``rendered`` gets the exact gradient and ``target`` gets one only through the difference:
    minus ``rendered``'s, not the derivative of the formula in ``target``."""
    _check(rendered, target, reduction)
    return _reduce((rendered - target).square() / (target.detach().square() + eps), reduction)


class _PixelLoss(nn.Module):
    """A loss that reduces per-element terms: usable with pixel sampling (``pixelwise``)."""

    pixelwise = True
    reduction = "mean"

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return _reduce(self.elementwise(rendered, target), self.reduction)

    def elementwise(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def pixel_terms(self, rendered: torch.Tensor, target: torch.Tensor, pixel_count: int) -> torch.Tensor:
        """Per-pixel terms ``l_j`` with ``loss(image) = mean_j l_j`` over the ``pixel_count``
        pixels of the full images; ``rendered``, ``target``: ``(N, C)`` -> ``(N,)``."""
        terms = self.elementwise(rendered, target)
        if self.reduction == "mean":
            return terms.mean(-1)
        if self.reduction == "sum":
            return terms.sum(-1) * pixel_count
        raise ValueError("pixel sampling needs a loss with reduction 'mean' or 'sum', not 'none'")


class L1Loss(_PixelLoss):
    """Module twin of :func:`l1_loss`."""

    def __init__(self, reduction: str = "mean") -> None:
        super().__init__()
        _check(torch.zeros(1, device="cpu"), torch.zeros(1, device="cpu"), reduction)
        self.reduction = reduction

    def elementwise(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return l1_loss(rendered, target, "none")

    def extra_repr(self) -> str:
        return f"reduction={self.reduction!r}"


class L2Loss(L1Loss):
    """Module twin of :func:`l2_loss`."""

    def elementwise(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return l2_loss(rendered, target, "none")


class RelativeL2Loss(_PixelLoss):
    """Module twin of :func:`relative_l2_loss`."""

    def __init__(self, eps: float = 1e-2, reduction: str = "mean") -> None:
        super().__init__()
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        _check(torch.zeros(1, device="cpu"), torch.zeros(1, device="cpu"), reduction)
        self.eps, self.reduction = eps, reduction

    def elementwise(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return relative_l2_loss(rendered, target, self.eps, "none")

    def extra_repr(self) -> str:
        return f"eps={self.eps}, reduction={self.reduction!r}"


PIXEL_LOSSES: dict[str, type[nn.Module]] = {"l1": L1Loss, "l2": L2Loss, "relative_l2": RelativeL2Loss}
