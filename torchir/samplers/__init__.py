"""Stateful samplers, of two kinds.

* Pixel samplers (:class:`PixelSampler`; ``PIXEL_SAMPLERS``) choose which pixels a step renders,
  with the weights that keep the loss's gradient unbiased (:func:`sampled_loss`,
  :func:`torchir.functions.render_pixels`).
* Render samplers (:class:`RenderSampler`, the protocol :func:`torchir.functions.render` takes as
  ``sampler=``; ``RENDER_SAMPLERS``) render with their own stateful integrator:
  :class:`ReSTIRSampler` reuses light samples across gradient steps (:class:`ReSTIROptions`).

``SAMPLERS`` maps the names a YAML config uses (``sampler: {type: adaptive, budget: 0.25}``)
to either kind; each is built as ``SAMPLERS[type](scene, **options)``.
"""
from .pixel import AdaptivePixelSampler, LossPixelSampler, PixelBatch, PixelSampler, SampledLoss, UniformPixelSampler, sampled_loss
from .restir import ReSTIROptions, ReSTIRSampler

from ..functions._sampler_op import RenderSampler

PIXEL_SAMPLERS: dict[str, type] = {  # choose the pixels a step renders (render_pixels, sampled_loss)
    "uniform": UniformPixelSampler,
    "loss": LossPixelSampler,
    "adaptive": AdaptivePixelSampler,
}
RENDER_SAMPLERS: dict[str, type] = {  # render with their own stateful integrator (render(..., sampler=)): RenderSampler
    "restir": ReSTIRSampler,
}
SAMPLERS: dict[str, type] = {**PIXEL_SAMPLERS, **RENDER_SAMPLERS}  # the YAML names: cls(scene, **options)

__all__ = ["SAMPLERS", "PIXEL_SAMPLERS", "RENDER_SAMPLERS", "RenderSampler", "PixelBatch", "SampledLoss", "sampled_loss", "PixelSampler", "UniformPixelSampler", "LossPixelSampler", "AdaptivePixelSampler", "ReSTIRSampler", "ReSTIROptions"]
