"""Separable products ``M_H @ x @ M_W^T`` with banded matrices, by a small native kernel.

The LOI loss blurs ``(B, C, K, H, W)`` volumes with truncated Gaussians (and their exact
cell means). As dense matrix products that costs ``H + W`` multiply-adds per voxel whatever
the kernel's width; a banded product costs its width ``L`` (7 for ``alpha = 1``, 31 for
``alpha = 5``, against ~560 at 256² with the LOI margin). torch has no banded product on the
CPU (its 1-channel ``conv2d`` measured 2x slower than the dense product), so this module
compiles one short C function on first use, with the system's C compiler, into a per-user
cache, and calls it through ``ctypes``. Without a compiler (or for float64, non-CPU tensors,
matrices that are not narrow, or ``TORCHIR_NATIVE=0``) it falls back to the dense product,
which gives the same values to float32 rounding.

Example:
    >>> m = gaussian_matrix(64, 2.0)
    >>> sandwich(m, torch.rand(3, 64, 64), m).shape
    torch.Size([3, 64, 64])
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import subprocess
import tempfile
import threading
import warnings
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch

from ._warnings import user_stacklevel

__all__ = ["sandwich", "sandwich_adjoint", "native_available", "native_products", "ENV_NATIVE"]

ENV_NATIVE = "TORCHIR_NATIVE"  # "0": always the dense product
ENV_CACHE = "TORCHIR_CACHE"  # where compiled kernels are kept (default ~/.cache/torchir)
_NARROW = 0.5  # banded when the band is at most this fraction of the input length

_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
typedef float v8 __attribute__((vector_size(32)));
static inline v8 ld(const float* p) { v8 v; memcpy(&v, p, sizeof v); return v; }
static inline void st(float* p, v8 v) { memcpy(p, &v, sizeof v); }

#ifdef __AVX__
#include <immintrin.h>
/* dst[k * ld_dst + b] = src[b * ld_src + k] for one 8 x 8 block */
static inline void transpose8(const float* src, int64_t ld_src, float* dst, int64_t ld_dst) {
  __m256 r[8], t[8], u[8];
  for (int k = 0; k < 8; ++k) r[k] = _mm256_loadu_ps(src + k * ld_src);
  for (int k = 0; k < 4; ++k) {
    t[2 * k] = _mm256_unpacklo_ps(r[2 * k], r[2 * k + 1]);
    t[2 * k + 1] = _mm256_unpackhi_ps(r[2 * k], r[2 * k + 1]);
  }
  for (int k = 0; k < 2; ++k) {
    u[4 * k] = _mm256_shuffle_ps(t[4 * k], t[4 * k + 2], 0x44);
    u[4 * k + 1] = _mm256_shuffle_ps(t[4 * k], t[4 * k + 2], 0xEE);
    u[4 * k + 2] = _mm256_shuffle_ps(t[4 * k + 1], t[4 * k + 3], 0x44);
    u[4 * k + 3] = _mm256_shuffle_ps(t[4 * k + 1], t[4 * k + 3], 0xEE);
  }
  for (int k = 0; k < 4; ++k) {
    _mm256_storeu_ps(dst + k * ld_dst, _mm256_permute2f128_ps(u[k], u[k + 4], 0x20));
    _mm256_storeu_ps(dst + (k + 4) * ld_dst, _mm256_permute2f128_ps(u[k], u[k + 4], 0x31));
  }
}
#endif

/* acc[x] = sum_l w[l] * src[l * X + x], x < X */
static void band_row(const float* src, int64_t X, const float* w, int64_t L, float* acc) {
  int64_t x = 0;
  for (; x + 32 <= X; x += 32) {
    v8 a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0};
    for (int64_t l = 0; l < L; ++l) {
      const float* r = src + l * X + x;
      const v8 c = (v8){0} + w[l];
      a0 += c * ld(r); a1 += c * ld(r + 8); a2 += c * ld(r + 16); a3 += c * ld(r + 24);
    }
    st(acc + x, a0); st(acc + x + 8, a1); st(acc + x + 16, a2); st(acc + x + 24, a3);
  }
  for (; x + 8 <= X; x += 8) {
    v8 a0 = {0};
    for (int64_t l = 0; l < L; ++l) a0 += ((v8){0} + w[l]) * ld(src + l * X + x);
    st(acc + x, a0);
  }
  for (; x < X; ++x) {
    float a = 0.f;
    for (int64_t l = 0; l < L; ++l) a += w[l] * src[l * X + x];
    acc[x] = a;
  }
}

/* out[p, x, i] = sum_l w[i * L + l] * in[p, s[i] + l, x]: a banded (Nout, Nin) matrix applied
   along axis -2 of in (P, Nin, X), written transposed as (P, X, Nout). Returns 0, or 1 when
   out of memory. */
int band_t(const float* in, float* out, int64_t P, int64_t Nin, int64_t X, int64_t Nout,
           const int64_t* s, int64_t L, const float* w, int threads) {
  const int64_t B = 8, nblk = (Nout + B - 1) / B;
  int failed = 0;
  #pragma omp parallel num_threads(threads) reduction(|:failed)
  {
    float* acc = malloc(sizeof(float) * B * X);
    if (!acc) failed = 1;
    #pragma omp for collapse(2) schedule(static)
    for (int64_t p = 0; p < P; ++p)
      for (int64_t k = 0; k < nblk; ++k) {
        if (!acc) continue;
        const int64_t i0 = k * B, nb = (Nout - i0) < B ? (Nout - i0) : B;
        for (int64_t b = 0; b < nb; ++b)
          band_row(in + (p * Nin + s[i0 + b]) * X, X, w + (i0 + b) * L, L, acc + b * X);
        float* o = out + p * X * Nout + i0;
        int64_t x = 0;
#ifdef __AVX__
        if (nb == B)
          for (; x + 8 <= X; x += 8) transpose8(acc + x, X, o + x * Nout, Nout);
#endif
        for (; x < X; ++x)
          for (int64_t b = 0; b < nb; ++b) o[x * Nout + b] = acc[b * X + x];
      }
    free(acc);
  }
  return failed;
}
"""
_FLAGS = ("-O3", "-march=native", "-fopenmp", "-shared", "-fPIC")


