"""Locally orderless images (LOI) loss: Wasserstein-1 between local intensity histograms.

Mehta, Chandraker and Ramamoorthi, "Locally Orderless Images for Optimization in Differentiable
Rendering" (CVPR 2025), "the paper" below; equation numbers are the paper's. Every pixel
becomes a local histogram of intensities: blur the image by the inner scale ``sigma`` (paper
Eq. 1-2), spread each value into a Gaussian over intensity of width ``beta`` (Eq. 3), and
average these over a spatial window of extent ``alpha`` (Eq. 4).
The loss is the 1-D Wasserstein-1 distance of rendered and reference local histograms per
pixel and channel, i.e. the L1 distance of their CDFs (Eq. 5, p = 1), summed over the
``sigma x alpha`` grid. Because a histogram keeps *which* intensities are nearby (not their
mean), a feature far from its target still gets a gradient towards the place where its own
intensity level is missing: the renderer's sparse RGB gradients reach much further.

The histogram is never materialised: with soft bins by the normal CDF ``Phi`` (each bin's exact
Gaussian mass), the local CDF at bin edge ``e_j`` is ``A_alpha * Phi((e_j - J_sigma) / beta)``,
and since the blur is linear, one blur of the *difference* of the two images' point CDFs per
scale suffices.
"""
from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import torch
from torch import nn

from . import _loi_native
from ._blur import blur
from ._loi_config import (FAST_CELL_FRACTION, LOI_PRESETS, TRANSFORMS, Transform, _as_batch, _config, _scales,
                          _transform, _weights)
from ._loi_terms import (_edges, _margin, _pad, _per_image, _point_cdf, _Prepared, _prepare, _reduce,
                         _scale_terms, _target_cdfs, _trim)
from ._warnings import user_stacklevel

__all__ = ["loi_loss", "LOILoss", "LOI_PRESETS", "TRANSFORMS", "FAST_CELL_FRACTION"]

__all__ = ["loi_loss", "LOILoss", "LOI_PRESETS", "TRANSFORMS"]

