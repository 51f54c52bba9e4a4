"""Image files <-> torch linear radiance, decided in one place.

Every image torchir reads (targets, textures) or writes (previews, results) goes through
:func:`read_image` and :func:`write_image`, so that a value means linear radiance on the torch
side whatever the file's encoding:

==================================  =========================  ==========================
file                                stored as                  ``colorspace="auto"``
==================================  =========================  ==========================
``.exr``, ``.hdr``, ``.pfm``        float, linear              read/written as is
``.png`` (8/16 bit), ``.jpg``       integers, sRGB-encoded     sRGB curve undone / applied
==================================  =========================  ==========================

``colorspace="srgb"`` or ``"linear"`` overrides what the file says (e.g. a PNG that holds
linear data, such as a normal or roughness map: ``"linear"``). Decoding is Mitsuba's own
(``mi.Bitmap``), applied once.

A photo's over-exposed pixels only bound the radiance from below: :func:`clipped_mask` finds
them (at the top code, and for JPEG also what the codec smeared from them), for a loss to leave
them out.
"""
from __future__ import annotations

import contextlib

import math
import numbers
from pathlib import Path
from typing import Literal

import numpy as np
import torch

__all__ = [
    "read_image", "write_image", "to_srgb", "srgb_encode", "srgb_decode", "save_png", "clipped_mask", "is_lossy",
    "COLORSPACES", "LINEAR_SUFFIXES", "ENCODED_SUFFIXES", "LOSSY_SUFFIXES", "SATURATED",
]

ColorSpace = Literal["auto", "srgb", "linear"]
COLORSPACES = ("auto", "srgb", "linear")
LINEAR_SUFFIXES = (".exr", ".hdr", ".pfm")
ENCODED_SUFFIXES = (".png", ".jpg", ".jpeg")
LOSSY_SUFFIXES = (".jpg", ".jpeg")

SATURATED = 0.995  # of the saturation: an 8-bit sRGB 254 decodes to 0.991, so >= 0.995 means 255
# A JPEG codes 8x8 blocks: what it smears from a clipped pixel stays within about a block of it.
LOSSY_REACH = 8
# ... and pulls clipped pixels below the top code (down to 0.87 of the saturation measured at
# quality 50-95), so a pixel that bright in the reach of a clipped one is taken as clipped too.
LOSSY_FLOOR = 0.5


def _check_colorspace(colorspace: str) -> None:
    if colorspace not in COLORSPACES:
        raise ValueError(f"colorspace must be one of {COLORSPACES}, got {colorspace!r}")


def _check_suffix(path: Path) -> None:
    if path.suffix.lower() not in LINEAR_SUFFIXES + ENCODED_SUFFIXES:
        raise ValueError(
            f"{str(path)!r}: unsupported image type {path.suffix!r}; use one of "
            f"{', '.join(LINEAR_SUFFIXES + ENCODED_SUFFIXES)}"
        )


def to_srgb(image: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear radiance ``(C, H, W)`` -> display sRGB in [0, 1] (clipped, sRGB transfer curve)."""
    return srgb_encode((image.detach().float() * exposure).clamp(0.0, 1.0))


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer curve (IEC 61966-2-1) on linear values >= 0, differentiable (the power
    branch never sees values below its threshold, so its gradient stays finite at 0)."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308).pow(1.0 / 2.4) - 0.055)


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`srgb_encode`, on encoded values >= 0, differentiable."""
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055).pow(2.4))


def is_lossy(path: str | Path) -> bool:
    """Whether an image file is lossy-compressed (JPEG), by its suffix."""
    return Path(path).suffix.lower() in LOSSY_SUFFIXES


