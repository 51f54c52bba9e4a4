"""``swap_parameter``: a parameter swapped for one of another shape in a live optimiser, with a
fresh or a carried state, the other parameters' state and the lr schedule untouched; and which
strategies ``rewrap_distributed`` rewraps (the real DDP rewrap: test_remesh_fit.py's slow DDP run)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from torch import nn

from torchir.geometry import AdamUniform
from torchir.training.param_swap import rewrap_distributed, swap_parameter


def _optimizer(kind: type = torch.optim.Adam):
    a, b = nn.Parameter(torch.ones(4)), nn.Parameter(torch.ones(2))
    optimizer = kind([{"params": [a], "lr": 0.1}, {"params": [b], "lr": 0.01}], lr=0.1)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=0.5)
    for _ in range(3):
        optimizer.zero_grad()
        (a.sum() + b.sum()).backward()
        optimizer.step()
        scheduler.step()
    return optimizer, scheduler, a, b


def _step(optimizer, *params) -> None:
    optimizer.zero_grad()
    sum(p.square().sum() for p in params).backward()
    optimizer.step()


@pytest.mark.parametrize("kind", [torch.optim.Adam, AdamUniform])
def test_a_fresh_parameter_restarts_and_the_rest_goes_on(kind):
    """The new tensor (another shape) takes the old one's place in its group with no state (its
    next step is an optimiser's first: step 1, the first Adam step of lr), the old one's state is
    dropped; the other parameter's state counts on, and the groups keep the scheduler's decay."""
    optimizer, scheduler, a, b = _optimizer(kind)
    new = nn.Parameter(torch.full((7,), 2.0))
    swap_parameter(optimizer, a, new)
    (held,) = optimizer.param_groups[0]["params"]
    assert held is new and a not in optimizer.state and new not in optimizer.state
    assert optimizer.param_groups[0]["lr"] == pytest.approx(0.1 * 0.5**3) and scheduler.optimizer is optimizer
    _step(optimizer, new, b)
    assert int(optimizer.state[new]["step"]) == 1 and int(optimizer.state[b]["step"]) == 4
    torch.testing.assert_close(new.detach(), torch.full((7,), 2.0 - 0.1 * 0.5**3))  # Adam's first step: lr


def test_a_carried_state_continues():
    """With ``state``, the new tensor steps on from it (the step count and moments given), and the
    optimiser's state_dict loads into a new optimiser over the new tensor (what a resume does)."""
    optimizer, _, a, b = _optimizer()
    new = nn.Parameter(torch.zeros(5))
    state = {"step": torch.tensor(3.0), "exp_avg": torch.ones(5), "exp_avg_sq": torch.ones(5)}
    swap_parameter(optimizer, a, new, state)
    _step(optimizer, new, b)
    assert int(optimizer.state[new]["step"]) == 4 and torch.allclose(optimizer.state[new]["exp_avg"], torch.full((5,), 0.9))
    fresh = torch.optim.Adam([{"params": [nn.Parameter(torch.zeros(5))], "lr": 0.1}, {"params": [nn.Parameter(torch.ones(2))], "lr": 0.01}])
    fresh.load_state_dict(optimizer.state_dict())
    assert int(fresh.state[fresh.param_groups[0]["params"][0]]["step"]) == 4


def test_bad_swaps_are_refused():
    optimizer, _, a, _ = _optimizer()
    with pytest.raises(ValueError, match="is not one of the optimiser.s"):
        swap_parameter(optimizer, nn.Parameter(torch.ones(4)), nn.Parameter(torch.ones(4)))
    with pytest.raises(ValueError, match="must be a leaf tensor that requires grad"):
        swap_parameter(optimizer, a, torch.ones(4))


def test_only_ddp_is_rewrapped_and_another_multi_process_strategy_is_refused():
    """One process: nothing to do; several under a strategy torchir cannot rewrap: an error
    naming it (its reducer would keep the replaced tensor: no gradient averaging of the new one)."""
    rewrap_distributed(SimpleNamespace(world_size=1, strategy=object()))
    with pytest.raises(RuntimeError, match="torchir does for DDP only; this run's strategy is object: use trainer.strategy: ddp"):
        rewrap_distributed(SimpleNamespace(world_size=2, strategy=object()))
