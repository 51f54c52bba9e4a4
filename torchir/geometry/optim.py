"""Uniform Adam: Adam whose second moment is one scalar per parameter tensor, so that every
vertex of a mesh moves at the same rate (Nicolet et al. 2021, "Large Steps in Inverse Rendering of
Geometry", §5)."""
from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import torch

__all__ = ["AdamUniform"]


class AdamUniform(torch.optim.Optimizer):
    """Adam with the *maximum* over a parameter's entries of its second-moment average as the
    one scale of all its entries (``mitsuba.ad.Adam(uniform=True)``).

    Per parameter tensor, with gradient ``g`` at step ``t``::

        m = β1 m + (1 - β1) g               (per entry)
        v = β2 v + (1 - β2) g²              (per entry)
        p -= lr √(1 - β2^t) / (1 - β1^t) · m / √(max(v) + ε²)      (ε <= 1e-6)
        p -= lr √(1 - β2^t) / (1 - β1^t) · m / (√max(v) + ε)       (ε > 1e-6)

    That is Dr.Jit's ``Adam(uniform=True)`` (what Mitsuba's shape tutorial uses), its two forms
    of ε included. The paper's ``largesteps.optimize.AdamUniform`` takes the same maximum
    (``max √v̂``, of the bias-corrected ``v̂ = v / (1 - β2^t)``) but adds a fixed ε = 1e-8 to
    ``√max(v̂)``: the two differ only where ``√max(v)`` is within a few ε of zero.

    Args:
        params: the parameters (or parameter groups), e.g. ``[u]`` of :class:`LargeSteps`.
        lr: the learning rate (the tutorial: 0.1).
        betas: ``(β1, β2)``, each in ``[0, 1)``.
        eps: ``ε >= 0``.

    Example:
        >>> u = torch.zeros(4, 3, requires_grad=True)
        >>> opt = AdamUniform([u], lr=0.1)
        >>> u.grad = torch.tensor([[1.0, 0, 0], [0, 2, 0], [0, 0, 0], [0, 0, 0]])
        >>> opt.step()
        >>> round(u[0, 0].item(), 4), round(u[1, 1].item(), 4)   # one scale, set by the larger gradient
        (-0.05, -0.1)

        (Adam's first step moves every entry with a gradient by ``lr``: -0.1 for both.)
    """

    def __init__(self, params: Iterable[Any], lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        if not 0.0 <= lr:
            raise ValueError(f"lr must be >= 0, got {lr}")
        if not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0):
            raise ValueError(f"betas must each be in [0, 1), got {betas}")
        if not 0.0 <= eps:
            raise ValueError(f"eps must be >= 0, got {eps}")
        super().__init__(params, dict(lr=lr, betas=tuple(betas), eps=eps))

    @torch.no_grad()
    def step(self, closure: Any = None) -> Any:
        """One update of every parameter that has a gradient; ``closure`` as in ``torch.optim``."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            eps = group["eps"]
            for p in group["params"]:
                if p.grad is None or p.numel() == 0:
                    continue
                grad = p.grad
                if grad.is_sparse:
                    raise RuntimeError("AdamUniform does not support sparse gradients")
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["step"] += 1
                t = state["step"]
                m, v = state["exp_avg"], state["exp_avg_sq"]
                m.lerp_(grad, 1.0 - beta1)
                v.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
                scale = group["lr"] * math.sqrt(1.0 - beta2**t) / (1.0 - beta1**t)  # Adam's bias corrections
                v_max = v.max()  # the uniform part: one second moment for the whole tensor
                denominator = (v_max + eps * eps).sqrt() if eps <= 1e-6 else v_max.sqrt() + eps
                p.sub_(m / denominator, alpha=scale)
        return loss
