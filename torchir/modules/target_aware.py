"""Target-aware image denoising for inverse rendering (Gu et al. 2024).

Gu, Back, Yoon and Moon, "Target-Aware Image Denoising for Inverse Monte Carlo Rendering"
(SIGGRAPH 2024), "the paper" below; equation numbers are the paper's. Each pixel ``c`` of the
noisy render ``f~`` is fitted, per channel, as an affine function of the *target* colour over
its ``(2r+1)^2`` window (truncated at the image border), with weights that depend only on the
target:

    w_{i|c} = exp(-||log(1+I_i) - log(1+I_c)||^2 / (2 b^2))                 (Eq. 9)
    (a_c, b_c) = argmin sum_i w_{i|c} (f~_i - a - b (I_i - I_c))^2            (Eq. 8)
    f^_c = a_c = sum_i l_{i|c} f~_i                                           (Eq. 11)

The smoother weights ``l`` depend only on the target, so the denoiser is one constant linear
operator ``L``: forward ``L f~``, backward ``L^T g`` (Eq. 12). Both run as loops over
the window's taps (``_Gather`` / ``_Scatter`` of :mod:`._windows`, autograd Functions, each the other's
backward, so double backward works too); the taps are built once per target and cached.

Memory: the coefficient maps cost ``O(C H W)``; the full tap table ``l`` costs
``(2r+1)^2 C H W`` numbers and is kept only when it fits ``max_cache_bytes`` (else each pass
recomputes the taps on the fly, slower but bounded).
"""
from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ._warnings import user_stacklevel
from ._windows import (_MAX_CACHE_ENTRIES, _finish, _Taps, apply_taps, check_hparams, check_mask, check_pair, choose_table,
                       serial_for, to_batch)

__all__ = ["TargetAwareDenoiser", "target_aware_denoise", "target_aware_denoise_reference"]

_WEIGHT_MODES = ("rgb", "per_channel")

# ------------------------------------------------------------------- target-aware weights
def _log_target(t: torch.Tensor, weight_mode: str) -> torch.Tensor:
    """``log(1 + max(I, 0))`` of the channels the weights use (Gu et al. 2024, Eq. 9)."""
    if bool((t <= -1).any()):
        raise ValueError("target has values <= -1: the weights use log(1 + I), which is undefined there")
    if bool((t < 0).any()):
        warnings.warn("target has negative values: the weights clamp them at 0 (log(1 + max(I, 0)))", stacklevel=user_stacklevel())
    if weight_mode == "rgb" and t.shape[1] >= 3:
        t = t[:, :3]
    return torch.log1p(t.clamp_min(0))


