"""G-buffer denoisers: the baselines of Gu et al. 2024 (cross-bilateral filter, G-buffer regression).

Gu et al. 2024 is "Target-Aware Image Denoising for Inverse Monte Carlo Rendering" (SIGGRAPH
2024), "the paper" below. Both weight a pixel's neighbours by how similar their G-buffers are
(albedo, shading normal, depth, from :func:`torchir.functions.render_gbuffers`) and by their
distance:

    w^cb_{i|c} = exp(-|q_i-q_c|^2/(2 b_q^2) - |rho_i-rho_c|^2/(2 b_rho^2)
                     - |n_i-n_c|^2/(2 b_n^2) - (d_i-d_c)^2/(2 b_d^2))       (Gu et al. 2024, Eq. 6)

* :class:`CrossBilateralDenoiser`: the weighted mean ``sum w f~ / sum w`` (Gu et al. 2024, Eq. 5);
* :class:`GBufferRegressionDenoiser`: a weighted local linear fit of ``f~`` on the G-buffers and
  the pixel offset (Moon et al. 2014, as the paper's baseline). As the released code: the
  regression columns are the raw G-buffer differences (albedo in [0, 1], depth / max depth) and
  the offset / r, with 1e-3 added to every diagonal entry of the normal matrix; the bandwidths
  enter the weights only.

The G-buffers describe the *current* scene, not the target: these filters blur target detail
that the scene does not show yet, which is what the target-aware denoiser avoids. Like it,
they are linear in ``noisy`` (backward = transposed taps); the weights are rebuilt on every
call, since the G-buffers change as the scene does (and, as in the paper, no gradient flows
through them: the second term of Eq. 4 is dropped).

Border: ``border="truncate"`` (default) drops window pixels outside the image;
``border="reflect"`` mirrors them as the authors' code does (numpy ``"reflect"``: the edge pixel
is not repeated), and the spatial term and offset columns then use the mirrored pixel's own
position, also as that code does. Our backward stays the exact transpose of the forward in both
modes (the released CBF backward is not, near the border: it assumes symmetric windows).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from ._windows import (
    _finish,
    _Taps,
    apply_taps,
    check_hparams,
    check_noisy,
    choose_table,
    mirror_index,
    pad_window,
    serial_for,
    to_batch,
)

__all__ = [
    "CrossBilateralDenoiser",
    "GBufferRegressionDenoiser",
    "cross_bilateral_denoise",
    "gbuffer_regression_denoise",
]

GUIDE_CHANNELS = 7  # albedo RGB, normal XYZ, depth (torchir.functions.render_gbuffers)
_RIDGE = 1e-3  # added to every diagonal entry of the regression's normal matrix (as the authors' code)
BORDERS = ("truncate", "reflect")


def _check_guide(guide: torch.Tensor | None, y: torch.Tensor) -> torch.Tensor:
    """``(B, 7, H, W)`` detached G-buffers matching ``y``."""
    if guide is None:
        raise ValueError(
            "this denoiser needs guide=(B,7,H,W) G-buffers (albedo, normal, depth) from "
            "torchir.functions.render_gbuffers"
        )
    g = to_batch(guide, "guide").detach()
    B, _, H, W = y.shape
    if g.shape[1] != GUIDE_CHANNELS or g.shape[2:] != (H, W) or g.shape[0] not in (1, B):
        raise ValueError(f"guide: expected ({B} or 1, {GUIDE_CHANNELS}, {H}, {W}), got {tuple(guide.shape)}")
    if g.device != y.device:
        raise ValueError(f"guide is on {g.device} but noisy is on {y.device}")
    bad = int((~torch.isfinite(g)).sum())
    if bad:
        raise ValueError(f"guide has {bad} NaN/Inf value(s)")
    return g


def _features(guide: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``(B, 7, H, W)`` G-buffers as the authors' code feeds them: albedo clamped to [0, 1],
    normal, depth divided by the image's maximum."""
    g = guide.to(dtype)
    albedo, normal, depth = g[:, :3].clamp(0, 1), g[:, 3:6], g[:, 6:7]
    d_max = depth.amax(dim=(1, 2, 3), keepdim=True)
    depth = torch.where(d_max > 0, depth / d_max.clamp_min(torch.finfo(dtype).tiny), depth)
    return torch.cat([albedo, normal, depth], 1)


def _scaled(f: torch.Tensor, bands: tuple[float, float, float]) -> torch.Tensor:
    """Features divided by their bandwidths ``(b_rho x3, b_n x3, b_d)``: then ``|f_i - f_c|^2 / 2``
    is the G-buffer part of the exponent of Eq. 6."""
    b_albedo, b_normal, b_depth = bands
    scale = f.new_tensor([b_albedo] * 3 + [b_normal] * 3 + [b_depth]).view(1, GUIDE_CHANNELS, 1, 1)
    return f / scale


