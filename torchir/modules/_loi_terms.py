"""The LOI loss's computation: the images' point CDFs at the bin edges, the aperture blurs of
their difference (banded, on cells where the aperture is wide) and the per-term Wasserstein-1
values, with a hand-written backward per inner scale (:class:`_SigmaTerm`)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Union

import torch
import torch.nn.functional as F

from . import _loi_native
from ._banded import sandwich, sandwich_adjoint
from ._blur import MIN_SCALE, blur, cell_means, gaussian_matrix
from ._loi_config import _as_batch, _check_mask, _Config, _transform, _warn_out_of_range

# A cell term's input is averaged over cells of at most POOL_FRACTION * alpha px before its blur.
# Coarser output cells keep this input grid: averaged over the output's own cells, cell_fraction
# 0.5 measured 3.4 % gradient error on glossy_highlight (2.6 % with this cap) and a displaced
# disk's gradient moved by 10 % (tests/modules/test_loi.py, within 5 % with it).
POOL_FRACTION = 0.15
_SQRT_HALF = math.sqrt(0.5)


def _phi_cdf(u: torch.Tensor) -> torch.Tensor:
    """``Phi(u)`` through ``erfc``, which torch vectorises (``torch.special.ndtr`` does not, and
    is slower for the same values; measured: docs/loi.md, "Measurements behind the design")."""
    return torch.erfc(u * -_SQRT_HALF).mul_(0.5)


def _margin(h: int, w: int, cfg: _Config) -> int:
    return math.ceil(cfg.pad_frac * max(h, w)) if cfg.border == "pad" else 0


def _pad(x: torch.Tensor, m: int, value: float) -> torch.Tensor:
    # A constant margin, identical in both images, keeps the gradient's sign right
    # near the frame, where renormalised borders flip it
    return F.pad(x, (m, m, m, m), value=value) if m else x


def _pixel_scales(cfg: _Config, h: int, w: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Scales in pixels (``relative`` scales are fractions of ``min(H, W)``)."""
    f = float(min(h, w)) if cfg.relative else 1.0
    fix = lambda s: 0.0 if s * f < MIN_SCALE else s * f  # noqa: E731
    return tuple(fix(s) for s in cfg.sigmas), tuple(fix(a) for a in cfg.alphas)