def clipped_mask(image: torch.Tensor, saturation: float = 1.0, lossy: bool = False) -> torch.Tensor:
    """The pixels of a photo that clipped: they only say "at least this bright".

    A pixel is clipped when any channel is at the top code, ``>= 0.995 * saturation`` (the whole
    pixel: JPEG mixes codes across channels, so a clipped lamp can read (254, 255, 255)). A lossy
    file (``lossy=True``, a JPEG) also smears its clipped pixels: edge pixels of a clipped lamp
    decode a few codes below the top (true radiance far above it) and their neighbours ring. So
    there a pixel is clipped too when any channel is ``>= 0.5 * saturation`` and it lies within
    8 pixels (one JPEG block) of a pixel at the top code; darker neighbours, whose ringing the
    sRGB curve shrinks in linear terms, stay in. ``lossy=False`` (PNG, EXR) is the top-code rule
    alone. A clipped region that JPEG kept entirely below the top code (a lamp of a pixel or two
    at low quality) cannot be told from a bright surface and is not found.

    Args:
        image: linear radiance, ``(C, H, W)`` or ``(B, C, H, W)``, any ``C >= 1`` (greyscale too).
        saturation: radiance at which the photo clipped (1.0 for 8/16-bit files read by
            :func:`read_image`).
        lossy: whether the image was decoded from a lossy file (see :func:`is_lossy`).

    Returns:
        bool, ``(1, H, W)`` or ``(B, 1, H, W)``: True where the pixel clipped (broadcasts over
        the channels).

    Example:
        >>> image = torch.zeros(3, 16, 16); image[:, 4:6, 4:8] = 1.0; image[:, 6, 4:8] = 0.9
        >>> int(clipped_mask(image).sum()), int(clipped_mask(image, lossy=True).sum())
        (8, 12)
    """
    if not isinstance(image, torch.Tensor) or image.dim() not in (3, 4) or image.shape[-3] < 1:
        shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
        raise ValueError(f"expected an image (C, H, W) or a batch (B, C, H, W), got {shape}")
    if not image.is_floating_point():
        raise TypeError(f"expected linear radiance as a floating-point tensor, got {image.dtype}")
    if isinstance(saturation, bool) or not isinstance(saturation, numbers.Real) or not 0 < saturation < math.inf:
        raise ValueError(f"saturation must be a finite number > 0, got {saturation!r}")
    if not isinstance(lossy, bool):
        raise TypeError(f"lossy must be True or False, got {lossy!r}")
    brightest = image.detach().amax(dim=-3, keepdim=True)
    clipped = brightest >= saturation * SATURATED
    if not lossy or not bool(clipped.any()):
        return clipped
    batch = clipped if image.dim() == 4 else clipped.unsqueeze(0)
    near = torch.nn.functional.max_pool2d(batch.float(), 2 * LOSSY_REACH + 1, stride=1, padding=LOSSY_REACH) > 0
    near = near if image.dim() == 4 else near.squeeze(0)
    return clipped | (near & (brightest >= saturation * LOSSY_FLOOR))


def read_image(path: str | Path, colorspace: ColorSpace = "auto", channels: int | None = None) -> torch.Tensor:
    """Read an image file as linear radiance, ``(C, H, W)`` float32 with ``C`` in {1, 3}.

    Args:
        path: an EXR/HDR/PFM (linear) or PNG/JPEG (8/16-bit, sRGB-encoded) file.
        colorspace: ``"auto"`` (the file's own encoding, table above), ``"srgb"`` (undo the
            sRGB curve whatever the file says) or ``"linear"`` (take the stored values as is).
        channels: ``None``: as stored (a greyscale file gives ``C = 1``, which broadcasts
            silently against a ``(3, H, W)`` render in a loss); ``3``: a greyscale file's channel
            repeated, as a target for an RGB render; ``1``: refuses a colour file.

    An alpha channel is dropped when it is fully opaque and refused otherwise (torchir
    compares radiance; a transparent pixel has none to compare).
    """
    import mitsuba as mi

    from . import backend

    _check_colorspace(colorspace)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {str(path)!r} (resolved to {path.resolve()})")
    _check_suffix(path)
    backend.variant()
    with _exr_threads(path):
        bitmap = mi.Bitmap(str(path))
    if colorspace != "auto":
        bitmap.set_srgb_gamma(colorspace == "srgb")
    formats = mi.Bitmap.PixelFormat
    has_alpha = bitmap.has_alpha()
    grey = bitmap.pixel_format() in (formats.Y, formats.YA)
    target_format = (formats.YA if has_alpha else formats.Y) if grey else (formats.RGBA if has_alpha else formats.RGB)
    # srgb_gamma=False asks for linear output: Mitsuba undoes the curve iff the bitmap is sRGB
    array = np.array(bitmap.convert(target_format, mi.Struct.Type.Float32, srgb_gamma=False), dtype=np.float32)
    if array.ndim == 2:
        array = array[..., None]
    if has_alpha:
        alpha = array[..., -1]
        if float(alpha.min()) < 1.0 - 1e-6:
            raise ValueError(
                f"{str(path)!r} has an alpha channel with transparent pixels (min alpha {alpha.min():.3g}); "
                f"torchir needs radiance everywhere: flatten it onto a background and save it without alpha"
            )
        array = array[..., :-1]
    if channels not in (None, 1, 3):
        raise ValueError(f"channels must be None, 1 or 3, got {channels!r}")
    if channels == 1 and array.shape[-1] != 1:
        raise ValueError(f"{str(path)!r} has {array.shape[-1]} colour channels; channels=1 asks for a greyscale image")
    if channels == 3 and array.shape[-1] == 1:
        array = np.repeat(array, 3, axis=-1)
    return torch.from_numpy(np.ascontiguousarray(array)).permute(2, 0, 1).contiguous()