def loi_loss(
    rendered: torch.Tensor,
    target: torch.Tensor,
    alphas: Sequence[float] = (1, 5, 15, 45),
    sigmas: Sequence[float] = (1, 5),
    beta: float = 0.125,
    value_range: tuple[float, float] = (0.0, 1.0),
    tail: int = 3,
    transform: Transform = None,
    channels: str = "independent",
    border: str = "pad",
    pad_frac: float = 0.25,
    weights: Sequence[Sequence[float]] | None = None,
    relative: bool = False,
    truncate: float = 3.0,
    reduction: str = "mean",
    mask: torch.Tensor | None = None,
    low_memory: bool = False,
    cell_fraction: float | None = None,
    exact: bool = False,
) -> torch.Tensor:
    r"""Locally orderless images loss (Mehta et al. 2025, Eqs. 1-5): W1 between local histograms.

    .. math::
        E = \sum_{\sigma, \alpha} w_{\sigma\alpha} \frac{1}{C |\Omega|} \sum_{c, x} \beta \sum_j
            \big| A_\alpha * (\Phi(\tfrac{e_j - J'_\sigma}{\beta}) - \Phi(\tfrac{e_j - J^{gt}_\sigma}{\beta})) \big|(x)

    Args:
        rendered: the rendered image (gradients flow to it).
        target: the reference image (treated as constant).
        alphas: extent scales (aperture std-devs in pixels; 0 = none), paper Eq. 4.
        sigmas: inner scales (image blur std-devs in pixels; 0 = none), paper Eq. 1.
        beta: tonal scale = bin width, paper Eq. 3.
        value_range: ``(k_lo, k_hi)`` of the histogram bins.
        tail: extra bins on each side of the range (0 = paper-literal ``k in [0, 1]``).
        transform: intensity map applied to both images first: ``None``/``"identity"``,
            ``"clamp"`` (to ``value_range``), ``"reinhard"`` (``x/(1+x)``, for HDR renders),
            ``"log1p"``, or a callable.
        channels: ``"independent"`` (per-channel marginals, averaged) or ``"luminance"``.
        border: ``"pad"`` (a constant margin of ``pad_frac * max(H, W)`` pixels around both
            images, which keeps the gradient's sign right near the frame) or ``"renormalize"``
            (border-renormalised blurs only).
        weights: ``(len(sigmas), len(alphas))`` per-term weights (default all 1).
        relative: scales are fractions of ``min(H, W)`` instead of pixels.
        truncate: Gaussian kernels are cut at ``truncate`` std-devs (capped at the image size).
        reduction: ``"mean"`` / ``"sum"`` over the batch, or ``"none"`` for ``(B,)``.
        mask: ``(B, 1|C, H, W)`` non-negative per-pixel weights of the W1 terms.
        low_memory: recompute the big tensors in backward instead of storing them (the torch
            path; the fused kernel, float32 on the CPU, stores none of them anyway).
        cell_fraction: speed for accuracy. Each ``alpha`` term takes ``|A_alpha * D|`` on the
            exact means of ``floor(cell_fraction * alpha)``-pixel cells instead of on every
            pixel (0 = every pixel, the exact loss; ``None`` = 0.15, or 0 with ``exact``), and
            ``D`` is averaged over cells of at most ``0.15 alpha`` px before the blur. The
            blurred field is smooth at scale ``alpha``, so only cells that straddle one of its
            zero crossings differ; ``torchir bench loi`` measures speed and loss/gradient error.
        exact: evaluate every term on every pixel (the paper's loss). The default evaluates
            large-``alpha`` terms on cells (``cell_fraction=0.15``: at ``alphas=(1, 5, 15, 45)``
            the last two on 2 and 6 px cells): close to the exact loss and its gradient in a
            fraction of the time (measured: docs/loi.md, "Measurements behind the design").

    Returns:
        A scalar (``(B,)`` for ``reduction="none"``). Each term is a mean over channels and
        pixels, so identical images give 0 and constant images ``a, b`` (in range) give
        ``len(sigmas) * len(alphas) * |a - b|``.

    Shape:
        rendered, target: ``(B, C, H, W)`` or ``(C, H, W)``, same shape.

    Example:
        >>> x, y = torch.rand(1, 3, 32, 32, requires_grad=True), torch.rand(1, 3, 32, 32)
        >>> loi_loss(x, y, alphas=(1, 5), sigmas=(1,)).backward()
    """
    cfg = _config(alphas, sigmas, beta, value_range, tail, transform, channels, border, pad_frac, weights, relative, truncate, reduction, low_memory, cell_fraction, exact)
    p = _prepare(rendered, target, mask, cfg)
    return _reduce(_per_image(p, cfg, _target_cdfs(p, cfg)), cfg.reduction)


