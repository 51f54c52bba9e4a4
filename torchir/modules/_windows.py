"""The windowed-regression machinery the two regression denoisers share: mirrored window
padding, a window's taps (weights per offset) applied as a pair of autograd Functions, each the
other's backward, the choice of a cached tap table within a memory budget, and input checks."""
from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
import torch.nn.functional as F

from ._warnings import user_stacklevel

_IMPLS = ("auto", "taps", "cached")
_MAX_CACHE_ENTRIES = 64  # per module: one entry per view (batch of views) and target
_SERIAL_BELOW = 2**20  # elements per tap op below which the tap loops run on one torch thread


@contextmanager
def serial_for(numel: int) -> Iterator[None]:
    """One torch thread for the tap loops of small images. Each tap op then takes tens of
    microseconds, and on a shared, oversubscribed CPU OpenMP's fork/join per op made 2 threads
    far slower than 1 (measured: docs/troubleshooting.md, "Measurements behind the design")."""
    threads = torch.get_num_threads()
    if threads == 1 or numel >= _SERIAL_BELOW:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


# ----------------------------------------------------------------------------- tap machinery
def mirror_index(n: int, r: int) -> list[int]:
    """Source pixel of each of the ``n + 2r`` positions of an axis padded by ``r`` on both sides,
    mirrored about the edge pixels without repeating them (numpy ``mode="reflect"``: ``-1 -> 1``,
    ``n -> n - 2``), as the authors' released code does; reflected again when ``r >= n``."""
    if n == 1:
        return [0] * (1 + 2 * r)
    period = 2 * (n - 1)
    return [m if m < n else period - m for m in (k % period for k in range(-r, n + r))]


def _mirror_runs(n: int, r: int) -> list[tuple[int, int, int, bool]]:
    """``mirror_index`` as maximal runs ``(padded start, source start, length, reversed)`` of
    consecutive source pixels, so the adjoint can add whole slices (no atomics, deterministic)."""
    index, runs, start = mirror_index(n, r), [], 0
    while start < len(index):
        end = start + 1
        step = index[end] - index[start] if end < len(index) else 1
        if abs(step) == 1:
            while end < len(index) and index[end] - index[end - 1] == step:
                end += 1
        runs.append((start, min(index[start], index[end - 1]), end - start, step < 0))
        start = end
    return runs


def pad_window(x: torch.Tensor, r: int, border: str) -> torch.Tensor:
    """``(..., H + 2r, W + 2r)``: zeros outside the image (``"truncate"``) or mirrored pixels."""
    if border == "truncate":
        return F.pad(x, (r, r, r, r))
    H, W = x.shape[-2:]
    rows = torch.tensor(mirror_index(H, r), device=x.device)
    cols = torch.tensor(mirror_index(W, r), device=x.device)
    return x.index_select(-2, rows).index_select(-1, cols)


def _fold_axis(x: torch.Tensor, dim: int, n: int, r: int) -> torch.Tensor:
    """Adjoint of mirror-padding axis ``dim`` (length ``n + 2r`` -> ``n``)."""
    shape = list(x.shape)
    shape[dim] = n
    out = x.new_zeros(shape)
    for start, src, length, reverse in _mirror_runs(n, r):
        part = x.narrow(dim, start, length)
        out.narrow(dim, src, length).add_(part.flip(dim) if reverse else part)
    return out


def unpad_window(x_pad: torch.Tensor, r: int, border: str) -> torch.Tensor:
    """The exact adjoint of :func:`pad_window`: crop, or add each mirrored pixel back to its source."""
    H, W = x_pad.shape[-2] - 2 * r, x_pad.shape[-1] - 2 * r
    if border == "truncate":
        return x_pad[..., r : r + H, r : r + W].contiguous()
    return _fold_axis(_fold_axis(x_pad, x_pad.dim() - 1, W, r), x_pad.dim() - 2, H, r)


