"""The LOI loss's terms of one inner scale, forward and gradient fused per bin (native kernel).

``loi_sigma`` in :mod:`._banded`'s compiled library takes one ``(H, W)`` plane per batch item,
channel and bin edge at a time: the point-CDF difference ``D``, every aperture term's
``A_alpha D`` through its banded stages, ``|A_alpha D|`` weighted and summed (the W1 distance of
Mehta et al. 2025, Eq. 5), and, for the gradient, ``A_alpha^T (sign(A_alpha D) w)`` summed over
the terms and chained to ``J_sigma``, all while the plane is in cache. The ``(B, C, K, H, W)``
volumes the torch path makes (``u``, ``D``, one ``A_alpha D`` per term, their signs,
``dE/dD``) are never materialised, and the gradient is ready when the forward pass ends (the
loss is a sum: its backward only scales it). The reference's CDFs must come from
:func:`point_cdf` (the same ``Phi``). Same values as the torch path to float32 rounding (``Phi``
and ``exp`` by polynomials good to ~1e-7 relative); float32 CPU tensors only, else
:func:`sigma_term` returns ``None``.
"""
from __future__ import annotations

import ctypes
from collections.abc import Sequence

import torch

from . import _banded

__all__ = ["sigma_term", "point_cdf", "usable"]

_i64, _ptr = ctypes.c_int64, ctypes.c_void_p


class _BandC(ctypes.Structure):
    _fields_ = [("start", _ptr), ("w", _ptr), ("length", _i64), ("n_out", _i64), ("n_in", _i64)]


class _StageC(ctypes.Structure):
    _fields_ = [("h", _BandC), ("w", _BandC), ("ht", _BandC), ("wt", _BandC)]


class _TermC(ctypes.Structure):
    _fields_ = [("n_stages", _i64), ("stages", ctypes.POINTER(_StageC)), ("pw", _ptr), ("pw_bstride", _i64),
                ("pw_cstride", _i64), ("out_h", _i64), ("out_w", _i64), ("scale", ctypes.c_float)]


def _band(form: _banded._Band) -> _BandC:
    return _BandC(form.start.data_ptr(), form.weights.data_ptr(), form.length, form.start.numel(), form.n_in)


def _stage(mh: torch.Tensor, mw: torch.Tensor) -> _StageC:
    (h, ht), (w, wt) = _banded._forms(mh), _banded._forms(mw)  # any width: a dense matrix is a wide band
    return _StageC(_band(h), _band(w), _band(ht), _band(wt))


def usable(x: torch.Tensor) -> bool:
    """Whether the kernel applies to ``x`` (float32 on the CPU, native products on and built)."""
    return _banded._enabled and x.dtype == torch.float32 and x.device.type == "cpu" and _banded._load() is not None


def point_cdf(j_sigma: torch.Tensor, edges: torch.Tensor, beta: float) -> torch.Tensor:
    """``Phi((e_k - J) / beta)``, ``(B, C, K, H, W)``, with the kernel's own ``Phi`` (where
    :func:`usable`): a reference's CDFs must come from the same ``Phi`` as the rendered image's
    inside :func:`sigma_term`, or equal pixels differ by rounding and the sign of ``A D`` there
    turns into noise (measured: docs/loi.md)."""
    lib = _banded._load()
    j = j_sigma.detach().contiguous()
    e = edges.detach().to(torch.float32).contiguous()
    b, c, h, w = j.shape
    z = j.new_empty(b, c, e.numel(), h, w)
    lib.point_cdf(j.data_ptr(), e.data_ptr(), b * c, e.numel(), h * w, float(beta), z.data_ptr(), torch.get_num_threads())
    return z


def sigma_term(
    j_sigma: torch.Tensor,
    z_target: torch.Tensor,
    edges: torch.Tensor,
    beta: float,
    operators: Sequence[tuple[tuple[torch.Tensor, torch.Tensor], ...] | None],
    term_weights: Sequence[torch.Tensor],
    scales: Sequence[float],
    want_grad: bool,
) -> tuple[torch.Tensor, torch.Tensor | None] | None:
    """``sum_t scale_t sum |A_t D| w_t`` per batch item and its gradient in ``j_sigma``.

    Args:
        j_sigma: ``(B, C, H, W)`` the rendered image blurred by sigma, on the support.
        z_target: ``(B, C, K, H, W)`` the reference's point CDFs on the same support.
        edges: ``(K,)`` bin edges.
        operators: per term, its stages ``(M_H, M_W)`` in order (``None``: the identity).
        term_weights: per term, ``(B, 1|C, H', W')`` pixel weights on its output cells.
        scales: per term, ``weight * beta / C``.
        want_grad: also return ``d loss[b] / d j_sigma``.

    Returns:
        ``(loss (B,), grad (B, C, H, W) or None)``, or ``None`` where the kernel does not apply.
    """
    if not (usable(j_sigma) and z_target.dtype == torch.float32):
        return None
    lib = _banded._load()
    j = j_sigma.detach().contiguous()
    z = z_target.detach().contiguous()
    e = edges.detach().to(torch.float32).contiguous()
    b, c, h, w = j.shape
    k = e.numel()
    if tuple(z.shape) != (b, c, k, h, w):
        raise ValueError(f"point CDFs {tuple(z.shape)} do not match the image {tuple(j.shape)} and {k} bin edges")
    keep: list[object] = []  # everything the C structures point into, alive for the call
    terms = (_TermC * len(operators))()
    largest = h * w
    for i, (ops, weights, scale) in enumerate(zip(operators, term_weights, scales)):
        stages = [_stage(mh, mw) for mh, mw in ops or ()]
        array = (_StageC * max(1, len(stages)))(*stages)
        out_h, out_w = (ops[-1][0].shape[0], ops[-1][1].shape[0]) if ops else (h, w)
        for mh, mw in ops or ():
            (ho, hi), (wo, wi) = mh.shape, mw.shape
            largest = max(largest, hi * wi, wi * ho, ho * wo, wo * hi)  # input, the two transposed passes, output
        pw = weights.detach().to(torch.float32).contiguous()
        if pw.dim() != 4 or pw.shape[0] != b or pw.shape[1] not in (1, c) or tuple(pw.shape[2:]) != (out_h, out_w):
            raise ValueError(f"term {i}: pixel weights {tuple(pw.shape)} do not match its cells {(b, c, out_h, out_w)}")
        keep += [array, pw]
        terms[i] = _TermC(len(stages), array, pw.data_ptr(), pw.shape[1] * out_h * out_w, out_h * out_w if pw.shape[1] > 1 else 0, out_h, out_w, float(scale))
    loss = torch.zeros(b, dtype=torch.float64, device=j.device)
    grad = torch.zeros_like(j) if want_grad else None
    failed = lib.loi_sigma(j.data_ptr(), z.data_ptr(), e.data_ptr(), b, c, k, h, w, float(beta), terms, len(operators), largest,
                           loss.data_ptr(), grad.data_ptr() if grad is not None else None, torch.get_num_threads())
    if failed:
        raise MemoryError("torchir LOI kernel: out of memory for its plane buffers")
    return loss.to(j_sigma.dtype), grad