def _target_taps(
    target: torch.Tensor,
    mask: torch.Tensor | None,
    radius: int,
    bandwidth: float,
    order: int,
    weight_mode: str,
    var_floor: float,
    dtype: torch.dtype,
) -> _Taps:
    """The taps ``l_delta(c) = w_delta(c) (a_c + b_c (I_{c+delta} - I_c))`` of one target.

    Moments are accumulated in float64 (Gu et al. 2024, Eq. 10 solved in closed form):
    ``S0 = sum w``, ``x_mean = sum w x / S0``, ``v = sum w x^2 / S0 - x_mean^2`` with
    ``x = I_i - I_c``; then ``a = (1 + x_mean^2 / v*) / S0`` and ``b = -x_mean / (v* S0)``,
    ``v* = max(v, var_floor)``, so that ``sum_i l_{i|c} = 1`` exactly and
    ``sum_i l_{i|c} (I_i - I_c) = 0`` whenever ``v >= var_floor``.
    Masked-out pixels (mask 0) take part in no window and pass through unchanged.
    """
    r = radius
    B, _, H, W = target.shape
    I = target.to(torch.float64)
    L = _log_target(I, weight_mode)  # (B, 3|C, H, W)
    inv_2b2 = 1.0 / (2.0 * bandwidth * bandwidth)
    m = torch.ones(1, 1, H, W, dtype=torch.float64, device=I.device) if mask is None else mask
    I_pad, L_pad, m_pad = (F.pad(x, (r, r, r, r)) for x in (I, L, m))  # zero pad: m_pad = 0 outside

    def weight(dy: int, dx: int, L: torch.Tensor, L_pad: torch.Tensor, m: torch.Tensor, m_pad: torch.Tensor) -> torch.Tensor:
        if dy == r and dx == r:  # w_{c|c} = 1 (also for masked centres: they keep their own value)
            return torch.ones_like(m)
        d2 = (L_pad[..., dy : dy + H, dx : dx + W] - L).square()  # Gu et al. 2024, Eq. 9
        if weight_mode == "rgb":
            d2 = d2.sum(1, keepdim=True)
        inside = m_pad[..., dy : dy + H, dx : dx + W] if mask is None else m * m_pad[..., dy : dy + H, dx : dx + W]
        return torch.exp(d2 * -inv_2b2).mul_(inside)

    S0 = torch.zeros(B, 1, H, W, dtype=torch.float64, device=I.device)
    Sx = torch.zeros_like(I)
    Sxx = torch.zeros_like(I)
    K = 2 * r + 1
    for k in range(K * K):
        dy, dx = divmod(k, K)
        w = weight(dy, dx, L, L_pad, m, m_pad)
        S0 = S0 + w
        if order == 1:
            x = I_pad[..., dy : dy + H, dx : dx + W] - I
            Sx.addcmul_(w, x)
            Sxx.addcmul_(w, x.square())
    if order == 0:  # Nadaraya-Watson ablation (Gu et al. 2024, Sec. 4.1, Fig. 4)
        a, b = 1.0 / S0, None
    else:
        x_mean = Sx / S0
        v_star = (Sxx / S0 - x_mean.square()).clamp_min(0.0).clamp_min(var_floor)
        a = (1.0 + x_mean.square() / v_star) / S0
        b = -x_mean / (v_star * S0)

    # Per-call taps in the caller's dtype; recomputed on the fly when there is no table.
    I_d, I_pad_d, L_d, L_pad_d, m_d, m_pad_d = (x.to(dtype) for x in (I, I_pad, L, L_pad, m, m_pad))
    a_d = a.to(dtype)
    b_d = None if b is None else b.to(dtype)

    def tap(dy: int, dx: int) -> torch.Tensor:
        w = weight(dy, dx, L_d, L_pad_d, m_d, m_pad_d)
        if b_d is None:
            return w * a_d
        x = I_pad_d[..., dy : dy + H, dx : dx + W] - I_d
        return torch.addcmul(a_d, b_d, x).mul_(w)  # l_{c+delta|c}, Gu et al. 2024, Eq. 11

    return _Taps(r, (H, W), tap)


def _build_taps(
    target: torch.Tensor,
    mask: torch.Tensor | None,
    dtype: torch.dtype,
    radius: int,
    bandwidth: float,
    order: int,
    weight_mode: str,
    var_floor: float,
    impl: str,
    max_cache_bytes: int,
) -> _Taps:
    with torch.no_grad(), serial_for(target.numel()):
        taps = _target_taps(target, mask, radius, bandwidth, order, weight_mode, var_floor, dtype)
        choose_table(taps, torch.empty((), dtype=dtype, device=target.device), impl, max_cache_bytes, "target_aware_denoise")
    return taps


def _check_options(order: int, weight_mode: str, var_floor: float, clamp_min: float | None) -> None:
    if order not in (0, 1):
        raise ValueError(f"order must be 0 or 1 (the paper found no gain from higher orders), got {order!r}")
    if weight_mode not in _WEIGHT_MODES:
        raise ValueError(f"weight_mode must be one of {_WEIGHT_MODES}, got {weight_mode!r}")
    if not (var_floor > 0 and math.isfinite(var_floor)):
        raise ValueError(f"var_floor must be > 0, got {var_floor!r}")
    if clamp_min is not None and not math.isfinite(clamp_min):
        raise ValueError(f"clamp_min must be finite or None, got {clamp_min!r}")