class _Taps:
    """The taps ``l_delta(c)`` of a linear smoother over a ``(2r+1)^2`` window.

    ``tap(dy, dx)`` returns ``l_delta`` for the offset ``delta = (dy - r, dx - r)`` as a tensor
    broadcastable to ``(B, C, H, W)``; ``l_delta(c)`` multiplies the input at pixel ``c + delta``
    (zero outside the image for ``border="truncate"``, the mirrored pixel for ``"reflect"``).
    With ``table`` the taps are read from memory, else computed.
    """

    def __init__(self, radius: int, size: tuple[int, int], tap: Callable[[int, int], torch.Tensor],
                 border: str = "truncate") -> None:
        self.radius = radius
        self.size = size
        self.border = border
        self._tap = tap
        self.table: torch.Tensor | None = None  # (K*K, B, C', H, W)

    @property
    def kernel(self) -> int:
        return 2 * self.radius + 1

    def taps(self, squared: bool = False) -> Iterator[tuple[int, int, torch.Tensor]]:
        K = self.kernel
        for k in range(K * K):
            dy, dx = divmod(k, K)
            l = self.table[k] if self.table is not None else self._tap(dy, dx)
            yield dy, dx, l.square() if squared else l

    def materialize(self) -> None:
        one = self._tap(self.radius, self.radius)
        table = one.new_empty((self.kernel**2,) + tuple(one.shape))  # filled in place: no 2x peak
        with serial_for(one.numel()):
            for k, (_, _, l) in enumerate(self.taps()):
                table[k] = l
        self.table = table

    def table_bytes(self, like: torch.Tensor) -> int:
        """Bytes the tap table would take (from the shape of one tap)."""
        one = self._tap(self.radius, self.radius)
        return self.kernel**2 * one.numel() * like.element_size()

    def gather(self, y: torch.Tensor, squared: bool = False) -> torch.Tensor:
        """``out_c = sum_delta l_delta(c) y_{c+delta}`` (Gu et al. 2024, Eq. 11)."""
        r, (H, W) = self.radius, self.size
        y_pad = pad_window(y, r, self.border)
        out = torch.zeros_like(y)
        with serial_for(y.numel()):
            for dy, dx, l in self.taps(squared):
                out.addcmul_(l, y_pad[..., dy : dy + H, dx : dx + W])
        return out

    def scatter(self, g: torch.Tensor) -> torch.Tensor:
        """The transpose: ``grad_{c+delta} += l_delta(c) g_c`` (Gu et al. 2024, Eq. 12), as slice-adds
        into a padded buffer, then the adjoint of the padding: deterministic, no atomics."""
        r, (H, W) = self.radius, self.size
        g_pad = g.new_zeros(g.shape[:-2] + (H + 2 * r, W + 2 * r))
        with serial_for(g.numel()):
            for dy, dx, l in self.taps():
                g_pad[..., dy : dy + H, dx : dx + W].addcmul_(l, g)
        return unpad_window(g_pad, r, self.border)


class _Gather(torch.autograd.Function):
    """``L y`` with ``L`` given by a :class:`_Taps`; backward ``L^T g`` (itself differentiable)."""

    @staticmethod
    def forward(ctx: Any, y: torch.Tensor, taps: _Taps) -> torch.Tensor:
        ctx.taps = taps
        return taps.gather(y)

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor, None]:
        return _Scatter.apply(g, ctx.taps), None


class _Scatter(torch.autograd.Function):
    """``L^T g``; its backward is ``L h`` (the double backward of :class:`_Gather`)."""

    @staticmethod
    def forward(ctx: Any, g: torch.Tensor, taps: _Taps) -> torch.Tensor:
        ctx.taps = taps
        return taps.scatter(g)

    @staticmethod
    def backward(ctx: Any, h: torch.Tensor) -> tuple[torch.Tensor, None]:
        return _Gather.apply(h, ctx.taps), None


def apply_taps(noisy: torch.Tensor, taps: _Taps) -> torch.Tensor:
    """``L noisy`` through the custom autograd Functions (exact transposed backward)."""
    return _Gather.apply(noisy, taps)


def choose_table(taps: _Taps, like: torch.Tensor, impl: str, max_cache_bytes: int, what: str) -> None:
    """Materialise the tap table when ``impl`` and the memory budget allow (``impl="cached"``
    over budget: a clear error instead of an out-of-memory)."""
    if impl == "taps":
        return
    need = taps.table_bytes(like)
    if need <= max_cache_bytes:
        taps.materialize()
    elif impl == "cached":
        H, W = taps.size
        raise ValueError(
            f"{what}: impl='cached' needs {need / 2**30:.2f} GiB for the tap table "
            f"({taps.kernel}x{taps.kernel} window, {H}x{W} image), over max_cache_bytes="
            f"{max_cache_bytes / 2**30:.2f} GiB; use impl='auto' or 'taps' (bounded memory), "
            f"a smaller radius, or raise max_cache_bytes"
        )


