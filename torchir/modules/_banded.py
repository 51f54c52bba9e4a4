"""Separable products ``M_H @ x @ M_W^T`` with banded matrices, by a small native kernel.

The LOI loss blurs ``(B, C, K, H, W)`` volumes with truncated Gaussians (and their exact
cell means). As dense matrix products that costs ``H + W`` multiply-adds per voxel whatever
the kernel's width; a banded product costs its width ``L`` (7 for ``alpha = 1``, 31 for
``alpha = 5``, against ~560 at 256² with the LOI margin). torch has no banded product on the
CPU (and its 1-channel ``conv2d`` is slower than the dense product; measured: docs/loi.md,
"Measurements behind the design"), so this module compiles one short C function on first use,
with the system's C compiler, into a per-user cache, and calls it through ``ctypes``. Without a
compiler (or for float64, non-CPU tensors, matrices that are not narrow, or
``TORCHIR_NATIVE=0``) it falls back to the dense product, which gives the same values to
float32 rounding. The same library holds the LOI loss's fused per-bin kernel (``loi_sigma``,
``point_cdf``; called from :mod:`._loi_native`).

Example:
    >>> from torchir.modules._blur import gaussian_matrix
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
#include <math.h>
typedef float v8 __attribute__((vector_size(32)));
typedef int32_t vi8 __attribute__((vector_size(32)));
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
#if defined(__AVX2__) && defined(__FMA__)
  if (x < X) {  /* the last 1-7 columns: masked loads never touch memory past the row */
    const __m256i lanes = _mm256_cmpgt_epi32(_mm256_set1_epi32((int)(X - x)), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    __m256 a0 = _mm256_setzero_ps();
    for (int64_t l = 0; l < L; ++l) a0 = _mm256_fmadd_ps(_mm256_set1_ps(w[l]), _mm256_maskload_ps(src + l * X + x, lanes), a0);
    _mm256_maskstore_ps(acc + x, lanes, a0);
    x = X;
  }
#endif
  for (; x < X; ++x) {
    float a = 0.f;
    for (int64_t l = 0; l < L; ++l) a += w[l] * src[l * X + x];
    acc[x] = a;
  }
}

/* Rows i0 .. i0 + nb - 1 (nb <= 8) of a banded matrix applied along axis -2 of one plane
   in (Nin, X), written transposed into o = out + i0 of an (X, Nout) plane; acc holds 8 * X. */
static void band_block(const float* in, int64_t X, int64_t Nout, const int64_t* s, int64_t L,
                       const float* w, int64_t i0, int64_t nb, float* acc, float* out) {
  for (int64_t b = 0; b < nb; ++b)
    band_row(in + s[i0 + b] * X, X, w + (i0 + b) * L, L, acc + b * X);
  float* o = out + i0;
  int64_t x = 0;
#ifdef __AVX__
  if (nb == 8)
    for (; x + 8 <= X; x += 8) transpose8(acc + x, X, o + x * Nout, Nout);
#endif
  for (; x < X; ++x)
    for (int64_t b = 0; b < nb; ++b) o[x * Nout + b] = acc[b * X + x];
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
        band_block(in + p * Nin * X, X, Nout, s, L, w, i0, nb, acc, out + p * X * Nout);
      }
    free(acc);
  }
  return failed;
}

/* ---------------------------------------------------------------- the LOI loss, fused per bin */
typedef struct { const int64_t* start; const float* w; int64_t length, n_out, n_in; } band;
typedef struct { band h, w, ht, wt; } stage;  /* M_H, M_W and their transposes */
typedef struct {
  int64_t n_stages;       /* 0: the identity (no aperture) */
  const stage* stages;    /* applied in order: each out = M_H @ in @ M_W^T */
  const float* pw;        /* per-cell pixel weights, (B, 1|C, out_h, out_w) */
  int64_t pw_bstride, pw_cstride, out_h, out_w;
  float scale;            /* the term's weight * beta / C */
} term;

/* one plane through a banded pass: in (Nin, X) -> out (X, b->n_out) */
static void pass_t(const float* in, float* out, int64_t X, const band* b, float* acc) {
  for (int64_t i0 = 0; i0 < b->n_out; i0 += 8) {
    const int64_t nb = (b->n_out - i0) < 8 ? (b->n_out - i0) : 8;
    band_block(in, X, b->n_out, b->start, b->length, b->w, i0, nb, acc, out);
  }
}

#if defined(__AVX2__) && defined(__FMA__)
/* expf to ~2 ulp (Cephes' polynomial); exactly 0 below -87, where floats turn denormal, so
   saturated values give exactly zero gradients as the torch path does */
static inline __m256 vexp(__m256 x) {
  const __m256 underflow = _mm256_cmp_ps(x, _mm256_set1_ps(-87.0f), _CMP_LT_OQ);
  x = _mm256_max_ps(_mm256_min_ps(x, _mm256_set1_ps(88.0f)), _mm256_set1_ps(-87.0f));
  __m256 fx = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(1.44269504088896341f)), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  x = _mm256_fnmadd_ps(fx, _mm256_set1_ps(0.693359375f), x);
  x = _mm256_fnmadd_ps(fx, _mm256_set1_ps(-2.12194440e-4f), x);
  __m256 y = _mm256_set1_ps(1.9875691500e-4f);
  y = _mm256_fmadd_ps(y, x, _mm256_set1_ps(1.3981999507e-3f));
  y = _mm256_fmadd_ps(y, x, _mm256_set1_ps(8.3334519073e-3f));
  y = _mm256_fmadd_ps(y, x, _mm256_set1_ps(4.1665795894e-2f));
  y = _mm256_fmadd_ps(y, x, _mm256_set1_ps(1.6666665459e-1f));
  y = _mm256_fmadd_ps(y, x, _mm256_set1_ps(5.0000001201e-1f));
  y = _mm256_fmadd_ps(y, _mm256_mul_ps(x, x), _mm256_add_ps(x, _mm256_set1_ps(1.0f)));
  __m256i e = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(fx), _mm256_set1_epi32(127)), 23);
  return _mm256_andnot_ps(underflow, _mm256_mul_ps(y, _mm256_castsi256_ps(e)));
}

/* Phi(u) = erfc(-u / sqrt 2) / 2, with erfc by Numerical Recipes' Chebyshev fit (relative
   error < 1.2e-7) */
static inline __m256 vphi(__m256 u) {
  const __m256 z = _mm256_mul_ps(u, _mm256_set1_ps(-0.70710678118654752f));
  const __m256 sign_mask = _mm256_set1_ps(-0.0f);
  const __m256 a = _mm256_andnot_ps(sign_mask, z);
  const __m256 t = _mm256_div_ps(_mm256_set1_ps(1.0f), _mm256_fmadd_ps(a, _mm256_set1_ps(0.5f), _mm256_set1_ps(1.0f)));
  __m256 p = _mm256_set1_ps(0.17087277f);
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(-0.82215223f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(1.48851587f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(-1.13520398f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(0.27886807f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(-0.18628806f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(0.09678418f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(0.37409196f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(1.00002368f));
  p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(-1.26551223f));
  const __m256 half_erfc_a = _mm256_mul_ps(_mm256_mul_ps(t, vexp(_mm256_fnmadd_ps(a, a, p))), _mm256_set1_ps(0.5f));
  const __m256 negative = _mm256_cmp_ps(z, _mm256_setzero_ps(), _CMP_LT_OQ);  /* erfc(z) = 2 - erfc(-z) */
  return _mm256_blendv_ps(half_erfc_a, _mm256_sub_ps(_mm256_set1_ps(1.0f), half_erfc_a), negative);
}
#endif

/* sum_i |x[i]| w[i]: float partial sums in vectors (a scalar running sum is one long dependency
   chain), each block of 1024 added in double */
static double weighted_abs_sum(const float* x, const float* w, int64_t n) {
  double sum = 0.0;
  for (int64_t i0 = 0; i0 < n; i0 += 1024) {
    const int64_t i1 = n - i0 < 1024 ? n : i0 + 1024;
    v8 a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0};
    const vi8 mask = (vi8){0} + 0x7fffffff;  /* clears the sign bit: |x| */
    int64_t i = i0;
    for (; i + 32 <= i1; i += 32) {
      a0 += (v8)((vi8)ld(x + i) & mask) * ld(w + i);
      a1 += (v8)((vi8)ld(x + i + 8) & mask) * ld(w + i + 8);
      a2 += (v8)((vi8)ld(x + i + 16) & mask) * ld(w + i + 16);
      a3 += (v8)((vi8)ld(x + i + 24) & mask) * ld(w + i + 24);
    }
    const v8 a = (a0 + a1) + (a2 + a3);
    float partial = 0.0f;
    for (int k = 0; k < 8; ++k) partial += a[k];
    for (; i < i1; ++i) partial += fabsf(x[i]) * w[i];
    sum += partial;
  }
  return sum;
}

/* d[i] = Phi((e - J[i]) / beta) - Z[i], or Phi itself when Z is NULL */
static void point_cdf_difference(const float* J, const float* Z, float e, float inv_beta, int64_t n, float* d) {
  int64_t i = 0;
#if defined(__AVX2__) && defined(__FMA__)
  const __m256 ve = _mm256_set1_ps(e), vb = _mm256_set1_ps(inv_beta);
  for (; i + 8 <= n; i += 8) {
    const __m256 phi = vphi(_mm256_mul_ps(_mm256_sub_ps(ve, _mm256_loadu_ps(J + i)), vb));
    _mm256_storeu_ps(d + i, Z ? _mm256_sub_ps(phi, _mm256_loadu_ps(Z + i)) : phi);
  }
#endif
  for (; i < n; ++i) d[i] = 0.5f * erfcf((e - J[i]) * inv_beta * -0.70710678118654752f) - (Z ? Z[i] : 0.0f);
}

/* Z[q, j] = Phi((edges[j] - J[q]) / beta) for planes q < Q of HW samples: the point CDFs the
   fused kernel's differences are taken against (the same Phi, so equal images give exact 0) */
void point_cdf(const float* J, const float* edges, int64_t Q, int64_t K, int64_t HW, float beta, float* Z, int threads) {
  #pragma omp parallel for num_threads(threads) schedule(static)
  for (int64_t p = 0; p < Q * K; ++p)
    point_cdf_difference(J + (p / K) * HW, NULL, edges[p % K], 1.0f / beta, HW, Z + p * HW);
}

/* g[i] = k * exp(-u^2 / 2) * gd[i], u = (e - J[i]) / beta */
static void chain_to_j(const float* J, const float* gd, float e, float inv_beta, float k, int64_t n, float* g) {
  int64_t i = 0;
#if defined(__AVX2__) && defined(__FMA__)
  const __m256 ve = _mm256_set1_ps(e), vb = _mm256_set1_ps(inv_beta), vk = _mm256_set1_ps(k), mh = _mm256_set1_ps(-0.5f);
  for (; i + 8 <= n; i += 8) {
    const __m256 u = _mm256_mul_ps(_mm256_sub_ps(ve, _mm256_loadu_ps(J + i)), vb);
    const __m256 phi = vexp(_mm256_mul_ps(_mm256_mul_ps(u, u), mh));
    _mm256_storeu_ps(g + i, _mm256_mul_ps(_mm256_mul_ps(phi, vk), _mm256_loadu_ps(gd + i)));
  }
#endif
  for (; i < n; ++i) {
    const float u = (e - J[i]) * inv_beta;
    g[i] = k * expf(-0.5f * u * u) * gd[i];
  }
}

/* The LOI terms of one inner scale (W1 of each aperture term), forward and gradient in one pass per bin.
   J (B, C, H, W): the rendered image blurred by sigma, on the support; Z (B, C, K, H, W): the
   reference's point CDFs; edges (K). Adds each term's scale * sum |A D| pw to loss[b] and, when
   grad is not NULL, d loss[b] / d J into grad (B, C, H, W). buffer: the largest plane any term
   passes through. Returns 0, or 1 when out of memory. */
int loi_sigma(const float* J, const float* Z, const float* edges, int64_t B, int64_t C, int64_t K,
              int64_t H, int64_t W, float beta, const term* terms, int64_t n_terms, int64_t buffer,
              double* loss, float* grad, int threads) {
  const int64_t HW = H * W, P = B * C * K;
  const float inv_beta = 1.0f / beta, k = -1.0f / (beta * 2.50662827463100050f);
  int failed = 0;
  /* every plane's share is kept apart and summed in plane order afterwards: the planes are
     shared out dynamically (measured 1.4x faster than fixed shares on this 2-core VM), and
     the result must not depend on which thread took which plane */
  float* shares = grad ? malloc(sizeof(float) * P * HW) : NULL;
  double* losses = calloc((size_t)P, sizeof(double));
  if ((grad && !shares) || !losses) { free(shares); free(losses); return 1; }
  #pragma omp parallel num_threads(threads) reduction(|:failed)
  {
    int64_t longest = H > W ? H : W;
    for (int64_t t = 0; t < n_terms; ++t)
      for (int64_t s = 0; s < terms[t].n_stages; ++s) {
        const stage* st = terms[t].stages + s;
        const int64_t m[4] = {st->h.n_out, st->w.n_out, st->h.n_in, st->w.n_in};
        for (int q = 0; q < 4; ++q) longest = m[q] > longest ? m[q] : longest;
      }
    float* mem = malloc(sizeof(float) * (6 * buffer + 8 * longest));
    if (!mem) failed = 1;
    #pragma omp for schedule(dynamic, 1)
    for (int64_t p = 0; p < P; ++p) {
      if (!mem) continue;
      float *d = mem, *gd = mem + buffer, *tmp = mem + 2 * buffer, *x = mem + 3 * buffer,
            *y = mem + 4 * buffer, *sg = mem + 5 * buffer, *acc = mem + 6 * buffer;
      const int64_t b = p / (C * K), c = (p / K) % C, j = p % K;
      const float* Jp = J + (b * C + c) * HW;
      point_cdf_difference(Jp, Z + p * HW, edges[j], inv_beta, HW, d);
      if (shares) memset(gd, 0, sizeof(float) * HW);
      for (int64_t t = 0; t < n_terms; ++t) {
        const term* tm = terms + t;
        const float* out = d;
        for (int64_t s = 0; s < tm->n_stages; ++s) {  /* A_alpha D */
          const stage* st = tm->stages + s;
          float* dst = (out == x) ? y : x;
          pass_t(out, tmp, st->w.n_in, &st->h, acc);
          pass_t(tmp, dst, st->h.n_out, &st->w, acc);
          out = dst;
        }
        const int64_t n = tm->out_h * tm->out_w;
        const float* pw = tm->pw + b * tm->pw_bstride + c * tm->pw_cstride;
        losses[p] += tm->scale * weighted_abs_sum(out, pw, n);
        if (!shares) continue;
        for (int64_t i = 0; i < n; ++i)  /* sign(A D) pw scale, then A^T of it */
          sg[i] = (float)((out[i] > 0.0f) - (out[i] < 0.0f)) * pw[i] * tm->scale;
        const float* back = sg;
        for (int64_t s = tm->n_stages - 1; s >= 0; --s) {
          const stage* st = tm->stages + s;
          float* dst = (back == x) ? y : x;
          pass_t(back, tmp, st->w.n_out, &st->ht, acc);
          pass_t(tmp, dst, st->h.n_in, &st->wt, acc);
          back = dst;
        }
        for (int64_t i = 0; i < HW; ++i) gd[i] += back[i];
      }
      if (shares) chain_to_j(Jp, gd, edges[j], inv_beta, k, HW, shares + p * HW);
    }
    free(mem);
  }
  for (int64_t p = 0; p < P; ++p) loss[p / (C * K)] += losses[p];
  if (shares) {
    const int64_t chunk = 4096, n_chunks = (HW + chunk - 1) / chunk;
    #pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t q = 0; q < B * C * n_chunks; ++q) {
      const int64_t bc = q / n_chunks, i0 = (q % n_chunks) * chunk, i1 = HW - i0 < chunk ? HW : i0 + chunk;
      float* g = grad + bc * HW;
      for (int64_t j = 0; j < K; ++j) {
        const float* share = shares + (bc * K + j) * HW;
        for (int64_t i = i0; i < i1; ++i) g[i] += share[i];
      }
    }
  }
  free(shares);
  free(losses);
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
            lib.loi_sigma.argtypes = [ptr, ptr, ptr, i64, i64, i64, i64, i64, ctypes.c_float, ptr, i64, i64, ptr, ptr, ctypes.c_int]
            lib.loi_sigma.restype = ctypes.c_int
            lib.point_cdf.argtypes = [ptr, ptr, i64, i64, i64, ctypes.c_float, ptr, ctypes.c_int]
            lib.point_cdf.restype = None
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

    @property
    def narrow(self) -> bool:
        """Whether the band pays (at most ``_NARROW * n_in`` wide); else the dense product."""
        return self.length <= _NARROW * self.n_in

    @staticmethod
    def of(m: torch.Tensor) -> _Band:
        """The band form of ``m`` (as wide as its widest row's span of nonzeros)."""
        n_out, n_in = m.shape
        nonzero = m.detach().cpu() != 0
        cols = torch.arange(n_in, device="cpu")
        first = torch.where(nonzero, cols, n_in).min(1).values
        last = torch.where(nonzero, cols + 1, 0).max(1).values
        length = max(1, int((last - first).clamp(min=0).max()))
        start = torch.minimum(first, torch.tensor(n_in - length, device="cpu")).clamp(min=0)
        weights = torch.gather(m.detach().float().cpu(), 1, start[:, None] + torch.arange(length, device="cpu")[None])
        return _Band(start.contiguous(), weights.contiguous(), n_in)


_bands: dict[int, tuple[_Band, _Band]] = {}  # id(matrix) -> band forms of m and m^T


def _forms(m: torch.Tensor) -> tuple[_Band, _Band]:
    """Band forms of ``m`` and ``m^T``, cached per matrix object."""
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
    if not (bh.narrow and bw.narrow):
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