def target_aware_denoise(
    noisy: torch.Tensor,
    target: torch.Tensor,
    radius: int = 15,
    bandwidth: float = 0.1,
    order: int = 1,
    weight_mode: str = "rgb",
    var_floor: float = 1e-7,
    clamp_min: float | None = 0.0,
    mask: torch.Tensor | None = None,
    impl: str = "auto",
    max_cache_bytes: int = 2**30,
    check_finite: bool = True,
) -> torch.Tensor:
    """Denoise a Monte Carlo render by local linear regression on the target (Gu et al. 2024).

    ``f^_c = sum_{i in window(c)} l_{i|c} f~_i`` with ``l`` from the weighted least-squares fit
    ``f~_i ~ a_c + b_c (I_i - I_c)`` (Eqs. 8-11), weights ``exp(-||log(1+I_i) - log(1+I_c)||^2
    / (2 bandwidth^2))`` (Eq. 9). Linear in ``noisy``; the backward is the exact transpose (Eq. 12).
    No gradient flows to ``target``. This function builds the taps on every call; the module
    :class:`TargetAwareDenoiser` caches them per target.

    Args:
        noisy: the noisy render ``f~``.
        target: the target image ``I`` (batch 1 or the batch of ``noisy``), treated as a constant.
        radius: window half-width ``r`` (window ``(2r+1)^2``, truncated at the border); 0 = identity.
        bandwidth: ``b^I`` in log(1 + colour) units.
        order: 1 (local linear, the paper's method) or 0 (weighted mean, an ablation).
        weight_mode: ``"rgb"`` (one weight per pixel pair from the first 3 channels) or
            ``"per_channel"``.
        var_floor: floor of the weighted target variance in the 2x2 solve (flat windows).
        clamp_min: output clamp ``max(clamp_min, f^)``, gradient ``1[f^ >= clamp_min]`` (as the
            released code); ``None`` = the pure linear smoother.
        mask: bool ``(H,W)`` or ``(B|1,1,H,W)``: ``False`` pixels take part in no regression and
            pass through unchanged (background, invalid pixels).
        impl: ``"auto"`` (tap table when it fits ``max_cache_bytes``, else taps on the fly),
            ``"taps"`` (always on the fly: memory ``O(C H W)``), ``"cached"`` (table, or a
            ``ValueError`` when over budget).
        max_cache_bytes: memory budget of the tap table.
        check_finite: raise ``ValueError`` on NaN/Inf in ``noisy`` or ``target``.

    Returns:
        the denoised image, same shape and dtype as ``noisy``.

    Shape:
        noisy: ``(B, C, H, W)`` or ``(C, H, W)``; target: same, or ``(1, C, H, W)``.

    Example:
        >>> target = torch.rand(1, 3, 32, 32)
        >>> noisy = target + 0.1 * torch.randn(1, 3, 32, 32)
        >>> target_aware_denoise(noisy, target, radius=3).shape
        torch.Size([1, 3, 32, 32])
    """
    check_hparams(radius, bandwidth, impl, max_cache_bytes)
    _check_options(order, weight_mode, var_floor, clamp_min)
    y, t = check_pair(noisy, target, check_finite)
    m = check_mask(mask, y)
    taps = _build_taps(t, m, y.dtype, radius, bandwidth, order, weight_mode, var_floor, impl, max_cache_bytes)
    return _finish(apply_taps(y, taps), clamp_min, noisy)