# ------------------------------------------------------------------------- input checking
def to_batch(x: torch.Tensor, name: str) -> torch.Tensor:
    """``(B, C, H, W)`` view of a ``(C, H, W)`` or ``(B, C, H, W)`` image."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() == 3:
        return x.unsqueeze(0)
    if x.dim() != 4:
        raise ValueError(f"{name}: expected (B,C,H,W) or (C,H,W), got shape {tuple(x.shape)}")
    return x


def _check_finite(name: str, x: torch.Tensor) -> None:
    bad = int((~torch.isfinite(x.detach())).sum())
    if bad:
        raise ValueError(f"{name} has {bad} NaN/Inf value(s) (check_finite=False skips this check)")


def check_noisy(noisy: torch.Tensor, check_finite: bool) -> torch.Tensor:
    """Validated ``(B,C,H,W)`` view of ``noisy`` (float32/float64)."""
    y = to_batch(noisy, "noisy")
    if not y.is_floating_point() or y.dtype in (torch.float16, torch.bfloat16):
        raise TypeError(f"noisy must be float32 or float64, got {y.dtype}")
    if check_finite:
        _check_finite("noisy", y)
    return y


def check_pair(noisy: torch.Tensor, target: torch.Tensor, check_finite: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Validated ``(B,C,H,W)`` noisy and detached target (a batch-1 target is shared)."""
    y, t = check_noisy(noisy, check_finite), to_batch(target, "target")
    if not t.is_floating_point():
        raise TypeError(f"target must be a floating-point tensor, got {t.dtype}")
    if y.device != t.device:
        raise ValueError(f"noisy is on {y.device} but target is on {t.device}")
    if t.shape[1:] != y.shape[1:] or t.shape[0] not in (1, y.shape[0]):
        raise ValueError(
            f"noisy {tuple(noisy.shape)} and target {tuple(target.shape)} differ: expected equal "
            f"(C,H,W) and a target batch of 1 or {y.shape[0]}"
        )
    if t.requires_grad:
        warnings.warn("target requires grad: the denoiser treats it as a constant; no gradient flows to it", stacklevel=user_stacklevel())
        t = t.detach()
    if check_finite:
        _check_finite("target", t)
    return y, t


def check_mask(mask: torch.Tensor | None, y: torch.Tensor) -> torch.Tensor | None:
    """``(B', 1, H, W)`` float mask (1 = use the pixel) from a bool ``(H,W)``/``(B,1,H,W)`` mask."""
    if mask is None:
        return None
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
        raise TypeError("mask must be a bool tensor (True = pixel takes part in the regressions)")
    m = mask.reshape((1, 1) + tuple(mask.shape)) if mask.dim() == 2 else mask
    B, _, H, W = y.shape
    if m.dim() != 4 or m.shape[1] != 1 or m.shape[2:] != (H, W) or m.shape[0] not in (1, B):
        raise ValueError(f"mask: expected (H,W), (1,1,H,W) or (B,1,H,W) with H,W = {H},{W}, got {tuple(mask.shape)}")
    if m.device != y.device:
        raise ValueError(f"mask is on {m.device} but noisy is on {y.device}")
    return m.to(torch.float64)


def check_hparams(radius: int, bandwidth: float, impl: str, max_cache_bytes: int) -> None:
    if isinstance(radius, bool) or not isinstance(radius, int) or radius < 0:
        raise ValueError(f"radius must be an int >= 0, got {radius!r}")
    if not (isinstance(bandwidth, (int, float)) and math.isfinite(bandwidth) and bandwidth > 0):
        raise ValueError(f"bandwidth must be a finite number > 0, got {bandwidth!r}")
    if impl not in _IMPLS:
        raise ValueError(f"impl must be one of {_IMPLS}, got {impl!r}")
    if max_cache_bytes < 0:
        raise ValueError(f"max_cache_bytes must be >= 0, got {max_cache_bytes}")


def _finish(out: torch.Tensor, clamp_min: float | None, like: torch.Tensor) -> torch.Tensor:
    """Output clamp ``max(clamp_min, f^)`` and the caller's layout."""
    if clamp_min is not None:
        # the authors' code clamps with dr.maximum(0.0, f^), whose derivative w.r.t. f^ is 1 at
        # equality: so the gradient is 1[f^ >= clamp_min]. A window whose render is exactly 0 under
        # a non-black target (e.g. a reflectance at its lower bound) then still gets a signal.
        out = torch.where(out >= clamp_min, out, out.new_tensor(clamp_min))
    return out.squeeze(0) if like.dim() == 3 else out


# ------------------------------------------------------------------------------ functional