def write_image(path: str | Path, image: torch.Tensor, colorspace: ColorSpace = "auto", exposure: float = 1.0) -> Path:
    """Write linear radiance ``(C, H, W)`` (``C`` in {1, 3}) so that :func:`read_image` gives it back.

    EXR/HDR/PFM hold the values as float (``exposure`` ignored); PNG/JPEG hold them scaled by
    ``exposure``, clipped to [0, 1], sRGB-encoded (``colorspace="linear"``: not encoded) and
    quantised to 8 bits. Returns the path.
    """
    import mitsuba as mi

    from . import backend

    _check_colorspace(colorspace)
    if not isinstance(image, torch.Tensor) or image.dim() != 3 or image.shape[0] not in (1, 3):
        shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
        raise ValueError(f"expected an image (C, H, W) with C in (1, 3), got {shape}")
    path = Path(path)
    _check_suffix(path)
    if not bool(torch.isfinite(image).all()):
        raise ValueError(f"image for {str(path)!r} has NaN/Inf pixels")
    backend.variant()
    path.parent.mkdir(parents=True, exist_ok=True)
    array = np.ascontiguousarray(image.detach().float().permute(1, 2, 0).cpu().numpy())
    formats = mi.Bitmap.PixelFormat
    pixel_format = formats.Y if array.shape[-1] == 1 else formats.RGB
    encoded = path.suffix.lower() in ENCODED_SUFFIXES
    srgb = colorspace == "srgb" or (colorspace == "auto" and encoded)
    if srgb:
        array = _srgb_encode(np.clip(array * exposure, 0.0, 1.0) if encoded else array)
    elif encoded:
        array = np.clip(array * exposure, 0.0, 1.0)
    if encoded:
        # round to the nearest code ourselves: Mitsuba's float -> uint8 conversion is off by up to
        # one code (it gave 187 for 187.5 and 224 for 224.6)
        array = np.rint(array * 255.0).astype(np.uint8)
    bitmap = mi.Bitmap(array, pixel_format)
    bitmap.set_srgb_gamma(srgb)
    with _exr_threads(path):
        bitmap.write(str(path))
    return path


@contextlib.contextmanager
def _exr_threads(path: Path):
    """Mitsuba's OpenEXR reader and writer wait forever for a worker when Dr.Jit's pool has one
    thread (``drjit.set_thread_count(1)``, as users set for determinism: with Mitsuba 3.9.1 and
    Dr.Jit 1.5, reading or writing a 64x64 EXR never returned). Widen the pool to two for the
    file, then restore it."""
    import drjit as dr

    threads = dr.thread_count()
    if path.suffix.lower() != ".exr" or threads >= 2:
        yield
        return
    dr.sync_thread()
    dr.set_thread_count(2)
    try:
        yield
    finally:
        dr.set_thread_count(threads)


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (IEC 61966-2-1), for values >= 0."""
    x = np.maximum(x, 0.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def save_png(path: str | Path, image: torch.Tensor, exposure: float = 1.0) -> Path:
    """Tone-map a linear ``(C, H, W)`` image and write it as an 8-bit sRGB PNG; returns the path."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"save_png writes .png files, got {str(path)!r}")
    return write_image(path, image, exposure=exposure)
