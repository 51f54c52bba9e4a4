"""torchir.testing.gradcheck must pass correct gradients and catch wrong ones."""
from __future__ import annotations

import pytest
import torch

from torchir.functions import render
from torchir.testing import GradcheckError, check_gradients, gradcheck

KEY = "red.reflectance.value"


class _ScaleGrad(torch.autograd.Function):
    """Identity forward, gradient scaled by ``factor``: a deliberately wrong derivative."""

    @staticmethod
    def forward(ctx, x, factor):
        ctx.factor = factor
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.factor, None


def _loss(scene, factor=1.0):
    target = render(scene, {}, spp=32, seed=777).detach() * 0.5

    def loss(p, seed):
        img = render(scene, p, spp=8, seed=seed)
        return ((_ScaleGrad.apply(img, factor) - target) ** 2).mean()

    return loss


def test_passes_a_correct_render_gradient(cbox, red):
    report = check_gradients(_loss(cbox), {KEY: red}, seeds=range(8))
    assert report.passed, report
    assert len(report.checks) == 2 and all(c.name == KEY for c in report.checks)


@pytest.mark.parametrize("factor", [1.5, -1.0])
def test_catches_a_wrong_render_gradient(cbox, red, factor):
    with pytest.raises(GradcheckError, match=KEY):
        gradcheck(_loss(cbox, factor), {KEY: red}, seeds=range(8))
    assert gradcheck(_loss(cbox, factor), {KEY: red}, seeds=range(8), raise_exception=False) is False


def test_reports_which_parameter_failed():
    a = torch.tensor([1.0, 2.0], requires_grad=True)
    b = torch.tensor([0.5], requires_grad=True)

    def loss(p, seed):  # deterministic: b's gradient is wrong by a factor 2
        return (p["a"] ** 2).sum() + _ScaleGrad.apply(p["b"] ** 3, 2.0).sum()

    report = check_gradients(loss, {"a": a, "b": b}, seeds=range(3), eps=1e-3)
    assert {c.name for c in report.failed} == {"b"}
    assert "NO" in str(report) and "yes" in str(report)


def test_rejects_unusable_arguments():
    x = torch.ones(2, requires_grad=True)
    with pytest.raises(ValueError, match="3 seeds"):
        check_gradients(lambda p, s: p["x"].sum(), {"x": x}, seeds=[0, 1])
    with pytest.raises(ValueError, match="requires grad"):
        check_gradients(lambda p, s: p["x"].sum(), {"x": x.detach()})
