"""Grid volumes on the torch side: resampling a ``gridvolume``'s data in Mitsuba's voxel convention.

Mitsuba's ``gridvolume`` stores its values as a ``(Z, Y, X, C)`` tensor over the unit cube of its
local frame: voxel ``(k, j, i)`` is centred at local ``((i + 0.5) / X, (j + 0.5) / Y, (k + 0.5) / Z)``,
and between centres it interpolates trilinearly, clamping at the border (its default
``filter_type: trilinear``, ``wrap_mode: clamp``). :func:`resample` evaluates that field at the voxel
centres of another resolution, so a resampled grid is what Mitsuba itself would look up there: a
coarse-to-fine fit renders (nearly) the same image just before and after a resize.

Upsampling, this equals ``dr.resample(t, shape, filter="linear")`` and ``dr.upsample`` of a linear
``Texture3f`` (Mitsuba's volume tutorial). Downsampling, it point-samples the trilinear field (no
low-pass filter, as Mitsuba's lookup), where ``dr.resample`` averages over the wider footprint.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

__all__ = ["resample", "voxel_centres", "check_grid_shape"]


def check_grid_shape(shape: object, what: str = "shape") -> tuple[int, int, int]:
    """``shape`` as a ``(Z, Y, X)`` tuple of ints >= 1, or a ``ValueError`` naming ``what``."""
    if isinstance(shape, (str, bytes)) or not isinstance(shape, Sequence) or len(shape) != 3:
        raise ValueError(f"{what} must be (Z, Y, X), three ints >= 1, got {shape!r}")
    if any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in shape):
        raise ValueError(f"{what} must be (Z, Y, X), three ints >= 1, got {shape!r}")
    return tuple(int(n) for n in shape)  # type: ignore[return-value]


def resample(grid: torch.Tensor, shape: Sequence[int]) -> torch.Tensor:
    """Resample a grid volume to ``shape`` (trilinear, Mitsuba's voxel convention: module docstring).

    Differentiable in ``grid``; a linear function of its entries, so it also resamples an
    optimiser's moments.

    Args:
        grid: ``(Z, Y, X, C)`` values, Mitsuba's ``gridvolume`` layout (float32 or float64).
        shape: the new ``(Z', Y', X')``.

    Returns:
        ``(Z', Y', X', C)``, ``grid``'s dtype and device (a copy, also when the size is unchanged).

    Example:
        >>> ramp = torch.arange(4.0).reshape(1, 1, 4, 1).expand(2, 2, 4, 1)   # x = 0, 1, 2, 3
        >>> resample(ramp, (2, 2, 8))[0, 0, 2:6, 0].tolist()                  # half-voxel steps inside
        [0.75, 1.25, 1.75, 2.25]
    """
    if not isinstance(grid, torch.Tensor) or grid.dim() != 4:
        raise ValueError(f"grid must be a (Z, Y, X, C) tensor, got {getattr(grid, 'shape', type(grid).__name__)}")
    if not grid.is_floating_point():
        raise TypeError(f"grid must be a floating-point tensor, got {grid.dtype}")
    shape = check_grid_shape(tuple(shape))
    if tuple(grid.shape[:3]) == shape:
        return grid.clone()
    volume = grid.permute(3, 0, 1, 2).unsqueeze(0)  # (1, C, Z, Y, X)
    # align_corners=False: sample positions (i + 0.5) * in / out - 0.5 in voxel units, clamped to the edge
    out = F.interpolate(volume, size=shape, mode="trilinear", align_corners=False)
    return out[0].permute(1, 2, 3, 0).contiguous()


def voxel_centres(shape: Sequence[int], dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """Local coordinates ``(x, y, z)`` of the voxel centres of a ``(Z, Y, X)`` grid, ``(Z, Y, X, 3)``:
    entry ``[k, j, i]`` is ``((i + 0.5) / X, (j + 0.5) / Y, (k + 0.5) / Z)``."""
    z, y, x = (((torch.arange(n, dtype=dtype, device=device) + 0.5) / n) for n in check_grid_shape(tuple(shape)))
    zz, yy, xx = torch.meshgrid(z, y, x, indexing="ij")
    return torch.stack([xx, yy, zz], dim=-1)
