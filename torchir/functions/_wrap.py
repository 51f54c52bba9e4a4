"""``torch_to_drjit``: ``dr.wrap(source="torch", target="drjit")`` that refuses a second backward.

Dr.Jit's wrapper back-propagates with ``ADFlag.Default``, which deletes the AD edges it
traversed. A second backward through the same output (``retain_graph=True``:
``torch.autograd.grad`` per output, a Jacobian row by row, two losses on one image) then finds
no edges and silently returned the *first* call's input gradients whatever its own output
gradient. This wrapper raises there instead, with what to do.

Keeping the edges instead (``ClearInterior | ClearInput``, freed with the image) gave right
second gradients, but in a full test run (``--randomly-seed=4258395770``) a shared scene's mesh
buffer then changed under a later test (memory released while in use: the graph of a custom op
freed late); with Dr.Jit's own flags the same order passed. So the edges go as in ``dr.wrap``.
The forward, the PyTree flattening and the conversions are Dr.Jit's own.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import drjit as dr
from drjit import interop
from torch.autograd import function

F = TypeVar("F", bound=Callable)

_FUNCTION = None
SECOND_BACKWARD = (
    "this torchir render was already back-propagated: Dr.Jit frees its derivative graph at the first "
    "backward, so a second one (retain_graph=True, torch.autograd.grad per output) would return the "
    "first one's gradient. Render again for each backward, or sum the losses and call backward once."
)


def _function() -> type:
    global _FUNCTION
    if _FUNCTION is None:
        class TorchToDrJit(interop.create_torch_wrapper()):
            @staticmethod
            @function.once_differentiable
            def backward(ctx, *grad_outputs):
                if getattr(ctx, "back_propagated", False):
                    raise RuntimeError(SECOND_BACKWARD)
                ctx.back_propagated = True
                interop.new_drjit_scope()
                dr.set_grad(ctx.output, interop.to_drjit(grad_outputs, "torch"))
                grads = dr.backward_to(ctx.inputs)
                grads = [grad if dr.grad_enabled(x) else None for grad, x in zip(grads, ctx.inputs)]
                grads = interop.from_drjit(grads, "torch")[0]
                interop.new_drjit_scope()
                return None, None, *grads

        _FUNCTION = TorchToDrJit
    return _FUNCTION


def torch_to_drjit(func: F) -> F:
    """Decorate a Dr.Jit function to take and return torch tensors, differentiably, with a
    backward that refuses to run twice (see the module docstring)."""

    @functools.wraps(func)
    def wrapped(*args, **kwargs):
        outputs = _function().apply(func, *interop.flatten((args, kwargs)))
        result = interop.unflatten(interop.torch_desc_o, *outputs)
        interop.torch_desc_o = None
        return result

    return wrapped
