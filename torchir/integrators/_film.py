"""Camera-sample lanes to images."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

__all__ = ["develop"]


def develop(contrib: mi.Color3f, spp: int, h: int, w: int) -> mi.TensorXf:
    """Box-filtered (H, W, 3) image: the mean of each pixel's ``spp`` consecutive lanes
    (a block sum, so the result is deterministic)."""
    chans = [dr.block_sum(c, spp) / spp if spp > 1 else mi.Float(c) for c in (contrib.x, contrib.y, contrib.z)]
    return mi.TensorXf(dr.ravel(mi.Color3f(*chans)), shape=(h, w, 3))