def _edges(cfg: _Config, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The ``K = N + 2T + 1`` bin edges ``lo + j beta``, ``j = -T .. N + T``."""
    lo, hi = cfg.value_range
    n = max(1, round((hi - lo) / cfg.beta))
    j = torch.arange(-cfg.tail, n + cfg.tail + 1, dtype=torch.float64, device="cpu")
    return (lo + j * cfg.beta).to(dtype=dtype, device=device)


def _point_cdf(j_sigma: torch.Tensor, edges: torch.Tensor, beta: float) -> torch.Tensor:
    """Point CDFs at the bin edges, before the aperture: ``Phi((e_j - J_sigma(x)) / beta)``,
    ``(B, C, K, H, W)``; by the fused kernel's ``Phi`` where that kernel will take the difference
    (see ``_loi_native``)."""
    if _loi_native.usable(j_sigma) and not (j_sigma.requires_grad and torch.is_grad_enabled()):
        return _loi_native.point_cdf(j_sigma, edges, beta)
    return _phi_cdf((edges.view(1, 1, -1, 1, 1) - j_sigma.unsqueeze(2)) / beta)


def _pixel_weights(b: int, h: int, w: int, m: int, mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """Per-pixel weights of the W1 terms (Eq. 5) on the (padded) canvas, ``(B, 1|C, Hp, Wp)``.

    The loss is a mean over the image's pixels; the margin of ``border="pad"`` is summed
    with the same weight (normalised by the *unpadded* pixel count, so values are comparable
    with ``border="renormalize"``). A mask weights image pixels (normalised by its sum); the
    margin keeps weight 1."""
    if mask is None:
        return like.new_full((b, 1, h + 2 * m, w + 2 * m), 1.0 / (h * w))
    norm = mask.mean(1, keepdim=True).flatten(1).sum(1).view(b, 1, 1, 1)
    return _pad(mask, m, 1.0) / norm


@dataclass(frozen=True)
class _Term:
    """How one ``(sigma, alpha)`` term is evaluated on the padded canvas.

    ``trim``: pixels dropped on every side of the canvas. With ``border="pad"`` the CDF
    difference is exactly 0 farther than ``r_sigma`` from the image, so after the aperture blur
    nothing is left beyond ``r_sigma + r_alpha``; the renormalised blur on a canvas cropped to
    ``r_sigma + 2 r_alpha + 1`` therefore gives the same values (exact, only cheaper).
    ``cell``: the term's ``|A_alpha * D|`` is evaluated on the means of ``cell x cell`` blocks
    (1 = every pixel, exact; see ``cell_fraction``). ``pool``: ``D`` is first averaged over
    ``pool x pool`` blocks (at most ``POOL_FRACTION * alpha``; 1 = not at all)."""

    alpha: float
    weight: float
    trim: int
    cell: int
    pool: int = 1  # the input's averaging cells (1: none)


def _reach(scale: float, truncate: float) -> int:
    return 0 if scale < MIN_SCALE else math.ceil(truncate * scale)


def _support_trim(sigma: float, margin: int, cfg: _Config) -> int:
    """Canvas trim outside which the CDF difference ``D`` is exactly 0: with ``border="pad"``
    both images are the same constant farther than ``r_sigma`` from the image."""
    return margin - min(margin, _reach(sigma, cfg.truncate))


def _plan(sigma: float, alphas: Sequence[float], weights: Sequence[float], margin: int, cfg: _Config) -> tuple[_Term, ...]:
    r_s = _reach(sigma, cfg.truncate)
    cells = [max(1, int(cfg.cell_fraction * a)) for a in alphas]
    return tuple(
        _Term(a, w, margin - min(margin, r_s + (2 * _reach(a, cfg.truncate) + 1 if a >= MIN_SCALE else 0)), cell, min(cell, max(1, int(POOL_FRACTION * a))))
        for a, w, cell in zip(alphas, weights, cells)
    )


def _trim(x: torch.Tensor, k: int) -> torch.Tensor:
    return x[..., k : x.shape[-2] - k, k : x.shape[-1] - k] if k else x


Stage = tuple[torch.Tensor, torch.Tensor]  # (M_H, M_W): one product M_H @ x @ M_W^T
Operators = Union[tuple[Stage, ...], None]  # applied in order; None: the identity


@lru_cache(maxsize=128)
def _operator(n: int, alpha: float, cell: int, pool: int, offset: int, n_support: int, truncate: float, dtype: torch.dtype, device: str) -> tuple[torch.Tensor, ...]:
    """The aperture blur of an ``n``-sample canvas restricted to the columns of the support
    ``[offset, offset + n_support)``, outside which its input is 0 (the same values as the full
    blur, at ``n_support / n`` of its cost), as one or two matrices applied in order.

    ``pool == 1``: one matrix, ``(n, n_support)`` per sample, or the per-cell means of the blur
    ``R (ceil(n / cell), n_support)``. ``pool > 1``: ``R`` factored as a box mean over cells of
    ``pool`` samples, ``P (n_pool, n_support)``, then ``G = R E`` on those cells (``E`` spreads a
    cell's mean over its samples): exact where the input is constant within each pool cell, and
    the wide blur runs on ``pool^2`` times fewer samples, for a gradient error close to that of
    ``R`` itself (measured: docs/loi.md, "Measurements behind the design")."""
    rows = gaussian_matrix(n, alpha, truncate, torch.float64, "cpu") if cell == 1 else cell_means(n, alpha, cell, truncate, torch.float64, "cpu")[0]
    rows = rows[:, offset : offset + n_support]
    if pool == 1:
        return (rows.to(dtype=dtype, device=device).contiguous(),)
    members = torch.arange(offset, offset + n_support, device="cpu") // pool
    members = members - members[0]
    spread = (members[:, None] == torch.arange(int(members[-1]) + 1, device="cpu")[None, :]).to(torch.float64)  # E (n_support, n_pool)
    pooled = spread.T / spread.sum(0)[:, None]
    return tuple(m.to(dtype=dtype, device=device).contiguous() for m in (pooled, rows @ spread))


def _operators(t: _Term, canvas: tuple[int, int], support: tuple[int, int], truncate: float, like: torch.Tensor) -> Operators:
    """The term's stages from the support (``(Hs, Ws)``, centred in the ``canvas``) to its own
    cells; ``None`` when the aperture is the identity (no aperture, same canvas)."""
    (ch, cw), (sh, sw) = canvas, support
    nh, nw = ch - 2 * t.trim, cw - 2 * t.trim
    if t.alpha < MIN_SCALE and (nh, nw) == (sh, sw):  # (alpha = 0 has 1-pixel cells)
        return None
    dev = str(like.device)
    rows = _operator(nh, t.alpha, t.cell, t.pool, (nh - sh) // 2, sh, truncate, like.dtype, dev)
    cols = _operator(nw, t.alpha, t.cell, t.pool, (nw - sw) // 2, sw, truncate, like.dtype, dev)
    return tuple(zip(rows, cols))


def _term_operators(d: torch.Tensor, pw: torch.Tensor, terms: Sequence[_Term], truncate: float) -> list[Operators]:
    """Each term's operators for ``d`` on the support, ``pw`` on the padded canvas."""
    canvas, support = tuple(pw.shape[-2:]), tuple(d.shape[-2:])
    return [_operators(t, canvas, support, truncate, d) for t in terms]


def _aperture(d: torch.Tensor, ops: Operators) -> torch.Tensor:
    """``A_alpha * D`` on the term's cells, ``(.., H', W')``, from ``D`` on the support
    (banded and native where it can be)."""
    for mh, mw in ops or ():
        d = sandwich(mh, d, mw)
    return d


def _aperture_adjoint(g: torch.Tensor, ops: Operators) -> torch.Tensor:
    for mh, mw in reversed(ops or ()):
        g = sandwich_adjoint(mh, g, mw)
    return g


def _term_weights(pw: torch.Tensor, t: _Term) -> torch.Tensor:
    """Pixel weights on the term's canvas, summed per cell: ``(B, 1|C, H', W')``."""
    pw = _trim(pw, t.trim)
    if t.cell == 1:
        return pw
    # sums over the cells of cell_means (samples i // cell; the last cell may be partial)
    return F.avg_pool2d(pw, t.cell, stride=t.cell, ceil_mode=True, divisor_override=1)


def _term_value(out: torch.Tensor, t: _Term, beta: float, pw: torch.Tensor) -> torch.Tensor:
    """One term's W1 (Eq. 5), unweighted, ``(B,)``, from its blurred difference ``out = A_alpha * D``."""
    w1 = out.abs().sum(2) * beta  # (B, C, H', W'): W1 per pixel/cell and channel
    return (w1 * _term_weights(pw, t)).flatten(1).sum(1) / out.shape[1]


def _scale_terms(d: torch.Tensor, terms: Sequence[_Term], beta: float, pw: torch.Tensor, truncate: float) -> list[torch.Tensor]:
    """The W1 (Eq. 5) of each term: ``[(B,)]``, from ``d = Phi' - Phi^gt`` (the difference of the
    point CDFs, blurred once instead of both images' CDFs) on the support."""
    return [_term_value(_aperture(d, op), t, beta, pw) for t, op in zip(terms, _term_operators(d, pw, terms, truncate))]


class _SigmaTerm(torch.autograd.Function):
    """``sum_alpha w_alpha E(sigma, alpha)`` for one inner scale, with a hand-written backward.

    Forward: ``u = (e_j - J_sigma') / beta``, ``D = Phi(u) - Phi^gt``, then per term
    ``|A_alpha * D|`` summed over bins and weighted pixels (Eq. 5). Backward:
    ``dE/dD = sum_alpha A_alpha^T (sign(A_alpha * D) w pw)`` and
    ``dE/dJ_sigma' = -sum_j phi(u_j) dE/dD_j / beta``. Fusing these saves most of the
    elementwise passes autograd would make over the ``(B, C, K, H, W)`` tensors. It stores
    ``u``, ``D`` and the blurred differences, or only ``J_sigma'`` with ``low_memory`` (then
    everything is recomputed in backward). Not twice differentiable."""

    @staticmethod
    def _difference(j_sigma, z_target, edges, beta):
        u = (edges.view(1, 1, -1, 1, 1) - j_sigma.unsqueeze(2)).div_(beta)
        return u, _phi_cdf(u).sub_(z_target)  # D = Phi' - Phi^gt

    @staticmethod
    def forward(ctx, j_sigma, z_target, edges, beta, terms, pw, truncate, low_memory):  # noqa: D102
        ops = _term_operators(z_target, pw, terms, truncate)
        fused = None
        if _loi_native.usable(j_sigma) and z_target.dtype == torch.float32:
            fused = _loi_native.sigma_term(
                j_sigma, z_target, edges, beta, ops, [_term_weights(pw, t) for t in terms],
                [t.weight * beta / j_sigma.shape[1] for t in terms], want_grad=ctx.needs_input_grad[0],
            )
        ctx.fused = fused is not None
        if fused is not None:  # the native kernel: the gradient comes with the loss
            total, grad_j = fused
            ctx.save_for_backward(grad_j if grad_j is not None else j_sigma.new_zeros(0))
            return total
        u, d = _SigmaTerm._difference(j_sigma, z_target, edges, beta)
        outs = [_aperture(d, op) for op in ops]
        total = sum(t.weight * _term_value(out, t, beta, pw) for t, out in zip(terms, outs))
        if low_memory:
            ctx.save_for_backward(j_sigma, z_target, edges, pw)
        else:
            ctx.save_for_backward(j_sigma, z_target, edges, pw, u, d, *outs)
        ctx.beta, ctx.terms, ctx.ops, ctx.truncate, ctx.low_memory = beta, terms, ops, truncate, low_memory
        return total

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # noqa: D102
        if ctx.fused:
            (grad_j,) = ctx.saved_tensors
            return grad.view(-1, 1, 1, 1).to(grad_j.dtype) * grad_j, None, None, None, None, None, None, None
        j_sigma, z_target, edges, pw, *stored = ctx.saved_tensors
        beta, terms = ctx.beta, ctx.terms
        if ctx.low_memory:
            u, d = _SigmaTerm._difference(j_sigma, z_target, edges, beta)
            outs = [None] * len(terms)  # recomputed one at a time below
        else:
            u, d, *outs = stored
        c = d.shape[1]
        grad_d = torch.zeros_like(d)
        for t, op, out in zip(terms, ctx.ops, outs):
            out = _aperture(d, op) if out is None else out
            scale = (grad.view(-1, 1, 1, 1) * _term_weights(pw, t)).mul_(t.weight * beta / c).unsqueeze(2)
            grad_d += _aperture_adjoint(torch.sign(out).mul_(scale), op)
        phi = u.square().mul_(-0.5).exp_()  # sqrt(2 pi) phi(u); the constant goes below
        grad_j = phi.mul_(grad_d).sum(2).mul_(-1.0 / (beta * math.sqrt(2 * math.pi)))  # d Phi(u) / dJ = -phi(u) / beta
        return grad_j, None, None, None, None, None, None, None


@dataclass
class _Prepared:
    rendered: torch.Tensor  # transformed, padded (B, C', Hp, Wp)
    target: torch.Tensor
    pw: torch.Tensor
    edges: torch.Tensor
    sigmas: tuple[float, ...]  # in pixels
    alphas: tuple[float, ...]
    shape: tuple[int, int, int, int]  # of the unpadded (transformed) images
    margin: int
    plans: tuple[tuple[_Term, ...], ...]  # per sigma, every alpha (weight 0 included)
    trims: tuple[int, ...]  # per sigma: the canvas trim of the support its CDF difference is computed on


def _prepare_one(name: str, x: torch.Tensor, cfg: _Config, warned: set[str] | None) -> torch.Tensor:
    j = _transform(x, cfg)
    _warn_out_of_range(name, j, cfg, warned)
    return j


def _prepare(rendered: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None, cfg: _Config, warned: set[str] | None = None) -> _Prepared:
    r, t = _as_batch("rendered", rendered), _as_batch("target", target)
    if r.shape != t.shape:
        raise ValueError(f"rendered and target shapes differ: {tuple(r.shape)} vs {tuple(t.shape)}")
    dtype = torch.promote_types(r.dtype, t.dtype)
    r, t = r.to(dtype), t.detach().to(dtype)
    if mask is not None:
        mask = _check_mask(mask, r)
    jr, jt = _prepare_one("rendered", r, cfg, warned), _prepare_one("target", t, cfg, warned)
    b, c, h, w = jr.shape
    if mask is not None and mask.shape[1] not in (1, c):
        raise ValueError(f"mask has {mask.shape[1]} channels but the compared images have {c}")
    m = _margin(h, w, cfg)
    lo = cfg.value_range[0]
    sigmas, alphas = _pixel_scales(cfg, h, w)
    plans = tuple(_plan(s, alphas, w_row, m, cfg) for s, w_row in zip(sigmas, cfg.weights))
    trims = tuple(_support_trim(s, m, cfg) for s in sigmas)
    return _Prepared(
        rendered=_pad(jr, m, lo),
        target=_pad(jt, m, lo),
        pw=_pixel_weights(b, h, w, m, mask, jr),
        edges=_edges(cfg, dtype, jr.device),
        sigmas=sigmas,
        alphas=alphas,
        shape=(b, c, h, w),
        margin=m,
        plans=plans,
        trims=trims,
    )


def _target_cdfs(p: _Prepared, cfg: _Config) -> list[torch.Tensor]:
    """The reference's point CDFs per sigma, on its support."""
    return [_point_cdf(_trim(blur(p.target, s, cfg.truncate), k), p.edges, cfg.beta) for s, k in zip(p.sigmas, p.trims)]


def _per_image(p: _Prepared, cfg: _Config, z_targets: list[torch.Tensor]) -> torch.Tensor:
    """The total ``sum_{sigma, alpha} w E(sigma, alpha)`` per batch item, ``(B,)``."""
    total = p.rendered.new_zeros(p.shape[0])
    for s, zt, plan, trim in zip(p.sigmas, z_targets, p.plans, p.trims):
        terms = tuple(t for t in plan if t.weight)
        if not terms:
            continue
        j_sigma = _trim(blur(p.rendered, s, cfg.truncate), trim)  # inner scale, Eqs. 1-2
        total = total + _SigmaTerm.apply(j_sigma, zt, p.edges, cfg.beta, terms, p.pw, cfg.truncate, cfg.low_memory)
    return total


def _reduce(x: torch.Tensor, reduction: str) -> torch.Tensor:
    return x.mean() if reduction == "mean" else x.sum() if reduction == "sum" else x
