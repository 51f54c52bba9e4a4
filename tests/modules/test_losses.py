"""Per-pixel losses (torchir.modules.losses): values against torch's own reductions, the
relative L2 weighting, per-pixel terms for pixel sampling, and the argument checks."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from torchir.modules import PIXEL_LOSSES, L1Loss, L2Loss, RelativeL2Loss, l1_loss, l2_loss, relative_l2_loss

from tests.helpers import DEVICE

D64 = torch.float64


def _pair(shape=(2, 3, 5, 4), seed=0):
    g = torch.Generator(device=DEVICE).manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=D64), torch.rand(shape, generator=g, dtype=D64)


def _relative(r, t, eps):
    return (r - t).square() / (t.square() + eps)


@pytest.mark.parametrize("reduction", ["mean", "sum", "none"])
def test_l1_l2_match_torch(reduction):
    """The functions and modules equal torch's l1/mse losses under every reduction."""
    r, t = _pair()
    torch.testing.assert_close(l1_loss(r, t, reduction), F.l1_loss(r, t, reduction=reduction), rtol=1e-12, atol=0)
    torch.testing.assert_close(l2_loss(r, t, reduction), F.mse_loss(r, t, reduction=reduction), rtol=1e-12, atol=0)
    torch.testing.assert_close(L1Loss(reduction)(r, t), F.l1_loss(r, t, reduction=reduction), rtol=1e-12, atol=0)
    torch.testing.assert_close(L2Loss(reduction)(r, t), F.mse_loss(r, t, reduction=reduction), rtol=1e-12, atol=0)


def test_default_reduction_is_mean():
    r, t = _pair()
    for fn, name in [(l1_loss, "l1"), (l2_loss, "l2"), (relative_l2_loss, "relative_l2")]:
        assert fn(r, t).item() == pytest.approx(fn(r, t, reduction="mean").item(), rel=1e-12)
        assert PIXEL_LOSSES[name]()(r, t).item() == pytest.approx(fn(r, t).item(), rel=1e-12)
        assert PIXEL_LOSSES[name]().reduction == "mean"


@pytest.mark.parametrize("eps", [1e-2, 0.5])
def test_relative_l2_weights_by_target_squared(eps):
    """``(r - t)^2 / (t^2 + eps)``: the same relative error weighs alike at any brightness;
    the default ``eps`` is 1e-2 for the function and the module alike."""
    r, t = _pair()
    for reduction in ("mean", "sum", "none"):
        expected = _relative(r, t, eps)
        expected = expected.mean() if reduction == "mean" else expected.sum() if reduction == "sum" else expected
        torch.testing.assert_close(relative_l2_loss(r, t, eps, reduction), expected, rtol=1e-12, atol=0)
        torch.testing.assert_close(RelativeL2Loss(eps, reduction)(r, t), expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(relative_l2_loss(r, t), _relative(r, t, 1e-2).mean(), rtol=1e-12, atol=0)
    torch.testing.assert_close(RelativeL2Loss()(r, t), _relative(r, t, 1e-2).mean(), rtol=1e-12, atol=0)
    assert RelativeL2Loss().eps == 1e-2


def test_relative_l2_denominator_is_constant():
    """The weight ``1 / (t^2 + eps)`` is detached: the target's gradient is only the
    numerator's, minus the rendered image's."""
    r, t = _pair()
    r, t = r.requires_grad_(), t.requires_grad_()
    gr, gt = torch.autograd.grad(relative_l2_loss(r, t, 0.1, "sum"), (r, t))
    torch.testing.assert_close(gr, 2 * (r - t).detach() / (t.detach().square() + 0.1), rtol=1e-12, atol=0)
    torch.testing.assert_close(gt, -gr, rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", sorted(PIXEL_LOSSES))
@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_pixel_terms_average_to_the_loss(name, reduction):
    """``loss(image) == mean_j l_j`` over the image's pixels (what pixel sampling estimates)."""
    r, t = _pair((1, 3, 6, 5))
    loss = PIXEL_LOSSES[name](reduction=reduction)
    assert loss.pixelwise is True
    flat = lambda x: x[0].flatten(1).T  # noqa: E731, (N, C) pixels
    terms = loss.pixel_terms(flat(r), flat(t), 30)
    assert terms.shape == (30,)
    assert terms.mean().item() == pytest.approx(loss(r, t).item(), rel=1e-12)


def test_pixel_terms_refuse_reduction_none():
    r, t = _pair((4, 3))
    with pytest.raises(ValueError, match="^pixel sampling needs a loss with reduction 'mean' or 'sum', not 'none'$"):
        L2Loss("none").pixel_terms(r, t, 4)


def test_registry_and_repr():
    assert PIXEL_LOSSES == {"l1": L1Loss, "l2": L2Loss, "relative_l2": RelativeL2Loss}
    assert repr(L2Loss("sum")) == "L2Loss(reduction='sum')"
    assert repr(RelativeL2Loss(0.25, "none")) == "RelativeL2Loss(eps=0.25, reduction='none')"


def test_bad_arguments():
    r, t = _pair()
    with pytest.raises(TypeError, match="^rendered and target must be torch tensors$"):
        l1_loss(r.cpu().numpy(), t)
    with pytest.raises(TypeError, match="^rendered and target must be torch tensors$"):
        l2_loss(r, t.cpu().numpy())
    with pytest.raises(ValueError, match=r"^rendered and target shapes differ: \(2, 3, 5, 4\) vs \(2, 3, 5, 3\)"):
        relative_l2_loss(r, t[..., :3])
    for make in (lambda: L1Loss("avg"), lambda: L2Loss("avg"), lambda: RelativeL2Loss(reduction="avg"), lambda: l1_loss(r, t, "avg")):
        with pytest.raises(ValueError, match=r"^reduction must be one of \('mean', 'sum', 'none'\), got 'avg'"):
            make()
    for eps in (0.0, -1.0):
        with pytest.raises(ValueError, match=f"^eps must be > 0, got {eps}$"):
            RelativeL2Loss(eps)


def test_relative_l2_gradients_match_its_docstring():
    """gradcheck of both inputs: ``rendered``'s gradient is the true derivative; ``target``
    does get a gradient (the docstring must not say it gets none), but only through the
    difference, so it is not the derivative of the formula in ``target``."""
    r, t = _pair((1, 2, 3, 3), seed=1)
    r, t = r.requires_grad_(), (t + 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: relative_l2_loss(x, t.detach(), 0.1), (r,))
    assert not torch.autograd.gradcheck(lambda y: relative_l2_loss(r.detach(), y, 0.1), (t,), raise_exception=False)
    gr, gt = torch.autograd.grad(relative_l2_loss(r, t, 0.1), (r, t))
    assert torch.count_nonzero(gt) == gt.numel()
    torch.testing.assert_close(gt, -gr, rtol=1e-12, atol=0)
    doc = " ".join(relative_l2_loss.__doc__.split())
    assert "no gradient flows" not in doc and "only through the difference" in doc
