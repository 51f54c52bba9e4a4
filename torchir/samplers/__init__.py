"""Stateful samplers: pixel samplers (paper 000) and ReSTIR reservoirs (paper 004).

``SAMPLERS`` maps the names a YAML config uses (``sampler: {type: adaptive, budget: 0.25}``)
to sampler classes; each is built as ``SAMPLERS[type](scene, **options)``.
"""
from .pixel import AdaptivePixelSampler, LossPixelSampler, PixelBatch, PixelSampler, SampledLoss, UniformPixelSampler, sampled_loss
from .restir import ReSTIROptions, ReSTIRSampler

SAMPLERS: dict[str, type] = {  # name -> sampler class, constructed as cls(scene, **options)
    "uniform": UniformPixelSampler,
    "loss": LossPixelSampler,
    "adaptive": AdaptivePixelSampler,
    "restir": ReSTIRSampler,
}

__all__ = ["SAMPLERS", "PixelBatch", "SampledLoss", "sampled_loss", "PixelSampler", "UniformPixelSampler", "LossPixelSampler", "AdaptivePixelSampler", "ReSTIRSampler", "ReSTIROptions"]