def target_aware_denoise_reference(
    noisy: torch.Tensor,
    target: torch.Tensor,
    radius: int = 15,
    bandwidth: float = 0.1,
    order: int = 1,
    weight_mode: str = "rgb",
    clamp_min: float | None = 0.0,
) -> torch.Tensor:
    """Slow, obviously-correct reference: per pixel and channel, a weighted least-squares solve
    of Eq. 10 with ``torch.linalg.lstsq`` on the explicit design matrix (no variance floor).
    For tests on tiny images only. Shapes as :func:`target_aware_denoise`; float64 output."""
    y, t = to_batch(noisy, "noisy").double(), to_batch(target, "target").double()
    B, C, H, W = y.shape
    t = t.expand(B, -1, -1, -1)
    L = torch.log1p(t.clamp_min(0))
    Lw = L[:, :3] if weight_mode == "rgb" and C >= 3 else L
    out = torch.empty_like(y)
    for n in range(B):
        for i in range(H):
            for j in range(W):
                i0, i1, j0, j1 = max(0, i - radius), min(H, i + radius + 1), max(0, j - radius), min(W, j + radius + 1)
                d2 = (Lw[n, :, i0:i1, j0:j1] - Lw[n, :, i : i + 1, j : j + 1]).square()
                w_all = torch.exp(-(d2.sum(0, keepdim=True) if weight_mode == "rgb" else d2) / (2 * bandwidth**2))
                for c in range(C):
                    w = w_all[0 if weight_mode == "rgb" else c].reshape(-1)
                    x = (t[n, c, i0:i1, j0:j1] - t[n, c, i, j]).reshape(-1)
                    X = torch.stack([torch.ones_like(x), x], 1)[:, : order + 1]  # rows [1, I_i - I_c]
                    Y = y[n, c, i0:i1, j0:j1].reshape(-1, 1)
                    sw = w.sqrt().unsqueeze(1)
                    coef = torch.linalg.lstsq(sw * X, sw * Y, driver="gelsd").solution  # Eq. 10
                    out[n, c, i, j] = coef[0, 0]
    if clamp_min is not None:
        out = out.clamp_min(clamp_min)
    return out.squeeze(0) if noisy.dim() == 3 else out


