"""The LOI loss's settings: validation of its arguments and images, the intensity transforms and
the paper's presets (Mehta et al. 2025, "Locally Orderless Images for Optimization in
Differentiable Rendering")."""
from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Union

import torch

from ._blur import MIN_SCALE
from ._warnings import user_stacklevel

__all__ = ["LOI_PRESETS", "TRANSFORMS", "FAST_CELL_FRACTION"]

_REDUCTIONS = ("mean", "sum", "none")
_BORDERS = ("pad", "renormalize")
_CHANNELS = ("independent", "luminance")
_LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709, linear RGB
_SMALL_BETA = 1.0 / 128  # below: many bins, gradient only within 3 beta of each value (warns)
_OUT_OF_RANGE_FRACTION = 0.01  # warn when more pixels than this lie beyond k_hi + 3 beta
# The default (exact=False): terms with alpha >= 1 / FAST_CELL_FRACTION px are evaluated on
# cells of floor(FAST_CELL_FRACTION * alpha) px, their input averaged over the same cells first.
# Measured on glossy_highlight at 256² (torchir bench loi --only cost, largest over 3
# renders): loss within 0.037 %, image gradient within 0.66 % of exact; 0.25 gives 1.5 %.
FAST_CELL_FRACTION = 0.15


def _reinhard(x: torch.Tensor) -> torch.Tensor:
    return x / (1 + x.abs())  # x / (1 + x) for radiance, odd-symmetric so negatives stay finite


