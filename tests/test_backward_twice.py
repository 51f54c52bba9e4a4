"""A render's backward run more than once (``retain_graph=True``): each backward is the gradient
of its own output gradient. Dr.Jit's ``dr.wrap`` deleted the AD edges at the first backward, so
a second one silently returned the first one's gradient (a Jacobian row by row, two losses on one
image); torchir's wrapper (``torchir.functions._wrap``) keeps them until torch drops the graph."""
from __future__ import annotations

import gc

import pytest
import torch

import torchir
from torchir.functions import render, render_pixels
from torchir.functions.render import _RenderOp

KEY = "red.reflectance.value"


def _two_weights(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return torch.rand(image.shape, generator=g), torch.rand(image.shape, generator=g) - 0.5


def test_render_backward_twice_gives_each_output_gradients_own_gradient(cbox):
    x = cbox.get(KEY).requires_grad_()
    image = render(cbox, {KEY: x}, spp=4, seed=11)
    w1, w2 = _two_weights(image)
    g1, = torch.autograd.grad(image, x, w1, retain_graph=True)
    g2, = torch.autograd.grad(image, x, w2, retain_graph=True)
    g12, = torch.autograd.grad(image, x, w1 + w2)
    fresh, = torch.autograd.grad(render(cbox, {KEY: x}, spp=4, seed=11), x, w2)
    assert not torch.allclose(g1, g2, rtol=0.1)  # the weights really differ
    torch.testing.assert_close(g2, fresh, rtol=1e-5, atol=1e-7)  # the same replayed paths
    torch.testing.assert_close(g1 + g2, g12, rtol=1e-4, atol=1e-6)  # one linear map


def test_render_pixels_backward_twice(cbox):
    x = cbox.get(KEY).requires_grad_()
    index = torch.arange(0, 256, 3)
    values = render_pixels(cbox, {KEY: x}, index, spp=2, seed=4)
    w1, w2 = _two_weights(values)
    g1, = torch.autograd.grad(values, x, w1, retain_graph=True)
    g2, = torch.autograd.grad(values, x, w2)
    fresh, = torch.autograd.grad(render_pixels(cbox, {KEY: x}, index, spp=2, seed=4), x, w2)
    assert not torch.allclose(g1, g2, rtol=0.1)
    torch.testing.assert_close(g2, fresh, rtol=1e-5, atol=1e-7)


def test_a_second_backward_through_a_restir_render_is_refused(painting):
    from torchir.samplers import ReSTIRSampler

    key = "wall.bsdf.reflectance.value"
    x = painting.get(key).requires_grad_()
    image = render(painting, {key: x}, spp=1, seed=2, sampler=ReSTIRSampler(painting))
    first, = torch.autograd.grad(image.sum(), x, retain_graph=True)
    assert torch.isfinite(first).all() and first.abs().sum() > 0
    with pytest.raises(RuntimeError, match="cannot run twice"):
        torch.autograd.grad(image.sum(), x)


def test_the_render_op_is_freed_with_its_image(cbox):
    """The kept AD edges hold the op (its values and bindings) only as long as the image."""
    def live_ops() -> int:
        gc.collect()
        return sum(type(o) is _RenderOp for o in gc.get_objects())

    before = live_ops()
    x = cbox.get(KEY).requires_grad_()
    image = render(cbox, {KEY: x}, spp=1, seed=1)
    image.sum().backward()
    del image
    assert live_ops() == before
