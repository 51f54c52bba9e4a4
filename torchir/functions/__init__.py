"""torch autograd Functions around Dr.Jit renders: the only torch/Dr.Jit boundary in torchir."""
from .gbuffers import render_gbuffers
from .render import render
from ._sampler_op import RenderSampler
from .render_pixels import render_pixels

__all__ = ["render", "render_pixels", "render_gbuffers", "RenderSampler"]
