"""Small modules the training tests refer to by class path."""
from __future__ import annotations

import torch
from torch import nn


class NaNAfterLoss(nn.Module):
    """L2 loss that turns NaN from its ``steps``-th call on (to test the NaN guard)."""

    def __init__(self, steps: int = 3) -> None:
        super().__init__()
        self.steps, self.calls = steps, 0

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        loss = (rendered - target).square().mean()
        return loss * float("nan") if self.calls > self.steps else loss
