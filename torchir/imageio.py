"""Writing torch images for people to look at: tone mapping and PNG output."""
from __future__ import annotations

from pathlib import Path

import torch


def to_srgb(image: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear radiance ``(C, H, W)`` -> display sRGB in [0, 1] (clipped, sRGB transfer curve)."""
    x = (image.detach().float() * exposure).clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1.0 / 2.4) - 0.055)


def save_png(path: str | Path, image: torch.Tensor, exposure: float = 1.0) -> Path:
    """Tone-map a linear ``(C, H, W)`` image and write it as an 8-bit PNG; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if image.dim() != 3 or image.shape[0] not in (1, 3):
        raise ValueError(f"expected (C, H, W) with C in (1, 3), got {tuple(image.shape)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = to_srgb(image, exposure).expand(3, -1, -1).permute(1, 2, 0).cpu().numpy()
    plt.imsave(path, rgb)
    return path
