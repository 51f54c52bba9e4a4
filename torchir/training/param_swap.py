"""Replace one parameter of a torch optimiser by a new tensor, mid-run: a resized volume grid (a
coarse-to-fine schedule) or a remeshed surface, whose ``nn.Parameter`` has a new shape.

The optimiser keeps its parameter groups (learning rates with the scheduler's decay so far, names)
and every other parameter's
state; the new parameter takes the old one's place in its group, with the state given (e.g. the
old moments resampled to the new shape) or a fresh one (none: the optimiser initialises it at its
next step, as Mitsuba's shape tutorial restarts Adam after a remesh).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any, Optional

import torch

__all__ = ["swap_parameter", "map_state", "rewrap_distributed"]


def swap_parameter(optimizer: torch.optim.Optimizer, old: torch.Tensor, new: torch.Tensor,
                   state: Optional[dict[str, Any]] = None) -> None:
    """Put ``new`` in ``old``'s place among ``optimizer``'s parameters, in place.

    Args:
        optimizer: any ``torch.optim.Optimizer`` (Adam, SGD, :class:`torchir.geometry.AdamUniform`).
        old: a parameter of ``optimizer`` (by identity).
        new: its replacement (any shape).
        state: ``new``'s optimiser state (e.g. :func:`map_state` of ``old``'s), or ``None`` for a
            fresh state. ``old``'s state is dropped either way.

    Example:
        >>> a = torch.nn.Parameter(torch.zeros(2)); opt = torch.optim.Adam([a], lr=0.1)
        >>> a.grad = torch.ones(2); opt.step()
        >>> b = torch.nn.Parameter(torch.zeros(3))
        >>> swap_parameter(opt, a, b, map_state(opt.state[a], a, lambda t: t.mean().expand(3).clone()))
        >>> opt.param_groups[0]["params"][0] is b, tuple(opt.state[b]["exp_avg"].shape)
        (True, (3,))
    """
    if not (new.is_leaf and new.requires_grad):
        raise ValueError("swap_parameter: the new parameter must be a leaf tensor that requires grad (an nn.Parameter)")
    places = [(g, i) for g in optimizer.param_groups for i, p in enumerate(g["params"]) if p is old]
    if not places:
        raise ValueError(f"swap_parameter: the parameter to replace (shape {tuple(old.shape)}) is not one of the optimiser's")
    if any(p is new for g in optimizer.param_groups for p in g["params"]):
        raise ValueError("swap_parameter: the new parameter is already one of the optimiser's")
    for group, index in places:
        group["params"][index] = new
    optimizer.state.pop(old, None)
    if state:
        optimizer.state[new] = dict(state)


def map_state(state: dict[str, Any], old: torch.Tensor, fn: Callable[[torch.Tensor], torch.Tensor]) -> dict[str, Any]:
    """A new state dict: ``state`` (one parameter's optimiser state) with ``fn`` applied to each
    tensor of ``old``'s shape (Adam's ``exp_avg``, ``exp_avg_sq``); step counts and other entries are
    kept, as copies (Adam increments its step tensor in place: a shared one would count twice)."""
    out = {}
    for k, v in state.items():
        if k != "step" and isinstance(v, torch.Tensor) and v.shape == old.shape:
            out[k] = fn(v)
        else:
            out[k] = v.clone() if isinstance(v, torch.Tensor) else v
    return out


def rewrap_distributed(trainer: Any) -> None:
    """Under DDP, wrap the LightningModule in a new ``DistributedDataParallel`` so that its
    gradient reducer covers the parameters as they are now (the old wrapper's buckets hold the
    replaced tensors: without this, DDP silently averages nothing into the new one). A collective:
    every process calls it at the same step. The wrapper's constructor broadcasts rank 0's
    parameters, so the processes start the new ones equal. Without DDP (one process) it does nothing; another multi-process strategy is refused."""
    from lightning.pytorch.strategies import DDPStrategy

    strategy = getattr(trainer, "strategy", None)
    if trainer.world_size <= 1:
        return
    if not isinstance(strategy, DDPStrategy):
        raise RuntimeError(f"a parameter replaced mid-run needs its gradients reduced anew, which torchir does for DDP "
                           f"only; this run's strategy is {type(strategy).__name__}: use trainer.strategy: ddp")
    strategy.model = strategy.lightning_module
    strategy.configure_ddp()
