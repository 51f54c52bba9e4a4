"""``torch_to_drjit``: ``dr.wrap(source="torch", target="drjit")`` whose backward can run again.

Dr.Jit's wrapper back-propagates with ``ADFlag.Default``, which deletes the AD edges it
traversed. A second backward through the same output (``retain_graph=True``:
``torch.autograd.grad`` per output, a Jacobian row by row, two losses on one image) then
finds no edges and silently returns the *first* call's input gradients whatever its own
output gradient. This wrapper keeps the edges (they are freed with the output, when torch
drops the graph) and clears the input gradients before each backward, so every backward is
the gradient of its own ``grad_outputs``. The forward, the PyTree flattening and the
conversions are Dr.Jit's own.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import drjit as dr
from drjit import interop
from torch.autograd import function

F = TypeVar("F", bound=Callable)

_RETAIN_EDGES = dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput
_FUNCTION = None


def _function() -> type:
    global _FUNCTION
    if _FUNCTION is None:
        class TorchToDrJit(interop.create_torch_wrapper()):
            @staticmethod
            @function.once_differentiable
            def backward(ctx, *grad_outputs):
                interop.new_drjit_scope()
                dr.clear_grad(ctx.inputs)  # an earlier backward left its gradients on the leaves
                dr.set_grad(ctx.output, interop.to_drjit(grad_outputs, "torch"))
                grads = dr.backward_to(ctx.inputs, flags=_RETAIN_EDGES)
                grads = [grad if dr.grad_enabled(x) else None for grad, x in zip(grads, ctx.inputs)]
                grads = interop.from_drjit(grads, "torch")[0]
                dr.clear_grad(ctx.inputs)
                interop.new_drjit_scope()
                return None, None, *grads

        _FUNCTION = TorchToDrJit
    return _FUNCTION


def torch_to_drjit(func: F) -> F:
    """Decorate a Dr.Jit function to take and return torch tensors, differentiably, with a
    backward that may run more than once (see the module docstring)."""

    @functools.wraps(func)
    def wrapped(*args, **kwargs):
        outputs = _function().apply(func, *interop.flatten((args, kwargs)))
        result = interop.unflatten(interop.torch_desc_o, *outputs)
        interop.torch_desc_o = None
        return result

    return wrapped
