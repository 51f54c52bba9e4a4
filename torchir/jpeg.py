"""What a JPEG photo did to its colours, and a correction for fitting to it.

Most JPEGs (cameras, ``PIL``, Mitsuba's writer, libjpeg's default) store the two chroma channels
(Cb, Cr of the sRGB-encoded values) at half resolution in both directions ("4:2:0") and
interpolate them back on decoding; each channel is then cut into 8x8 blocks whose DCT
coefficients are rounded to multiples of the file's quantisation steps. Both move colours: next
to a colour edge the decoded target mixes the neighbouring pixels' chroma, and a smooth wall's
blocks round their mean colour the same way. An L2 fit of a colour is pulled off its value
(measured on the Cornell box's lamp: docs/training.md, "JPEG targets").

:func:`subsample_chroma` is the codec's chroma filter, :func:`chroma_sampling` reads from a file
which subsampling it used. The filter follows libjpeg: the encoder averages each ``h x v`` block
of chroma (the last row and column replicated), the decoder's default "fancy" upsampling
interpolates linearly between block centres (triangle weights 9/16, 3/16, 3/16, 1/16 for 2x2; the
edges replicated): ``torch.nn.functional.interpolate(mode="bilinear", align_corners=False)``.
:func:`jpeg_round_trip` is the whole codec: libjpeg itself (through Pillow) re-encoding with the
tables :func:`quantization_tables` reads from the file and the file's subsampling, which gives
back a file written by libjpeg (Mitsuba's writer, Pillow, most software) bit for bit from the
same 8-bit image.

The codec is not linear in radiance (sRGB, rounding): applied to a noisy render it shifts the
render's mean, and linearised about the target it filters the target's already filtered chroma
a second time, which is worse (measured: docs/training.md, "Measurements behind the design").
:class:`CodecCorrection` therefore adds to the render the codec's change of a *running mean* of
the renders, a constant for the gradient: linear in the render, and its own noise averaged away.
Pixel-sampled fits (``render_pixels``) are not corrected: a pixel batch has no neighbours to filter.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import torch
import torch.nn.functional as F

from .imageio import srgb_decode, srgb_encode

__all__ = ["chroma_sampling", "quantization_tables", "subsample_chroma", "jpeg_round_trip", "CodecCorrection"]

# JFIF's R'G'B' -> Y'CbCr (rows Y, Cb, Cr) on values in [0, 1]; the 0.5 offsets of Cb, Cr cancel
_RGB_TO_YCC = torch.tensor([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]], dtype=torch.float64, device="cpu")
_START_OF_FRAME = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def chroma_sampling(path: str | Path) -> tuple[int, int]:
    """``(h, v)``: how many luma pixels a chroma sample of the JPEG at ``path`` spans across and
    down: ``(2, 2)`` for 4:2:0, ``(2, 1)`` for 4:2:2, ``(1, 1)`` for full chroma, a greyscale JPEG
    or a file that is not a JPEG. Read from the frame header (the luma component's sampling
    factors over the chroma components')."""
    for marker, segment in _header_segments(path):
        if marker in _START_OF_FRAME:
            count = segment[9]
            factors = [(segment[11 + 3 * k] >> 4, segment[11 + 3 * k] & 0x0F) for k in range(count)]
            if count < 3:
                return (1, 1)
            (hy, vy), chroma = factors[0], factors[1:3]
            hc, vc = max(h for h, _ in chroma), max(v for _, v in chroma)
            return (max(hy // max(hc, 1), 1), max(vy // max(vc, 1), 1))
    return (1, 1)


def _header_segments(path: str | Path) -> Iterator[tuple[int, bytes]]:
    """``(marker, segment)`` for each header segment of the JPEG at ``path`` before its first
    scan, ``segment`` from the marker's 0xFF on (its length at 2-3, its payload from 4). Nothing
    for a file that is not a JPEG; it stops where a marker must be and is not (malformed)."""
    data = Path(path).read_bytes()
    if data[:2] != b"\xff\xd8":
        return
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xDA:  # start of scan: the headers are over
            return
        length = int.from_bytes(data[i + 2:i + 4], "big")
        yield marker, data[i:i + 2 + length]
        i += 2 + length


def subsample_chroma(image: torch.Tensor, factors: tuple[int, int] = (2, 2), srgb: bool = True) -> torch.Tensor:
    """``image`` as a JPEG with chroma subsampling ``factors`` would decode it (differentiable).

    Args:
        image: linear radiance ``(3, H, W)`` or ``(B, 3, H, W)``; clipped to the codec's [0, 1]
            first (values above 1 are kept as they are: a photo's clipped pixels are masked).
        factors: ``(h, v)`` from :func:`chroma_sampling`; ``(1, 1)`` returns ``image`` unchanged.
        srgb: the file stores sRGB-encoded values (the codec mixes those); False: linear ones.

    Returns:
        the same shape, linear radiance.

    Example:
        >>> edge = torch.zeros(3, 4, 4); edge[0, :, :1] = 1.0   # a red column beside black
        >>> subsample_chroma(edge)[:, 0, 1]                       # the codec bleeds it into its neighbour
        tensor([0.0562, 0.0000, 0.0000])
    """
    h, v = (int(f) for f in factors)
    if (h, v) == (1, 1):
        return image
    if image.dim() not in (3, 4) or image.shape[-3] != 3:
        raise ValueError(f"expected an RGB image (3, H, W) or (B, 3, H, W), got shape {tuple(image.shape)}")
    batched = image if image.dim() == 4 else image[None]
    out = _decode(_mix(_encode(batched.clamp(0.0, 1.0), srgb), h, v).clamp(0.0, 1.0), srgb)  # the decoder clips too
    out = torch.where(batched > 1.0, batched, out)
    return out if image.dim() == 4 else out[0]


class CodecCorrection:
    """Per view, ``image + (f(m) - m)`` with ``f`` what the codec does (:func:`jpeg_round_trip`
    when the file's quantisation tables are known, else the chroma filter :func:`subsample_chroma`)
    and ``m`` a running mean of that view's images (the last ``window`` or so, detached): what the
    codec would change in the render, added as a constant (see the module docstring). State is kept
    in memory only: after a resume the mean starts again from the next render.

    Example::

        correct = CodecCorrection()
        photo = "photo.jpg"
        image = correct(render, view=0, factors=chroma_sampling(photo), tables=quantization_tables(photo))
    """

    def __init__(self, window: int = 32) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = window
        self.means: dict[int, tuple[torch.Tensor, int]] = {}

    def __call__(self, image: torch.Tensor, view: int, factors: tuple[int, int], srgb: bool = True,
                 tables: torch.Tensor | None = None) -> torch.Tensor:
        if tables is None and tuple(int(f) for f in factors) == (1, 1):
            return image
        mean, count = self.means.get(view, (None, 0))
        current = image.detach()
        if mean is None or mean.shape != current.shape:
            mean, count = current.clone(), 0
        count += 1
        mean = mean.lerp(current, 1.0 / min(count, self.window))
        self.means[view] = (mean, count)
        coded = subsample_chroma(mean, factors, srgb) if tables is None else jpeg_round_trip(mean, tables, factors, srgb)
        return image + (coded - mean)


def _encode(x: torch.Tensor, srgb: bool) -> torch.Tensor:
    return srgb_encode(x) if srgb else x


def _decode(x: torch.Tensor, srgb: bool) -> torch.Tensor:
    return srgb_decode(x) if srgb else x


def _mix(x: torch.Tensor, h: int, v: int) -> torch.Tensor:
    """The codec's chroma filter on R'G'B' ``(B, 3, H, W)`` (linear in ``x``)."""
    rows, cols = x.shape[-2:]
    to_ycc = _RGB_TO_YCC.to(x)
    ycc = torch.einsum("ij,bjhw->bihw", to_ycc, x)
    padded = F.pad(ycc[:, 1:], (0, (-cols) % h, 0, (-rows) % v), mode="replicate")
    small = F.avg_pool2d(padded, kernel_size=(v, h), stride=(v, h))
    chroma = F.interpolate(small, scale_factor=(v, h), mode="bilinear", align_corners=False)[..., :rows, :cols]
    return torch.einsum("ij,bjhw->bihw", torch.linalg.inv(to_ycc), torch.cat([ycc[:, :1], chroma], dim=1))


# JPEG's zig-zag scan: entry k of a stored table is coefficient _ZIGZAG[k] (row-major u * 8 + v)
_ZIGZAG = (0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21, 28,
           35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55,
           62, 63)


def quantization_tables(path: str | Path) -> torch.Tensor | None:
    """``(3, 8, 8)``: the quantisation step of each DCT coefficient ``(u, v)`` for the Y, Cb and Cr
    components of the JPEG at ``path`` (read from its DQT and frame headers), or None for a file
    that is not a three-component JPEG."""
    tables: dict[int, torch.Tensor] = {}
    for marker, segment in _header_segments(path):
        if marker == 0xDB:  # define quantisation table(s): [precision << 4 | id, 64 steps in zig-zag order] ...
            j = 4
            while j < len(segment):
                wide, table_id = segment[j] >> 4, segment[j] & 0x0F
                size = 2 if wide else 1
                raw = segment[j + 1:j + 1 + 64 * size]
                if len(raw) < 64 * size:
                    return None
                steps = [int.from_bytes(raw[k * size:(k + 1) * size], "big") for k in range(64)]
                table = torch.zeros(64, dtype=torch.float64, device="cpu")
                table[list(_ZIGZAG)] = torch.tensor(steps, dtype=torch.float64, device="cpu")
                tables[table_id] = table.reshape(8, 8)
                j += 1 + 64 * size
        elif marker in _START_OF_FRAME:
            count = segment[9]
            ids = [segment[12 + 3 * k] for k in range(count)]
            if count != 3 or any(t not in tables for t in ids):
                return None
            return torch.stack([tables[t] for t in ids])
    return None


_PIL_SUBSAMPLING = {(1, 1): 0, (2, 1): 1, (2, 2): 2}  # Pillow's codes for 4:4:4, 4:2:2, 4:2:0


def jpeg_round_trip(image: torch.Tensor, tables: torch.Tensor, factors: tuple[int, int] = (2, 2), srgb: bool = True) -> torch.Tensor:
    """``image`` written as a JPEG with quantisation ``tables`` and chroma subsampling ``factors``,
    and read back: the codec itself (libjpeg through Pillow, baseline, its default integer DCT and
    "fancy" upsampling), so a file written by libjpeg is reproduced bit for bit from the same
    8-bit image. Not differentiable (it rounds): for :class:`CodecCorrection`.

    Args:
        image: linear radiance ``(3, H, W)`` or ``(B, 3, H, W)``; values above 1 are returned as they are.
        tables: ``(3, 8, 8)`` from :func:`quantization_tables` (natural order, Y, Cb, Cr).
        factors: ``(h, v)`` from :func:`chroma_sampling`: ``(1, 1)``, ``(2, 1)`` or ``(2, 2)``.
        srgb: the file stores sRGB-encoded values.

    Returns:
        the same shape and dtype, linear radiance.
    """
    import io

    import numpy as np
    from PIL import Image

    if image.dim() not in (3, 4) or image.shape[-3] != 3:
        raise ValueError(f"expected an RGB image (3, H, W) or (B, 3, H, W), got shape {tuple(image.shape)}")
    if tuple(tables.shape) != (3, 8, 8):
        raise ValueError(f"expected quantisation tables of shape (3, 8, 8), got {tuple(tables.shape)}")
    factors = tuple(int(f) for f in factors)
    if factors not in _PIL_SUBSAMPLING:
        raise ValueError(f"chroma subsampling {factors} is not one of {sorted(_PIL_SUBSAMPLING)}")
    steps = [[int(v) for v in t.flatten().tolist()] for t in tables]
    qtables = steps[:2] if steps[2] == steps[1] else steps
    batched = (image if image.dim() == 4 else image[None]).detach()
    codes = torch.round(255.0 * _encode(batched.double().clamp(0.0, 1.0), srgb)).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    decoded = []
    for frame in codes:
        buffer = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(frame), "RGB").save(buffer, "JPEG", qtables=qtables, subsampling=_PIL_SUBSAMPLING[factors])
        buffer.seek(0)
        decoded.append(np.asarray(Image.open(buffer).convert("RGB")))
    out = _decode(torch.from_numpy(np.stack(decoded)).permute(0, 3, 1, 2).double() / 255.0, srgb).to(batched)
    out = torch.where(batched > 1.0, batched, out)
    return out if image.dim() == 4 else out[0]
