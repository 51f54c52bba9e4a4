"""``AdamUniform``: one second-moment scale per parameter tensor, the maximum of its entries'
(Nicolet et al. 2021); pinned by hand against the formula and against Dr.Jit's
``mi.ad.Adam(uniform=True)`` (the optimiser of Mitsuba's shape tutorial) on the same gradients."""
from __future__ import annotations

import io
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch

from tests.helpers import DEVICE, raised_message
from torchir.geometry import AdamUniform


def test_one_step_by_hand():
    """Step 1 with β = (0.8, 0.9): ``m = 0.2 g``, ``v = 0.1 g²``, each entry moves by
    ``lr √(1 - β2) / (1 - β1) · m / √(max v + ε²)``: the largest gradient sets one scale for all;
    a second tensor keeps its own scale."""
    g = torch.tensor([[0.5, -2.0], [1.0, 0.0]], device=DEVICE)
    h = torch.tensor([1e-3, -1e-3], device=DEVICE)
    p, q = torch.zeros(2, 2, device=DEVICE, requires_grad=True), torch.ones(2, device=DEVICE, requires_grad=True)
    opt = AdamUniform([p, q], lr=0.3, betas=(0.8, 0.9), eps=1e-8)
    p.grad, q.grad = g.clone(), h.clone()
    opt.step()
    scale = 0.3 * math.sqrt(1 - 0.9) / (1 - 0.8)
    expected_p = -scale * (0.2 * g) / math.sqrt(0.1 * 4.0 + 1e-16)  # max g² = 4
    expected_q = 1 - scale * (0.2 * h) / math.sqrt(0.1 * 1e-6 + 1e-16)
    torch.testing.assert_close(p.detach(), expected_p, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(q.detach(), expected_q, rtol=1e-6, atol=1e-7)
    # the second step by hand too: the moments are running averages, both bias corrections at t = 2
    p.grad = -g
    opt.step()
    m, v = 0.8 * 0.2 * g + 0.2 * (-g), 0.9 * 0.1 * g**2 + 0.1 * g**2
    step_2 = 0.3 * math.sqrt(1 - 0.9**2) / (1 - 0.8**2) * m / math.sqrt(float(v.max()) + 1e-16)
    torch.testing.assert_close(p.detach(), expected_p - step_2, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("eps", [1e-8, 1e-2])
def test_matches_mitsubas_uniform_adam_over_several_steps(eps):
    """Five steps of two parameters of different gradient scales (a mesh's latent, a colour) on
    the same gradients as Dr.Jit's ``Adam(uniform=True)``: the same values, for ε inside Dr.Jit's
    ``√(v + ε²)`` form (its default) and in its ``√v + ε`` form."""
    gen = torch.Generator(device="cpu").manual_seed(3)
    grads = [(torch.randn(12, generator=gen, dtype=torch.float64), 1e-2 * torch.randn(3, generator=gen, dtype=torch.float64))
             for _ in range(5)]
    start = {"latent": np.linspace(-1, 1, 12), "colour": np.array([0.2, 0.5, 0.8])}
    theirs = mi.ad.Adam(lr=0.05, uniform=True, beta_1=0.85, beta_2=0.99, epsilon=eps)
    for key, value in start.items():
        theirs[key] = mi.Float(value)
    ours = {k: torch.tensor(v, dtype=torch.float32, device=DEVICE, requires_grad=True) for k, v in start.items()}
    opt = AdamUniform(ours.values(), lr=0.05, betas=(0.85, 0.99), eps=eps)
    for g_latent, g_colour in grads:
        for key, g in (("latent", g_latent), ("colour", g_colour)):
            dr.set_grad(theirs[key], mi.Float(g.cpu().numpy()))
            ours[key].grad = g.to(device=DEVICE, dtype=torch.float32)
        theirs.step()
        opt.step()
        for key in start:
            np.testing.assert_allclose(ours[key].detach().cpu().numpy(), np.array(theirs[key]), rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.array(theirs["latent"]), start["latent"])  # they moved


def test_state_dict_round_trips():
    """Two steps, a state dict saved as a checkpoint is (``torch.save``), a new optimiser loaded
    from it: the next steps are the same."""
    p = torch.linspace(0, 1, 6, device=DEVICE).requires_grad_()
    opt = AdamUniform([p], lr=0.1)
    grads = [torch.randn(6, device=DEVICE) for _ in range(4)]
    for g in grads[:2]:
        p.grad = g.clone()
        opt.step()
    q = p.detach().clone().requires_grad_()
    resumed = AdamUniform([q], lr=0.1)
    buffer = io.BytesIO()
    torch.save(opt.state_dict(), buffer)
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    assert resumed.state[q]["step"] == 2
    for g in grads[2:]:
        p.grad, q.grad = g.clone(), g.clone()
        opt.step()
        resumed.step()
    torch.testing.assert_close(q, p, rtol=0, atol=0)


def test_parameters_without_gradient_stay_and_bad_settings_are_refused():
    p, q = torch.ones(3, device=DEVICE, requires_grad=True), torch.ones(3, device=DEVICE, requires_grad=True)
    opt = AdamUniform([p, q], lr=0.1)
    p.grad = torch.ones(3, device=DEVICE)
    opt.step()
    assert bool((q == 1).all()) and bool((p < 1).all()) and q not in opt.state
    assert "betas must each be in [0, 1)" in raised_message(ValueError, AdamUniform, [p], lr=0.1, betas=(0.9, 1.0))
    assert "lr must be >= 0" in raised_message(ValueError, AdamUniform, [p], lr=-1.0)
    assert "eps must be >= 0" in raised_message(ValueError, AdamUniform, [p], lr=0.1, eps=-1e-8)
