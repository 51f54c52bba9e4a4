"""A render's backward run a second time (``retain_graph=True``). Dr.Jit's ``dr.wrap`` deletes the
AD edges at the first backward, so a second one silently returned the first one's gradient (a
Jacobian row by row, two losses on one image: measured on cbox, ``[13.35, 8.79, 3.80]`` again
where a fresh render gives ``[40.05, 0, 0]``). torchir's wrapper (``torchir.functions._wrap``)
refuses it with what to do; keeping the edges instead corrupted memory in a full run (see there)."""
from __future__ import annotations

import gc

import pytest
import torch

from torchir.functions import render, render_pixels
from torchir.functions.render import _RenderOp

from tests.helpers import DEVICE

KEY = "red.reflectance.value"


def _weights(shape: torch.Size) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator(device=DEVICE).manual_seed(3))


def test_a_second_render_backward_is_refused_and_the_first_is_right(cbox):
    x = cbox.get(KEY).requires_grad_()
    image = render(cbox, {KEY: x}, spp=4, seed=11)
    w = _weights(image.shape)
    first, = torch.autograd.grad(image, x, w, retain_graph=True)
    with pytest.raises(RuntimeError, match="already back-propagated.*Render again"):
        torch.autograd.grad(image, x, torch.ones_like(image))
    fresh, = torch.autograd.grad(render(cbox, {KEY: x}, spp=4, seed=11), x, w)
    torch.testing.assert_close(first, fresh, rtol=1e-5, atol=1e-7)


def test_a_second_render_pixels_backward_is_refused(cbox):
    x = cbox.get(KEY).requires_grad_()
    values = render_pixels(cbox, {KEY: x}, torch.arange(0, 256, 3), spp=2, seed=4)
    torch.autograd.grad(values.sum(), x, retain_graph=True)
    with pytest.raises(RuntimeError, match="already back-propagated"):
        torch.autograd.grad(values.sum(), x)


def test_a_second_backward_through_a_restir_render_is_refused(painting):
    from torchir.samplers import ReSTIRSampler

    key = "wall.bsdf.reflectance.value"
    x = painting.get(key).requires_grad_()
    image = render(painting, {key: x}, spp=1, seed=2, sampler=ReSTIRSampler(painting))
    first, = torch.autograd.grad(image.sum(), x, retain_graph=True)
    assert torch.isfinite(first).all() and first.abs().sum() > 0
    with pytest.raises(RuntimeError, match="already back-propagated"):
        torch.autograd.grad(image.sum(), x)


def test_the_render_op_is_freed_with_its_image(cbox):
    def live_ops() -> int:
        gc.collect()
        return sum(type(o) is _RenderOp for o in gc.get_objects())

    before = live_ops()
    x = cbox.get(KEY).requires_grad_()
    image = render(cbox, {KEY: x}, spp=1, seed=1)
    image.sum().backward()
    del image
    assert live_ops() == before