# ---------------------------------------------------------------------------------- module
class TargetAwareDenoiser(nn.Module):
    """Module twin of :func:`target_aware_denoise` that caches the taps per target.

    The cache is keyed by ``views`` (a list of view ids; ``None`` = one shared slot), shape,
    dtype and device, and checked against a copy of the target (and mask) on every call, so an
    in-place change of the target rebuilds it. ``enabled=False`` returns ``noisy`` unchanged
    (e.g. for the last, bias-free iterations of a run). No learnable parameters.

    Example:
        >>> den = TargetAwareDenoiser(radius=7)
        >>> target = torch.rand(2, 3, 32, 32)
        >>> den(target + 0.1 * torch.randn_like(target), target, views=[0, 1]).shape
        torch.Size([2, 3, 32, 32])
    """

    needs_guide = False  # weights come from the target only (no G-buffers)

    def __init__(
        self,
        radius: int = 15,
        bandwidth: float = 0.1,
        order: int = 1,
        weight_mode: str = "rgb",
        var_floor: float = 1e-7,
        clamp_min: float | None = 0.0,
        impl: str = "auto",
        max_cache_bytes: int = 2**30,
        check_finite: bool = True,
        enabled: bool = True,
    ) -> None:
        super().__init__()
        check_hparams(radius, bandwidth, impl, max_cache_bytes)
        _check_options(order, weight_mode, var_floor, clamp_min)
        self.radius, self.bandwidth, self.order, self.weight_mode = radius, float(bandwidth), order, weight_mode
        self.var_floor, self.clamp_min, self.impl = float(var_floor), clamp_min, impl
        self.max_cache_bytes, self.check_finite, self.enabled = int(max_cache_bytes), check_finite, enabled
        self._cache: OrderedDict[tuple, tuple[torch.Tensor, torch.Tensor | None, _Taps]] = OrderedDict()

    # ------------------------------------------------------------------ cache
    def clear_cache(self) -> None:
        self._cache.clear()

    def _cache_bytes(self) -> int:
        return sum(e[2].table.numel() * e[2].table.element_size() for e in self._cache.values() if e[2].table is not None)

    def _taps(self, y: torch.Tensor, t: torch.Tensor, m: torch.Tensor | None, views: Sequence[Any] | None) -> _Taps:
        key = (None if views is None else tuple(views), tuple(t.shape), y.dtype, y.device)
        entry = self._cache.get(key)
        if entry is not None:
            t_old, m_old, taps = entry
            same_mask = (m is None and m_old is None) or (m is not None and m_old is not None and torch.equal(m, m_old))
            if same_mask and torch.equal(t, t_old):  # also catches in-place edits of the target
                self._cache.move_to_end(key)
                return taps
            del self._cache[key]
        budget = self.max_cache_bytes - self._cache_bytes()
        taps = _build_taps(t, m, y.dtype, self.radius, self.bandwidth, self.order, self.weight_mode,
                           self.var_floor, "taps", 0)
        if self.impl != "taps":
            need = taps.table_bytes(y)
            while need > budget and self._cache:  # evict least recently used tables first
                self._cache.popitem(last=False)
                budget = self.max_cache_bytes - self._cache_bytes()
            with torch.no_grad():
                choose_table(taps, y, self.impl, budget, "TargetAwareDenoiser")
        self._cache[key] = (t.clone(), None if m is None else m.clone(), taps)
        while len(self._cache) > _MAX_CACHE_ENTRIES:
            self._cache.popitem(last=False)
        return taps

    def set_target(self, target: torch.Tensor, mask: torch.Tensor | None = None, views: Sequence[Any] | None = None,
                   dtype: torch.dtype = torch.float32) -> None:
        """Build (or reuse) the taps of ``target`` ahead of the first :meth:`forward`."""
        t = to_batch(target, "target").detach()
        self._taps(t.new_empty(t.shape, dtype=dtype), t, check_mask(mask, t), views)

    # ---------------------------------------------------------------- forward
    def forward(
        self,
        noisy: torch.Tensor,
        target: torch.Tensor,
        guide: torch.Tensor | None = None,
        views: Sequence[Any] | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Denoised ``noisy`` (same shape); ``guide`` is accepted for the common denoiser
        signature and ignored (the weights come from ``target`` only)."""
        if not self.enabled:
            return noisy
        y, t = check_pair(noisy, target, self.check_finite)
        m = check_mask(mask, y)
        if views is not None and len(views) != y.shape[0]:
            raise ValueError(f"views has {len(views)} ids for a batch of {y.shape[0]} images")
        taps = self._taps(y, t, m, views)
        return _finish(apply_taps(y, taps), self.clamp_min, noisy)

    # ------------------------------------------------------------ diagnostics
    def smoother_weights(self, target: torch.Tensor, mask: torch.Tensor | None = None, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """The smoother weights ``l_{c+delta|c}`` as ``(B, C, K*K, H, W)``, offsets in row-major
        order (``delta = (k // K - r, k % K - r)``), zero outside the image. For analysis/tests."""
        t = to_batch(target, "target").detach()
        taps = _build_taps(t, check_mask(mask, t), dtype, self.radius, self.bandwidth, self.order,
                           self.weight_mode, self.var_floor, "taps", 0)
        B, C, H, W = t.shape
        return torch.stack([l.expand(B, C, H, W) for _, _, l in taps.taps()], 2)

    def propagated_variance(self, variance: torch.Tensor, target: torch.Tensor, views: Sequence[Any] | None = None) -> torch.Tensor:
        """``Var[f^_c] = sum_i l_{i|c}^2 sigma_i^2`` for independent pixel noise of variance
        ``variance`` (same shape as the images); ``variance = 1`` gives the variance-reduction
        factor, and ``1 / factor`` the effective number of neighbours."""
        y, t = check_pair(variance, target, self.check_finite)
        with torch.no_grad():
            out = self._taps(y, t, None, views).gather(y, squared=True)
        return out.squeeze(0) if variance.dim() == 3 else out

    def extra_repr(self) -> str:
        return (
            f"radius={self.radius}, bandwidth={self.bandwidth}, order={self.order}, "
            f"weight_mode={self.weight_mode!r}, var_floor={self.var_floor}, clamp_min={self.clamp_min}, "
            f"impl={self.impl!r}, max_cache_bytes={self.max_cache_bytes}, enabled={self.enabled}"
        )
