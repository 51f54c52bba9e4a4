"""The Dr.Jit custom op behind torchir's render Functions.

Mitsuba's own render op replays the scene *as it is at backward time*: when another render
(other values) ran between a render and its backward, that backward differentiates the wrong
scene, and when one tensor is rendered twice before one backward, the second binding's AD
edges are consumed by the first traversal. :class:`BoundRenderOp` therefore owns the values
it rendered with and re-binds them, as fresh grad-enabled variables, before its adjoint pass
whenever the scene no longer holds its own live binding. In the common case (render, then
its backward, nothing in between) the binding made by the forward pass is reused, so a step
costs one ``params.update()`` like a native Mitsuba loop.
"""
from __future__ import annotations

from typing import Any

import drjit as dr

from ..backend import gc_paused


class BoundRenderOp(dr.CustomOp):
    """Base op: subclasses implement :meth:`primal` and :meth:`adjoint`.

    ``eval(scene, values, grad_names, settings)`` binds ``values`` (Mitsuba-typed Dr.Jit
    values, one per parameter name), runs :meth:`primal` and returns its Dr.Jit result;
    ``backward`` re-binds if needed, runs :meth:`adjoint` with the output gradient and hands
    the parameter gradients to Dr.Jit's AD graph (and so, through ``dr.wrap``, to torch).
    """

    def eval(self, scene, values: dict[str, Any], grad_names: frozenset[str], settings: Any):
        self.scene, self.values, self.grad_names, self.settings = scene, values, grad_names, settings
        with gc_paused():  # a scene freed by the collector mid-trace aborts the process
            self.fresh = scene.bind(values, grad_names, owner=self)
            with dr.suspend_grad():
                return self.primal()

    def backward(self) -> None:
        if not self.grad_names:
            return
        with gc_paused():
            self._backward()

    def _backward(self) -> None:
        if not self.scene.owns_live_binding(self):
            self.fresh = self.scene.bind(self.values, self.grad_names, owner=self)
        self.scene.release(self)  # the traversal below consumes the AD edges
        self.adjoint(self.grad_out())
        grads = {
            name: dr.grad(self.fresh[name]) if name in self.grad_names else _zeros_like(value)
            for name, value in self.values.items()
        }
        self.scene.drop_live_grads()  # nothing grad-enabled stays bound (see Scene.drop_live_grads)
        self.set_grad_in("values", grads)

    def forward(self) -> None:
        raise NotImplementedError("forward-mode derivatives through torchir's render are not supported")

    # ------------------------------------------------------------------ for subclasses
    def primal(self) -> Any:
        raise NotImplementedError

    def adjoint(self, grad_out: Any) -> None:
        raise NotImplementedError

    def name(self) -> str:
        return type(self).__name__


def _zeros_like(value: Any) -> Any:
    return dr.zeros(type(value), dr.shape(value) if dr.is_tensor_v(value) else dr.width(value))
