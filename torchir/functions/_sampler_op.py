"""The Dr.Jit op behind ``render(..., sampler=...)``: a render by a sampler's stateful integrator.

:class:`RenderSampler` is all :func:`torchir.functions.render` knows of such a sampler (e.g.
:class:`torchir.samplers.ReSTIRSampler`, Wang et al. 2023): the render boundary does not import the
sampler classes. Same binding discipline as every torchir render (:class:`BoundRenderOp`: the
backward re-binds this render's own values when another render ran in between). The primal
advances the integrator's state and keeps this step's paths on the op itself, so each backward
differentiates exactly the paths of its own forward, even when several renders are pending.
These passes are not frozen (the integrator keeps state across calls).
"""
from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Protocol, runtime_checkable

import drjit as dr
import mitsuba as mi

from ..scene import is_geometry_key
from ._bound_op import BoundRenderOp
from ._wrap import torch_to_drjit


@runtime_checkable
class RenderSampler(Protocol):
    """A sampler that renders with its own stateful integrator.

    Attributes:
        scene: the :class:`torchir.Scene` it was built for.
        integrator: ``step(mi_scene, sensor, seed, spp) -> (image (H, W, C) TensorXf, cache)``
            advances the state by one render; ``backward(mi_scene, cache, grad_image, seed, spp,
            geometry=bool, params=dict)`` back-propagates that render's paths. An integrator
            whose attribute ``zero_remainder`` is True also takes ``step(..., zero_remainder=
            bool)``: whether a differentiated value has an exact 0 (see
            :meth:`SamplerRenderOp.differentiates_a_zero`).
    """

    scene: Any
    integrator: Any

    def render_seed(self, seed: int) -> int:
        """The integrator's seed for a render with ``seed``."""

    def check_gradients(self, grad_names: Iterable[str]) -> None:
        """Raise for parameters whose gradient it cannot give; warn where it approximates.

        A sampler may also define ``prepare(values, grad_names, sensor, spp, seed)``, called
        before each render with the render's values and settings (e.g. to choose its settings
        from a probe of the scene at the first)."""


class SamplerRenderOp(BoundRenderOp):
    """Primal: one step of the sampler's integrator; adjoint: its gradient of that step."""

    def eval(self, scene, values, grad_names, settings, sampler):
        self.sampler = sampler
        return super().eval(scene, values, grad_names, settings)

    def primal(self) -> mi.TensorXf:
        s, r = self.settings, self.sampler
        options = {"zero_remainder": self.differentiates_a_zero()} if getattr(r.integrator, "zero_remainder", False) else {}
        image, self.cache = r.integrator.step(self.scene.mi_scene, s.sensor, r.render_seed(s.seed), s.spp, **options)
        return image

    def differentiates_a_zero(self) -> bool:
        """Whether a differentiated material or emitter value has an entry exactly 0 (a black
        texel, a light switched off): only there does a resampled estimator's gradient need
        the samples its target ``p̂ = lum(f)`` gives no weight (``f = 0``, ``df != 0``)."""
        for name in self.grad_names:
            if is_geometry_key(name):
                continue
            if bool(dr.any(dr.ravel(self.values[name]) == 0)):  # a tensor's ravel is its array
                return True
        return False

    def adjoint(self, grad_out: mi.TensorXf) -> None:
        s, r = self.settings, self.sampler
        geometry = any(is_geometry_key(name) for name in self.grad_names)
        r.integrator.backward(
            self.scene.mi_scene, self.cache, grad_out, r.render_seed(s.seed_grad), s.spp_grad,
            geometry=geometry, params=self.fresh,
        )
        self.cache = None  # free the paths


@torch_to_drjit
def render_with_sampler_drjit(scene, values: dict, grad_names: frozenset, settings, sampler):
    native = {name: scene.to_drjit(name, value) for name, value in values.items()}
    return dr.custom(SamplerRenderOp, scene, native, grad_names, settings, sampler)
