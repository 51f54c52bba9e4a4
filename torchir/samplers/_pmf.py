"""Pixel pmfs from per-pixel factor maps, and i.i.d. draws from them (pure torch).

The adaptive pmf of *Image-space Adaptive Sampling for Fast Inverse Rendering* (SIGGRAPH 2025),
"the paper" below, is ``p ∝ sqrt(p1 · p2)`` (paper Eq. 8), post-processed as its Algorithm 1:
each factor map is denoised (Gaussian blur) at its Stage-1 resolution, upsampled bilinearly to
the full resolution, combined over multi-resolution levels (Eq. 18, with our choice of level
weights), normalised and mixed with the uniform pmf (our addition) so that every pixel keeps
``p >= alpha / m``.
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Literal

import kornia
import torch
import torch.nn.functional as F

MultiRes = Literal["equal", "paper"]


def _check_map(name: str, value: torch.Tensor, views: int) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch tensor, got {type(value).__name__}")
    if value.dim() == 2:
        value = value.unsqueeze(0)
    if value.dim() != 3 or value.shape[0] != views:
        raise ValueError(f"{name} must be ({views}, h, w) (one map per view), got {tuple(value.shape)}")
    return value.detach().to(device="cpu", dtype=torch.float64)  # pmf maps live on the host


def _finite_or_zero(name: str, value: torch.Tensor) -> torch.Tensor:
    """Negative values are clamped to 0; NaN/Inf maps are replaced by zeros (uniform fallback)."""
    if not bool(torch.isfinite(value).all()):
        warnings.warn(f"{name} has NaN/Inf entries: this level falls back to the uniform pmf", stacklevel=4)
        return torch.zeros_like(value)
    return value.clamp_min(0.0)


def denoise_upsample(value: torch.Tensor, size: tuple[int, int], sigma: float) -> torch.Tensor:
    """Blur ``(V, h, w)`` with a Gaussian of ``sigma`` low-res pixels (5x5, replicate border; a
    CPU stand-in for the paper's learned denoiser and upsampler), then upsample bilinearly to
    ``size``; clamped to >= 0."""
    x = value.unsqueeze(1)  # (V, 1, h, w)
    if sigma > 0 and min(x.shape[-2:]) > 1:
        ksize = 2 * max(1, math.ceil(2 * sigma)) + 1
        # sigma as a tensor on x's device: kornia makes a float tuple into a tensor on the default device
        sigmas = torch.tensor([[sigma, sigma]], dtype=x.dtype, device=x.device)
        x = kornia.filters.gaussian_blur2d(x, (ksize, ksize), sigmas, border_type="replicate")
    if tuple(x.shape[-2:]) != tuple(size):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    return x.squeeze(1).clamp_min(0.0)


def _normalised(q: torch.Tensor) -> torch.Tensor | None:
    total = q.sum()
    if not bool(torch.isfinite(total)) or float(total) <= 0.0:
        return None
    return q / total


def pmf_from_maps(
    p1: torch.Tensor | Sequence[torch.Tensor],
    p2: torch.Tensor | Sequence[torch.Tensor] | None,
    size: tuple[int, int],
    alpha: float = 0.1,
    multires: MultiRes = "equal",
    sigma: float = 1.0,
    views: int | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The pixel pmf of factor maps ``p1`` (loss-adjoint second moments) and ``p2`` (derivative
    second moments), one map per multi-resolution level, finest first.

    Level ``d``'s unnormalised pmf is ``q_d = sqrt(up(blur(p1_d)) * up(blur(p2_d)))`` (paper
    Eq. 8; ``p2 = None`` gives the Eq. 5 baseline ``q_d = sqrt(up(blur(p1_d)))``). Levels combine
    as ``q = sum_d w_d q_d / sum(q_d)`` with ``w_d = 1/(D+1)`` (``"equal"``) or ``w_d ∝ 4^d``
    (``"paper"``: the literal sum of normalised coarse pmfs broadcast to their blocks, Eq. 18).
    A level whose maps are all zero or not finite contributes the uniform pmf. Finally
    ``p = (1 - alpha) q + alpha / m`` (a defensive mixture: ``p >= alpha / m``).

    Args:
        p1, p2: ``(V, h_d, w_d)`` float maps (or lists of them, one per level).
        size: full resolution ``(H, W)``.
        alpha: weight of the uniform pmf in ``[0, 1]``.
        multires: level weighting, ``"equal"`` or ``"paper"``.
        sigma: Gaussian denoising blur in low-res pixels (0: none).
        views: the number of views ``V`` the maps must have (default: that of ``p1``).

    Returns:
        ``(pmf, stats)``: pmf ``(V, H, W)`` float64 summing to 1; stats with the predicted
        gain ``g = m sum_j a_j / (sum_j sqrt a_j)^2`` of the finest level (uniform over optimal
        second moment, from Eq. 8) and the number of levels that fell back to uniform.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    if multires not in ("equal", "paper"):
        raise ValueError(f"multires must be 'equal' or 'paper', got {multires!r}")
    p1_levels = [p1] if isinstance(p1, torch.Tensor) else list(p1)
    p2_levels = None if p2 is None else ([p2] if isinstance(p2, torch.Tensor) else list(p2))
    if not p1_levels:
        raise ValueError("p1 has no levels")
    if p2_levels is not None and len(p2_levels) != len(p1_levels):
        raise ValueError(f"p1 has {len(p1_levels)} level(s), p2 has {len(p2_levels)}")
    if views is None:
        views = p1_levels[0].shape[0] if isinstance(p1_levels[0], torch.Tensor) and p1_levels[0].dim() == 3 else 1
    m = views * size[0] * size[1]
    uniform = torch.full((views, *size), 1.0 / m, dtype=torch.float64, device="cpu")
    combined = torch.zeros_like(uniform)
    weights = [1.0 if multires == "equal" else 4.0**d for d in range(len(p1_levels))]
    fallbacks, gain = 0, 1.0
    for d, weight in enumerate(weights):
        a1 = _finite_or_zero("p1", _check_map("p1", p1_levels[d], views))
        q = denoise_upsample(a1, size, sigma)
        if p2_levels is not None:
            a2 = _finite_or_zero("p2", _check_map("p2", p2_levels[d], views))
            q = q * denoise_upsample(a2, size, sigma)
        q = q.sqrt()  # paper Eq. 8 (the square root, as in Algorithm 1 line 8)
        level = _normalised(q)
        if level is None:
            fallbacks += 1
            level = uniform
        elif d == 0:
            a = q.square()  # a_j = p1_j p2_j, as used for the pmf
            gain = float(m * a.sum() / q.sum().square())
        combined += weight * level
    combined /= sum(weights)
    pmf = (1.0 - alpha) * combined + alpha / m  # defensive mixture with the uniform pmf
    return pmf / pmf.sum(), {"predicted_gain": gain, "uniform_levels": float(fallbacks)}


def cumulative(pmf: torch.Tensor) -> torch.Tensor:
    """Float64 CDF of a flat pmf whose last entry is exactly 1."""
    cdf = torch.cumsum(pmf.reshape(-1).to(torch.float64), 0)
    cdf = cdf / cdf[-1]
    cdf[-1] = 1.0
    return cdf


def draw(
    cdf: torch.Tensor, count: int, generator: torch.Generator, pdf: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` i.i.d. indices from the pmf of ``cdf`` by inverse CDF on a float64 cumsum
    (unlike ``torch.multinomial``, no 2^24 category limit), and their realised probabilities
    ``cdf[j] - cdf[j-1]`` (the pmf the draws really follow). ``pdf``: those differences
    precomputed (``torch.diff(cdf, prepend=0)``, the same numbers), read with one gather."""
    u = torch.rand(count, generator=generator, dtype=torch.float64, device="cpu")  # the pmf and its generator live on the host
    index = torch.searchsorted(cdf, u, right=True).clamp_(max=cdf.numel() - 1)
    if pdf is not None:
        return index, pdf[index]
    upper = cdf[index]
    lower = torch.where(index > 0, cdf[(index - 1).clamp_min(0)], torch.zeros_like(upper))
    return index, upper - lower