def _offsets(n: int, r: int, border: str, like: torch.Tensor) -> torch.Tensor:
    """``(2r+1, n)``: ``position(j + k - r) - j`` along one axis, where ``position`` is the pixel the
    window reads (the mirrored one for ``"reflect"``, as the authors' code does; for
    ``"truncate"`` just ``k - r``)."""
    src = mirror_index(n, r) if border == "reflect" else range(-r, n + r)
    pos = torch.tensor(list(src), dtype=like.dtype, device=like.device)
    j = torch.arange(n, dtype=like.dtype, device=like.device)
    return torch.stack([pos[k : k + n] - j for k in range(2 * r + 1)])


class _Window:
    """Per-tap quantities of a ``(2r+1)^2`` window over ``(B, *, H, W)`` G-buffers: padded
    features and the ``(H, W)`` pixel offsets ``(oy, ox)`` of each tap."""

    def __init__(self, f: torch.Tensor, radius: int, border: str) -> None:
        self.size = H, W = f.shape[2], f.shape[3]
        self.f, self.f_pad = f, pad_window(f, radius, border)
        self.oy, self.ox = _offsets(H, radius, border, f), _offsets(W, radius, border, f)

    def diff(self, dy: int, dx: int) -> torch.Tensor:
        """``f_{c+delta} - f_c`` ``(B, *, H, W)`` (meaningless outside the image for "truncate")."""
        H, W = self.size
        return self.f_pad[..., dy : dy + H, dx : dx + W] - self.f

    def offset(self, dy: int, dx: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(H, 1)`` and ``(1, W)`` pixel offsets of tap ``(dy, dx)``."""
        return self.oy[dy].unsqueeze(1), self.ox[dx].unsqueeze(0)


def _cb_weights(f: torch.Tensor, radius: int, b_space: float, border: str):
    """``weight(dy, dx)`` -> ``w^cb_delta`` ``(B, 1, H, W)`` (Gu et al. 2024, Eq. 6) from
    bandwidth-scaled features ``f``; zero outside the image for ``"truncate"``."""
    r = radius
    H, W = f.shape[2:]
    win = _Window(f, r, border)
    inside = None if border == "reflect" else pad_window(f.new_ones(1, 1, H, W), r, "truncate")

    def weight(dy: int, dx: int) -> torch.Tensor:
        oy, ox = win.offset(dy, dx)
        spatial = (oy.square() + ox.square()) / (2.0 * b_space**2)
        w = torch.exp(win.diff(dy, dx).square_().sum(1, keepdim=True).mul_(-0.5).sub_(spatial))
        return w if inside is None else w.mul_(inside[..., dy : dy + H, dx : dx + W])

    return weight


def _space_bandwidth(radius: int, sigma_space: float | None) -> float:
    return max(radius, 1) / 3.0 if sigma_space is None else float(sigma_space)  # b_q = half-width / 3


def _cross_bilateral_taps(guide: torch.Tensor, radius: int, b_space: float, bands: tuple[float, float, float],
                          dtype: torch.dtype, border: str, max_table_bytes: int = 0) -> _Taps:
    f = _scaled(_features(guide, dtype), bands)
    weight = _cb_weights(f, radius, b_space, border)
    K = 2 * radius + 1
    B, _, H, W = f.shape
    if K * K * B * H * W * f.element_size() <= max_table_bytes:  # one pass: weights, then normalise
        table = f.new_empty(K * K, B, 1, H, W)
        for k in range(K * K):
            table[k] = weight(*divmod(k, K))
        table /= table.sum(0)  # Gu et al. 2024, Eq. 5
        taps = _Taps(radius, (H, W), lambda dy, dx: table[dy * K + dx], border)
        taps.table = table
        return taps
    S0 = sum(weight(*divmod(k, K)) for k in range(K * K))  # >= 1: the centre weighs 1

    def tap(dy: int, dx: int) -> torch.Tensor:
        return weight(dy, dx).div_(S0)  # Gu et al. 2024, Eq. 5

    return _Taps(radius, (H, W), tap, border)


def _regression_taps(guide: torch.Tensor, radius: int, b_space: float, bands: tuple[float, float, float],
                     dtype: torch.dtype, border: str) -> _Taps:
    """Taps of the G-buffer local linear regression: rows ``x = [1, g_i - g_c, delta / r]``
    (10 columns, raw G-buffer differences as in the authors' code), ``M = sum w x x^T + ridge I``,
    ``l_{i|c} = w_{i|c} x_i^T M^{-1} e_1``."""
    r = radius
    f = _features(guide, torch.float64)
    weight = _cb_weights(_scaled(f, bands), r, b_space, border)
    win = _Window(f, r, border)
    B, n_f, H, W = f.shape
    scale = max(r, 1)

    def rows(dy: int, dx: int) -> torch.Tensor:  # (B, 10, H, W)
        one = torch.ones(B, 1, H, W, dtype=f.dtype, device=f.device)
        oy, ox = win.offset(dy, dx)
        offset = torch.stack(torch.broadcast_tensors(oy, ox)).div_(scale).expand(B, 2, H, W)
        # raw differences, not scaled by the bandwidths: the 1e-3 ridge is in these units (as in the
        # authors' code)
        return torch.cat([one, win.diff(dy, dx), offset], 1)

    n = n_f + 3
    M = _RIDGE * torch.eye(n, dtype=f.dtype, device=f.device).view(1, n, n, 1, 1).expand(B, n, n, H, W).clone()
    K = 2 * r + 1
    for k in range(K * K):
        dy, dx = divmod(k, K)
        x = rows(dy, dx)
        M += weight(dy, dx).unsqueeze(1) * x.unsqueeze(2) * x.unsqueeze(1)  # X^T W X (Gu et al. 2024, Eq. 10)
    e1 = torch.zeros(n, 1, dtype=f.dtype, device=f.device)
    e1[0] = 1.0
    u = torch.linalg.solve(M.permute(0, 3, 4, 1, 2), e1).squeeze(-1).permute(0, 3, 1, 2)  # (B, 10, H, W)

    def tap(dy: int, dx: int) -> torch.Tensor:
        return (weight(dy, dx) * (rows(dy, dx) * u).sum(1, keepdim=True)).to(dtype)

    return _Taps(r, (H, W), tap, border)


def _check_border(border: str) -> None:
    if border not in BORDERS:
        raise ValueError(f"border must be one of {BORDERS}, got {border!r}")


def _denoise(builder, noisy, guide, radius, sigma_space, bands, clamp_min, border, impl, max_cache_bytes,
             check_finite, what):
    check_hparams(radius, 1.0, impl, max_cache_bytes)
    _check_border(border)
    for name, b in zip(("sigma_albedo", "sigma_normal", "sigma_depth"), bands):
        if not (math.isfinite(b) and b > 0):
            raise ValueError(f"{name} must be > 0, got {b!r}")
    b_space = _space_bandwidth(radius, sigma_space)
    if not b_space > 0:
        raise ValueError(f"sigma_space must be > 0, got {sigma_space!r}")
    y = check_noisy(noisy, check_finite)
    g = _check_guide(guide, y)
    with torch.no_grad(), serial_for(g.numel()):
        if builder is _cross_bilateral_taps and impl != "taps":
            taps = builder(g, radius, b_space, bands, y.dtype, border, max_cache_bytes)
        else:
            taps = builder(g, radius, b_space, bands, y.dtype, border)
        if taps.table is None:
            choose_table(taps, y, impl, max_cache_bytes, what)
    return _finish(apply_taps(y, taps), clamp_min, noisy)


# ------------------------------------------------------------------------------ functional
def cross_bilateral_denoise(
    noisy: torch.Tensor,
    guide: torch.Tensor,
    radius: int = 15,
    sigma_space: float | None = None,
    sigma_albedo: float = 0.05,
    sigma_normal: float = 0.1,
    sigma_depth: float = 0.1,
    border: str = "truncate",
    impl: str = "auto",
    max_cache_bytes: int = 2**30,
    check_finite: bool = True,
) -> torch.Tensor:
    """Cross-bilateral filter guided by G-buffers (Gu et al. 2024, Eqs. 5-6).

    Args:
        noisy: the noisy render.
        guide: G-buffers from :func:`torchir.functions.render_gbuffers` (albedo, normal, depth).
        radius: window half-width (window ``2r+1``).
        sigma_space: ``b_q`` in pixels (default ``radius / 3``).
        sigma_albedo, sigma_normal, sigma_depth: ``b_rho``, ``b_n``, ``b_d`` (depth is divided
            by the image's maximum depth first).
        border: ``"truncate"`` (window cut off at the image border) or ``"reflect"`` (mirrored
            pixels, spatial weight from their own position: the authors' released code).
        impl, max_cache_bytes, check_finite: as :func:`torchir.modules.target_aware_denoise`.

    Shape:
        noisy ``(B, C, H, W)`` or ``(C, H, W)``; guide ``(B|1, 7, H, W)`` or ``(7, H, W)``.

    Example:
        >>> guide = torch.rand(1, 7, 16, 16)
        >>> cross_bilateral_denoise(torch.rand(1, 3, 16, 16), guide, radius=3).shape
        torch.Size([1, 3, 16, 16])
    """
    bands = (sigma_albedo, sigma_normal, sigma_depth)
    return _denoise(_cross_bilateral_taps, noisy, guide, radius, sigma_space, bands, None, border, impl,
                    max_cache_bytes, check_finite, "cross_bilateral_denoise")


def gbuffer_regression_denoise(
    noisy: torch.Tensor,
    guide: torch.Tensor,
    radius: int = 15,
    sigma_space: float | None = None,
    sigma_albedo: float = 0.05,
    sigma_normal: float = 0.1,
    sigma_depth: float = 0.1,
    clamp_min: float | None = 0.0,
    border: str = "truncate",
    impl: str = "auto",
    max_cache_bytes: int = 2**30,
    check_finite: bool = True,
) -> torch.Tensor:
    """Local linear regression on G-buffers with cross-bilateral weights (Gu et al. 2024, Sec. 5,
    Moon et al. 2014): per pixel, ``f~_i ~ a + beta . [g_i - g_c, (i - c)/r]`` fitted with
    weights ``w^cb`` (Eq. 6) and ridge ``1e-3`` on every diagonal entry; the output is ``a``.
    As the released code, ``g`` are the raw G-buffers (albedo clamped to [0, 1], depth / max
    depth), not divided by the bandwidths, so the ridge acts in those units. Arguments as
    :func:`cross_bilateral_denoise`, plus ``clamp_min`` (output clamp ``max(clamp_min, a)`` with
    gradient ``1[a >= clamp_min]``; ``None`` = off).

    Example:
        >>> guide = torch.rand(1, 7, 16, 16)
        >>> gbuffer_regression_denoise(torch.rand(1, 3, 16, 16), guide, radius=2).shape
        torch.Size([1, 3, 16, 16])
    """
    bands = (sigma_albedo, sigma_normal, sigma_depth)
    return _denoise(_regression_taps, noisy, guide, radius, sigma_space, bands, clamp_min, border, impl,
                    max_cache_bytes, check_finite, "gbuffer_regression_denoise")


# --------------------------------------------------------------------------------- modules
class CrossBilateralDenoiser(nn.Module):
    """Module twin of :func:`cross_bilateral_denoise` (the denoiser signature of torchir).

    ``forward(noisy, target, guide, views=None)``: ``target`` and ``views`` are accepted for the
    common signature and unused; ``guide`` is required. No learnable parameters.

    Example:
        >>> den = CrossBilateralDenoiser(radius=3)
        >>> den(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16), guide=torch.rand(1, 7, 16, 16)).shape
        torch.Size([1, 3, 16, 16])
    """

    needs_guide = True  # the trainer renders G-buffers before the differentiable render
    _function = staticmethod(cross_bilateral_denoise)

    def __init__(
        self,
        radius: int = 15,
        sigma_space: float | None = None,
        sigma_albedo: float = 0.05,
        sigma_normal: float = 0.1,
        sigma_depth: float = 0.1,
        border: str = "truncate",
        impl: str = "auto",
        max_cache_bytes: int = 2**30,
        check_finite: bool = True,
        enabled: bool = True,
    ) -> None:
        super().__init__()
        check_hparams(radius, 1.0, impl, max_cache_bytes)
        _check_border(border)
        self.radius, self.sigma_space, self.border = radius, sigma_space, border
        self.sigma_albedo, self.sigma_normal, self.sigma_depth = sigma_albedo, sigma_normal, sigma_depth
        self.impl, self.max_cache_bytes, self.check_finite, self.enabled = impl, max_cache_bytes, check_finite, enabled

    def _options(self) -> dict[str, Any]:
        return dict(radius=self.radius, sigma_space=self.sigma_space, sigma_albedo=self.sigma_albedo,
                    sigma_normal=self.sigma_normal, sigma_depth=self.sigma_depth, border=self.border,
                    impl=self.impl, max_cache_bytes=self.max_cache_bytes, check_finite=self.check_finite)

    def forward(self, noisy: torch.Tensor, target: torch.Tensor | None = None, guide: torch.Tensor | None = None,
                views: Sequence[Any] | None = None) -> torch.Tensor:
        if not self.enabled:
            return noisy
        return type(self)._function(noisy, guide, **self._options())

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self._options().items()) + f", enabled={self.enabled}"


class GBufferRegressionDenoiser(CrossBilateralDenoiser):
    """Module twin of :func:`gbuffer_regression_denoise`; signature as :class:`CrossBilateralDenoiser`."""

    _function = staticmethod(gbuffer_regression_denoise)

    def __init__(self, radius: int = 15, clamp_min: float | None = 0.0, **options: Any) -> None:
        super().__init__(radius=radius, **options)
        self.clamp_min = clamp_min

    def _options(self) -> dict[str, Any]:
        return dict(super()._options(), clamp_min=self.clamp_min)