class LOILoss(nn.Module):
    """Module twin of :func:`loi_loss`, with target-side caching, presets and inspection.

    The reference's point CDFs (one ``(B, C, K, H, W)`` tensor per inner scale) are cached
    for the last ``cache_target`` distinct targets (``True`` = 1, ``False``/0 = off), keyed on
    the tensor (same object and version, or equal content), so a fixed reference is processed
    once per run.

    Args:
        See :func:`loi_loss`; ``cache_target`` as above.

    Example:
        >>> loss_fn = LOILoss.preset("pathtracing", transform="reinhard")
        >>> rendered, target = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
        >>> loss = loss_fn(rendered, target)          # (B, C, H, W) each -> scalar
        >>> terms = loss_fn.terms(rendered, target)   # {(sigma, alpha): value}
        >>> sorted(terms)[0], loss.shape
        ((1.0, 1.0), torch.Size([]))
    """

    pixelwise = False  # local histograms couple pixels: not usable with pixel sampling

    def __init__(
        self,
        alphas: Sequence[float] = (1, 5, 15, 45),
        sigmas: Sequence[float] = (1, 5),
        beta: float = 0.125,
        value_range: tuple[float, float] = (0.0, 1.0),
        tail: int = 3,
        transform: Transform = None,
        channels: str = "independent",
        border: str = "pad",
        pad_frac: float = 0.25,
        weights: Sequence[Sequence[float]] | None = None,
        relative: bool = False,
        truncate: float = 3.0,
        reduction: str = "mean",
        cache_target: bool | int = True,
        low_memory: bool = False,
        cell_fraction: float | None = None,
        exact: bool = False,
    ) -> None:
        super().__init__()
        self.cfg = _config(
            alphas, sigmas, beta, value_range, tail, transform, channels, border, pad_frac, weights, relative, truncate, reduction, low_memory, cell_fraction, exact
        )
        if isinstance(cache_target, bool):
            cache_target = int(cache_target)
        if not isinstance(cache_target, int) or cache_target < 0:
            raise ValueError(f"cache_target must be a bool or an int >= 0, got {cache_target!r}")
        self.cache_size = cache_target
        self._cache: OrderedDict[int, tuple[torch.Tensor, int, tuple, torch.Tensor, list[torch.Tensor]]] = OrderedDict()
        self._warned: set[str] = set()  # out-of-range warnings already given (once per image role)
        self.cache_hits = 0
        self._memory_warned = False

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> LOILoss:
        """The paper's settings: ``"disks"`` (section 4.1), ``"pathtracing"`` (4.2, the default
        scales) or ``"raster"`` (4.4); keyword arguments override single options."""
        if name not in LOI_PRESETS:
            raise ValueError(f"unknown LOI preset {name!r}; choose from {sorted(LOI_PRESETS)}")
        return cls(**{**LOI_PRESETS[name], **overrides})

    # ------------------------------------------------------------------------ options
    def __getattr__(self, name: str) -> Any:
        cfg = self.__dict__.get("cfg")
        if cfg is not None and name in cfg.__dataclass_fields__:
            return getattr(cfg, name)
        return super().__getattr__(name)

    @property
    def n_terms(self) -> int:
        return self.cfg.n_terms

    def set_scales(self, alphas: Sequence[float] | None = None, sigmas: Sequence[float] | None = None, weights: Any = None) -> None:
        """Change the scale grid (a hook for schedules); clears the target cache."""
        alphas = self.cfg.alphas if alphas is None else _scales("alphas", alphas)
        sigmas = self.cfg.sigmas if sigmas is None else _scales("sigmas", sigmas)
        self.cfg = replace(self.cfg, alphas=alphas, sigmas=sigmas, weights=_weights(weights, len(sigmas), len(alphas)))
        self.clear_cache()

    def clear_cache(self) -> None:
        self._cache.clear()

    def extra_repr(self) -> str:
        c = self.cfg
        return (
            f"alphas={c.alphas}, sigmas={c.sigmas}, beta={c.beta}, value_range={c.value_range}, tail={c.tail}, "
            f"transform={c.transform!r}, border={c.border!r}, relative={c.relative}, reduction={c.reduction!r}, "
            f"low_memory={c.low_memory}, cell_fraction={c.cell_fraction} ({'exact' if c.cell_fraction == 0 else 'cells'})"
        )

    # ------------------------------------------------------------------------ forward
    def _target_cdfs(self, target: torch.Tensor, p: _Prepared) -> list[torch.Tensor]:
        if self.cache_size == 0:
            return _target_cdfs(p, self.cfg)
        key = (tuple(p.target.shape), p.target.dtype, p.target.device, p.margin, _loi_native.usable(p.target))  # (the Phi used)
        for k, (ref, version, ref_key, snapshot, z) in self._cache.items():
            if ref_key != key or snapshot.shape != target.shape:
                continue
            if ref is target and ref._version == version:
                hit = True  # the same, unmodified tensor: no comparison needed
            else:  # e.g. a collated copy of the same reference; compare with the snapshot
                hit = torch.equal(snapshot, target.detach())
            if hit:
                self._cache.move_to_end(k)
                self.cache_hits += 1
                return z
        with torch.no_grad():
            z = _target_cdfs(p, self.cfg)
        # holding the tensor keeps its id unique while cached; the snapshot guards in-place edits
        self._cache[id(target)] = (target, target._version, key, target.detach().clone(), z)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return z

    def _warn_memory(self, p: _Prepared) -> None:
        est = self.memory_estimate(p.shape, p.rendered.dtype)
        if est > 2**31 and not self.cfg.low_memory and not self._memory_warned:
            self._memory_warned = True
            warnings.warn(f"LOI loss needs ~{est / 2**30:.1f} GiB for autograd at {p.shape}: consider low_memory=True", stacklevel=user_stacklevel())

    def forward(self, rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        p = _prepare(rendered, target, mask, self.cfg, self._warned)
        self._warn_memory(p)
        return _reduce(_per_image(p, self.cfg, self._target_cdfs(target, p)), self.cfg.reduction)

    # ------------------------------------------------------------------------ inspection
    def terms(self, rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> dict[tuple[float, float], torch.Tensor]:
        """Unweighted per-scale values ``{(sigma, alpha): E(sigma, alpha)}`` (batch mean,
        detached), keyed by the configured (possibly relative) scales; for logging."""
        with torch.no_grad():
            p = _prepare(rendered, target, mask, self.cfg, self._warned)
            out = {}
            for s_cfg, s, zt, plan, k in zip(self.cfg.sigmas, p.sigmas, _target_cdfs(p, self.cfg), p.plans, p.trims):
                d = _point_cdf(_trim(blur(p.rendered, s, self.cfg.truncate), k), p.edges, self.cfg.beta) - zt
                for a_cfg, v in zip(self.cfg.alphas, _scale_terms(d, plan, self.cfg.beta, p.pw, self.cfg.truncate)):
                    out[(s_cfg, a_cfg)] = v.mean()
            return out

    def cdfs(self, img: torch.Tensor, sigma: float, alpha: float) -> torch.Tensor:
        """Local CDFs at the bin edges, ``(B, C, K, H, W)``, ``K = N + 2 tail + 1``
        (computed with this loss's transform, border and scale units)."""
        x = _as_batch("img", img)
        j = _transform(x, self.cfg)
        b, c, h, w = j.shape
        m = _margin(h, w, self.cfg)
        f = float(min(h, w)) if self.cfg.relative else 1.0
        sigma, alpha = _scales("sigma", sigma)[0] * f, _scales("alpha", alpha)[0] * f
        z = _point_cdf(blur(_pad(j, m, self.cfg.value_range[0]), sigma, self.cfg.truncate), _edges(self.cfg, j.dtype, j.device), self.cfg.beta)
        z = blur(z, alpha, self.cfg.truncate)
        return z[..., m : m + h, m : m + w] if m else z

    def histograms(self, img: torch.Tensor, sigma: float, alpha: float) -> torch.Tensor:
        """The locally orderless image (Eq. 4): local histograms ``(B, C, K + 1, H, W)`` whose
        bins are ``(-inf, e_0), [e_0, e_1), ..., [e_{K-1}, inf)``; they sum to 1 per pixel."""
        cdf = self.cdfs(img, sigma, alpha)
        zero = torch.zeros_like(cdf[:, :, :1])
        return torch.diff(cdf, dim=2, prepend=zero, append=torch.ones_like(zero))

    def memory_estimate(self, shape: Sequence[int], dtype: torch.dtype = torch.float32) -> int:
        """Approximate peak bytes of one forward + backward at image ``shape`` ((B,)C,H,W)
        on the torch path: backward keeps ~``2 + len(alphas)`` ``(B, C, K, Hp, Wp)`` tensors per
        sigma (low-memory mode: ~5 in all), plus the cached target CDFs (one per sigma). An
        upper bound: the small-alpha terms of ``border="pad"``, ``cell_fraction`` and the fused
        kernel (float32 on the CPU: one such tensor at a time, plus the cache) need less."""
        shape = tuple(shape) if len(shape) == 4 else (1, *shape)
        b, c, h, w = shape
        c = 1 if self.cfg.channels == "luminance" else c
        m = _margin(h, w, self.cfg)
        k = len(_edges(self.cfg, torch.float64, torch.device("cpu")))
        big = b * c * k * (h + 2 * m) * (w + 2 * m) * torch.empty((), dtype=dtype, device="cpu").element_size()
        n_s, n_a = len(self.cfg.sigmas), len(self.cfg.alphas)
        return big * ((5 if self.cfg.low_memory else (2 + n_a) * n_s) + n_s)