def _log1p(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.log1p(x.abs())


TRANSFORMS: dict[str, Callable[[torch.Tensor], torch.Tensor] | None] = {
    "identity": None,
    "clamp": None,  # clamps to value_range (resolved at call time)
    "reinhard": _reinhard,
    "log1p": _log1p,
}

# The paper's three settings; the raster preset follows Table 3's caption, not section 4.4's text ("as 4.1").
LOI_PRESETS: dict[str, dict[str, Any]] = {
    "disks": dict(alphas=(1, 5, 15), sigmas=(1, 5, 15, 45), beta=0.125),  # section 4.1, Table 1
    "pathtracing": dict(alphas=(1, 5, 15, 45), sigmas=(1, 5), beta=0.125),  # section 4.2, Table 2
    "raster": dict(alphas=(1, 5, 15, 45), sigmas=(0, 5), beta=0.03125),  # section 4.4, Table 3
}

Transform = Union[str, Callable[[torch.Tensor], torch.Tensor], None]


# ------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class _Config:
    alphas: tuple[float, ...]
    sigmas: tuple[float, ...]
    beta: float
    value_range: tuple[float, float]
    tail: int
    transform: Transform
    channels: str
    border: str
    pad_frac: float
    weights: tuple[tuple[float, ...], ...]  # (len(sigmas), len(alphas))
    relative: bool
    truncate: float
    reduction: str
    low_memory: bool
    cell_fraction: float

    @property
    def n_terms(self) -> int:
        return len(self.sigmas) * len(self.alphas)


def _scales(name: str, values: Sequence[float] | float) -> tuple[float, ...]:
    if isinstance(values, (int, float)) and not isinstance(values, bool):
        values = (values,)
    try:
        out = tuple(float(v) for v in values)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of numbers, got {values!r}") from None
    if not out:
        raise ValueError(f"{name} must not be empty")
    if any(not math.isfinite(v) or v < 0 for v in out):
        raise ValueError(f"{name} must be finite and >= 0, got {out}")
    return tuple(0.0 if v < MIN_SCALE else v for v in out)


def _weights(weights: Any, n_sigmas: int, n_alphas: int) -> tuple[tuple[float, ...], ...]:
    if weights is None:
        return tuple((1.0,) * n_alphas for _ in range(n_sigmas))
    rows = torch.as_tensor(weights, dtype=torch.float64, device="cpu")
    if tuple(rows.shape) != (n_sigmas, n_alphas):
        raise ValueError(f"weights must have shape (len(sigmas), len(alphas)) = {(n_sigmas, n_alphas)}, got {tuple(rows.shape)}")
    if not bool(torch.isfinite(rows).all()) or bool((rows < 0).any()):
        raise ValueError("weights must be finite and >= 0")
    return tuple(tuple(float(w) for w in row) for row in rows)


def _config(
    alphas, sigmas, beta, value_range, tail, transform, channels, border, pad_frac, weights, relative, truncate, reduction, low_memory,
    cell_fraction=None,
    exact=False,
) -> _Config:
    alphas, sigmas = _scales("alphas", alphas), _scales("sigmas", sigmas)
    beta = float(beta)
    if not math.isfinite(beta) or beta <= 0:
        raise ValueError(f"beta must be > 0, got {beta}")
    if beta < _SMALL_BETA:
        warnings.warn(
            f"beta={beta:g} < 1/128: many bins (memory grows with 1/beta) and a pixel only gets a "
            f"gradient where the histograms differ within ~3 beta of its own value",
            stacklevel=user_stacklevel(),
        )
    lo, hi = (float(v) for v in value_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"value_range must be finite (lo, hi) with lo < hi, got {value_range!r}")
    if isinstance(tail, bool) or not isinstance(tail, int) or tail < 0:
        raise ValueError(f"tail must be an int >= 0, got {tail!r}")
    if isinstance(transform, str) and transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {sorted(TRANSFORMS)} or a callable, got {transform!r}")
    if transform is not None and not isinstance(transform, str) and not callable(transform):
        raise TypeError(f"transform must be a name or a callable, got {type(transform).__name__}")
    if channels not in _CHANNELS:
        raise ValueError(f"channels must be one of {_CHANNELS}, got {channels!r}")
    if border not in _BORDERS:
        raise ValueError(f"border must be one of {_BORDERS}, got {border!r}")
    if not 0 <= float(pad_frac) <= 4:
        raise ValueError(f"pad_frac must be in [0, 4], got {pad_frac}")
    if not float(truncate) > 0:
        raise ValueError(f"truncate must be > 0, got {truncate}")
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")
    if not isinstance(exact, bool):
        raise TypeError(f"exact must be a bool, got {exact!r}")
    if cell_fraction is None:
        cell_fraction = 0.0 if exact else FAST_CELL_FRACTION
    if isinstance(cell_fraction, bool) or not (isinstance(cell_fraction, (int, float)) and 0 <= float(cell_fraction) <= 1):
        raise ValueError(f"cell_fraction must be in [0, 1], got {cell_fraction!r}")
    if exact and cell_fraction:
        raise ValueError(f"exact=True evaluates every pixel: cell_fraction must be 0 or None, got {cell_fraction!r}")
    return _Config(
        alphas=alphas,
        sigmas=sigmas,
        beta=beta,
        value_range=(lo, hi),
        tail=tail,
        transform=transform,
        channels=channels,
        border=border,
        pad_frac=float(pad_frac),
        weights=_weights(weights, len(sigmas), len(alphas)),
        relative=bool(relative),
        truncate=float(truncate),
        reduction=reduction,
        low_memory=bool(low_memory),
        cell_fraction=float(cell_fraction),
    )


# ------------------------------------------------------------------------------ input checks
def _as_batch(name: str, x: Any) -> torch.Tensor:
    """``(B, C, H, W)`` float view of an image argument, with layout/dtype/finiteness checks."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() not in (3, 4):
        raise ValueError(f"{name} must be (C, H, W) or (B, C, H, W), got shape {tuple(x.shape)}")
    if x.shape[-1] in (3, 4) and x.shape[-3] > 4:
        raise ValueError(
            f"{name} has shape {tuple(x.shape)}, which looks like Mitsuba's (H, W, C) layout; "
            f"torchir images are (C, H, W): use img.permute(2, 0, 1) (and drop an alpha channel)"
        )
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point image, got {x.dtype}")
    if x.numel() == 0:
        raise ValueError(f"{name} is empty (shape {tuple(x.shape)})")
    if not bool(torch.isfinite(x.detach()).all()):
        bad = int((~torch.isfinite(x.detach())).sum())
        raise ValueError(f"{name} has {bad} non-finite (NaN/Inf) values")
    x = x if x.dim() == 4 else x.unsqueeze(0)
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


def _check_mask(mask: Any, like: torch.Tensor) -> torch.Tensor:
    if not isinstance(mask, torch.Tensor):
        raise TypeError(f"mask must be a torch.Tensor, got {type(mask).__name__}")
    mask = mask if mask.dim() == 4 else mask.unsqueeze(0) if mask.dim() == 3 else mask
    b, c, h, w = like.shape
    if mask.dim() != 4 or mask.shape[0] not in (1, b) or mask.shape[1] not in (1, c) or tuple(mask.shape[2:]) != (h, w):
        raise ValueError(f"mask must be (B, 1, H, W) or (B, C, H, W) for images {tuple(like.shape)}, got {tuple(mask.shape)}")
    mask = mask.detach().to(like.dtype)
    if not bool(torch.isfinite(mask).all()) or bool((mask < 0).any()):
        raise ValueError("mask must be finite and >= 0")
    mask = mask.expand(b, -1, -1, -1)
    if bool((mask.flatten(1).sum(1) == 0).any()):
        raise ValueError("mask is zero everywhere for some batch item: nothing to compare")
    return mask


# ------------------------------------------------------------------------------ the pipeline
def _transform(x: torch.Tensor, cfg: _Config) -> torch.Tensor:
    """Luminance (optional) and the intensity transform tau (not in the paper, which works on [0, 1])."""
    if cfg.channels == "luminance":
        if x.shape[1] != 3:
            raise ValueError(f"channels='luminance' needs 3 channels, got {x.shape[1]}")
        x = (x * x.new_tensor(_LUMINANCE).view(1, 3, 1, 1)).sum(1, keepdim=True)
    t = cfg.transform
    if t is None or t == "identity":
        return x
    if t == "clamp":
        return x.clamp(*cfg.value_range)
    return (TRANSFORMS[t] if isinstance(t, str) else t)(x)


def _warn_out_of_range(name: str, j: torch.Tensor, cfg: _Config, warned: set[str] | None) -> None:
    if warned is not None and name in warned:
        return
    lo, hi = cfg.value_range
    reach = 3 * cfg.beta
    with torch.no_grad():
        outside = float(((j < lo - reach) | (j > hi + reach)).float().mean())
    if outside > _OUT_OF_RANGE_FRACTION:
        if warned is not None:
            warned.add(name)
        warnings.warn(
            f"LOI loss: {100 * outside:.1f}% of {name}'s values lie beyond value_range {cfg.value_range} "
            f"+- 3 beta, where histograms saturate and differences become invisible; use "
            f"transform='reinhard' (HDR renders) or a wider value_range",
            stacklevel=user_stacklevel(),
        )
