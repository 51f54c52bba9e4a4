"""The Dr.Jit op behind ``render(..., sampler=ReSTIRSampler)`` (paper 004).

Same binding discipline as every torchir render (:class:`BoundRenderOp`: the backward
re-binds this render's own values when another render ran in between). The primal advances
the sampler's reservoirs and keeps this step's paths on the op itself, so each backward
differentiates exactly the paths of its own forward, even when several renders are pending.
ReSTIR passes are not frozen (the integrator keeps state across calls).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..scene import _GEOMETRY_KEYS
from ._bound_op import BoundRenderOp


class ReSTIRRenderOp(BoundRenderOp):
    """Primal: one ReSTIR step (image + new reservoirs); adjoint: the interior-term gradient."""

    def eval(self, scene, values, grad_names, settings, sampler):
        self.sampler = sampler
        return super().eval(scene, values, grad_names, settings)

    def primal(self) -> mi.TensorXf:
        s, r = self.settings, self.sampler
        image, self.cache = r.integrator.step(self.scene.mi_scene, s.sensor, r.render_seed(s.seed), s.spp)
        return image

    def adjoint(self, grad_out: mi.TensorXf) -> None:
        s, r = self.settings, self.sampler
        geometry = any(name.rsplit(".", 1)[-1] in _GEOMETRY_KEYS for name in self.grad_names)
        if geometry:
            self.scene.warn_once(
                "restir-geometry",
                "ReSTIR with shape parameters (stage v2): interior term with reuse (ray-following shading "
                "points) + boundary terms of direct_projective without reuse; the temporal support test "
                "uses the current geometry (small bias, spec D7)",
            )
        r.integrator.backward(
            self.scene.mi_scene, self.cache, grad_out, r.render_seed(s.seed_grad), s.spp_grad,
            geometry=geometry, params=self.fresh,
        )
        self.cache = None  # free the paths


@dr.wrap(source="torch", target="drjit")
def render_restir_drjit(scene, values: dict, grad_names: frozenset, settings, sampler):
    native = {name: scene.to_drjit(name, value) for name, value in values.items()}
    return dr.custom(ReSTIRRenderOp, scene, native, grad_names, settings, sampler)