# ------------------------------------------------------------------------------ the library
def _cpu_identity() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return "\n".join(sorted({ln for ln in lines if ln.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor()


def _cache_dir() -> Path:
    root = os.environ.get(ENV_CACHE) or os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "torchir")
    return Path(root) / "kernels"


def _compile(compiler: str) -> Path:
    key = hashlib.sha256("\0".join((_SOURCE, compiler, *_FLAGS, platform.machine(), _cpu_identity())).encode()).hexdigest()[:16]
    target = _cache_dir() / f"banded-{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        src, lib = Path(tmp) / "banded.c", Path(tmp) / "banded.so"
        src.write_text(_SOURCE)
        done = subprocess.run([compiler, *_FLAGS, str(src), "-o", str(lib)], capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            raise RuntimeError(f"{compiler} failed: {done.stderr.strip()[-500:]}")
        os.replace(lib, target)  # atomic: concurrent processes each write a whole file
    return target


_lock = threading.Lock()
_library: ctypes.CDLL | None = None
_unavailable: str | None = None  # why there is no native library (reported once)


def _load() -> ctypes.CDLL | None:
    global _library, _unavailable
    with _lock:
        if _library is not None or _unavailable is not None:
            return _library
        if os.environ.get(ENV_NATIVE, "1") == "0":
            _unavailable = f"{ENV_NATIVE}=0"
            return None
        try:
            lib = ctypes.CDLL(str(_compile(os.environ.get("CC", "cc"))))
            i64, ptr = ctypes.c_int64, ctypes.c_void_p
            lib.band_t.argtypes = [ptr, ptr, i64, i64, i64, i64, ptr, i64, ptr, ctypes.c_int]
            lib.band_t.restype = ctypes.c_int
            _library = lib
        except (OSError, RuntimeError, subprocess.SubprocessError) as e:
            _unavailable = str(e)
            warnings.warn(
                f"torchir: no native banded blur ({e}); the LOI loss falls back to dense matrix products "
                f"(same values, several times slower). Install a C compiler (gcc) to speed it up.",
                stacklevel=user_stacklevel(),
            )
        return _library


def native_available() -> bool:
    """Whether the compiled kernel can be used (compiles it on first call)."""
    return _load() is not None


_enabled = True


@contextmanager
def native_products(enabled: bool) -> Iterator[None]:
    """Within the block, use the native kernel (``True``, where available) or always the dense
    products (``False``): for benchmarks that compare the two and for tests."""
    global _enabled
    before, _enabled = _enabled, bool(enabled)
    try:
        yield
    finally:
        _enabled = before


# ------------------------------------------------------------------------------ band forms
@dataclass(frozen=True)
class _Band:
    """A ``(n_out, n_in)`` matrix as rows of ``length`` weights starting at column ``start[i]``."""

    start: torch.Tensor  # (n_out,) int64
    weights: torch.Tensor  # (n_out, length) float32
    n_in: int

    @property
    def length(self) -> int:
        return self.weights.shape[1]

    @staticmethod
    def of(m: torch.Tensor) -> _Band | None:
        """The band form of ``m``, or ``None`` when its band is wider than ``_NARROW * n_in``."""
        n_out, n_in = m.shape
        nonzero = m != 0
        cols = torch.arange(n_in)
        first = torch.where(nonzero, cols, n_in).min(1).values
        last = torch.where(nonzero, cols + 1, 0).max(1).values
        length = max(1, int((last - first).clamp(min=0).max()))
        if length > _NARROW * n_in:
            return None
        start = torch.minimum(first, torch.tensor(n_in - length)).clamp(min=0)
        weights = torch.gather(m.detach().float().cpu(), 1, start[:, None] + torch.arange(length)[None])
        return _Band(start.contiguous(), weights.contiguous(), n_in)


_bands: dict[int, tuple[_Band | None, _Band | None]] = {}  # id(matrix) -> forms of m and m^T


def _forms(m: torch.Tensor) -> tuple[_Band | None, _Band | None]:
    key = id(m)
    if key not in _bands:
        _bands[key] = (_Band.of(m), _Band.of(m.T))
        weakref.finalize(m, _bands.pop, key, None)  # ids are reused once m is gone
    return _bands[key]


def _apply_t(x: torch.Tensor, band: _Band, lib: ctypes.CDLL) -> torch.Tensor:
    """``band @ x`` along axis -2 of ``x`` ``(..., n_in, X)``, returned as ``(..., X, n_out)``."""
    *batch, n_in, cols = x.shape
    planes = x.numel() // max(1, n_in * cols)
    out = x.new_empty(*batch, cols, band.start.numel())
    failed = lib.band_t(
        x.data_ptr(), out.data_ptr(), planes, n_in, cols, band.start.numel(), band.start.data_ptr(), band.length, band.weights.data_ptr(), torch.get_num_threads()
    )
    if failed:
        raise MemoryError("torchir banded blur: out of memory for its row buffers")
    return out


def _native(x: torch.Tensor, mh: torch.Tensor, mw: torch.Tensor, transposed: bool) -> torch.Tensor | None:
    if not _enabled or x.dtype != torch.float32 or x.device.type != "cpu" or x.numel() == 0:
        return None
    if (lib := _load()) is None:  # no compiler: no band forms either
        return None
    bh, bw = (_forms(mh)[transposed], _forms(mw)[transposed])
    if bh is None or bw is None:
        return None
    x = x.contiguous()
    return _apply_t(_apply_t(x, bh, lib), bw, lib)


class _Sandwich(torch.autograd.Function):
    """``mh @ x @ mw.T`` with the native product in both directions (float32 CPU)."""

    @staticmethod
    def forward(ctx, x, mh, mw):  # noqa: D102
        ctx.mats = (mh, mw)
        return _product(x, mh, mw, False)

    @staticmethod
    def backward(ctx, g):  # noqa: D102
        mh, mw = ctx.mats
        # under create_graph the dense product keeps the backward differentiable
        return (mh.T @ g @ mw if torch.is_grad_enabled() else _product(g, mh, mw, True)), None, None


def _product(x: torch.Tensor, mh: torch.Tensor, mw: torch.Tensor, transposed: bool) -> torch.Tensor:
    if (y := _native(x, mh, mw, transposed)) is not None:
        return y
    return mh.T @ x @ mw if transposed else mh @ x @ mw.T


def sandwich(mh: torch.Tensor, x: torch.Tensor, mw: torch.Tensor) -> torch.Tensor:
    """``mh @ x @ mw.T`` for constant matrices ``mh (H', H)``, ``mw (W', W)`` and ``x (..., H, W)``.

    Banded and native when it can be (see the module docstring), else the dense product; the
    same values to float32 rounding, differentiable in ``x``. Pass cached matrices: their band
    forms are cached per matrix object."""
    if x.requires_grad and torch.is_grad_enabled():
        return _Sandwich.apply(x, mh, mw)
    return _product(x, mh, mw, False)


def sandwich_adjoint(mh: torch.Tensor, g: torch.Tensor, mw: torch.Tensor) -> torch.Tensor:
    """``mh.T @ g @ mw``: the adjoint of :func:`sandwich`, ``g (..., H', W') -> (..., H, W)``
    (not differentiable; for hand-written backward passes)."""
    return _product(g, mh, mw, True)
