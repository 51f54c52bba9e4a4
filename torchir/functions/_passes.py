"""The primal and adjoint passes of a full render, frozen with ``dr.freeze`` where possible.

Tracing the integrator in Python costs about as much as running its kernels at small image
sizes, and torch waits for both (it needs the image, then the gradient, as data). A frozen
pass records its kernels once per configuration (sensor, spp, AD status of the bound values)
and replays them with new inputs: new seeds (passed opaque) and new parameter values. Binding
stays *outside* the frozen functions (binding inside crashed on replay), and gradients are
read after the frozen adjoint returns (read inside, a texture's gradient came back as zero).
A render that binds a tensor parameter with other than 3 channels (a 1-channel bitmap, a volume
grid) or a geometry parameter (vertex positions, transforms) runs unfrozen: replaying a frozen
pass after re-binding a 1-channel bitmap read stale memory (values of 1e18-1e26), and after
moving a mesh it traced rays against the recorded geometry (Dr.Jit 1.5, Mitsuba 3.9); RGB
textures and BSDF/emitter values replay exactly.
"""
from __future__ import annotations

import warnings
import weakref
from typing import Any

import drjit as dr
import mitsuba as mi

from .. import backend
from .._frozen import freeze
from ..scene import Scene
from ..welding import WeldedFaces, moving_meshes

def _primal(mi_scene: mi.Scene, sensor: int, seed: Any, spp: int) -> mi.TensorXf:
    sensor_obj = mi_scene.sensors()[sensor]
    image = mi_scene.integrator().render(mi_scene, sensor_obj, seed=seed, spp=spp, develop=True, evaluate=False)
    # As Mitsuba's own render op: re-seed the sensor's sampler so it does not keep the loop alive.
    sensor_obj.sampler().seed(0, 1)
    return image


def _adjoint(mi_scene: mi.Scene, sensor: int, grad_out: mi.TensorXf, seed: Any, spp: int, params: dict) -> None:
    sensor_obj = mi_scene.sensors()[sensor]
    mi_scene.integrator().render_backward(mi_scene, params, grad_out, sensor_obj, seed=seed, spp=spp)


def _freezable(integrator: mi.Integrator) -> bool:
    """Mitsuba's own path-replay integrators; not projective ones (Mitsuba refuses them inside
    frozen functions) nor custom Python integrators (they may keep state across calls)."""
    from mitsuba.python.ad.integrators.common import RBIntegrator

    return isinstance(integrator, RBIntegrator) and type(integrator).__module__.startswith("mitsuba.")


class RenderPasses:
    """Primal and adjoint render passes of one scene (frozen when enabled and possible)."""

    def __init__(self, scene: Scene) -> None:
        self.scene = weakref.proxy(scene)
        self.frozen = backend.frozen_renders() and _freezable(scene.integrator)
        limit = backend.frozen_recordings(scene.sensor_count)
        self._primal = freeze(_primal, limit=limit, warn_after=limit)
        self._adjoint = freeze(_adjoint, limit=limit, warn_after=limit)

    @property
    def recordings(self) -> int:
        """How many times the frozen passes were traced (stays constant once warm)."""
        return self._primal.n_recordings + self._adjoint.n_recordings

    def _replayable(self) -> bool:
        """Frozen passes are on, no geometry is bound, and every bound tensor is an RGB texture."""
        if not self.frozen:
            return False
        scene, params = self.scene, self.scene.params
        return all(
            not scene.info(name).discontinuous
            and (not dr.is_tensor_v(params[name]) or (len(params[name].shape) == 3 and params[name].shape[-1] == 3))
            for name in scene.bound_names
        )

    def primal(self, sensor: int, seed: int, spp: int) -> mi.TensorXf:
        if self._replayable():
            try:
                return self._primal(self.scene.mi_scene, sensor, dr.opaque(mi.UInt32, seed), spp)
            except Exception as error:  # noqa: BLE001 - fall back, loudly, rather than fail the run
                self._unfreeze(error)
        return _primal(self.scene.mi_scene, sensor, seed, spp)

    def adjoint(self, sensor: int, grad_out: mi.TensorXf, seed: int, spp: int, params: dict) -> None:
        if self._replayable():
            try:
                return self._adjoint(self.scene.mi_scene, sensor, grad_out, dr.opaque(mi.UInt32, seed), spp, params)
            except Exception as error:  # noqa: BLE001
                self._unfreeze(error)
                _clear_grads(params)  # a failed recording may have accumulated part of the gradient
        welded = _welded_boundary(self.scene, params)
        if welded:
            _split_adjoint(self.scene.mi_scene, sensor, grad_out, seed, spp, params, welded)
        else:
            _adjoint(self.scene.mi_scene, sensor, grad_out, seed, spp, params)

    def _unfreeze(self, error: Exception) -> None:
        self.frozen = False
        warnings.warn(f"frozen render pass failed ({error!r}); this scene now renders unfrozen", stacklevel=3)


def _welded_boundary(scene: Scene, params: dict) -> WeldedFaces | None:
    """Welded faces for a projective integrator's boundary terms on the moving meshes that repeat
    positions (uv seams, flat shading: :mod:`torchir.welding`), or None where nothing needs it."""
    from mitsuba.python.ad.integrators.common import PSIntegrator

    if not isinstance(scene.integrator, PSIntegrator):
        return None
    meshes = moving_meshes(scene.mi_scene, params)
    return WeldedFaces(scene.params, meshes, indirect=scene.integrator.sppi != 0) if meshes else None


def _split_adjoint(mi_scene: mi.Scene, sensor: int, grad_out: mi.TensorXf, seed: int, spp: int, params: dict,
                   welded: WeldedFaces) -> None:
    """A projective integrator's adjoint in two passes: the interior term on the user's faces,
    the boundary terms (primary and indirect silhouettes) on ``welded`` faces."""
    integrator = mi_scene.integrator()
    saved = integrator.sppc, integrator.sppp, integrator.sppi
    try:
        integrator.sppp = integrator.sppi = 0
        _adjoint(mi_scene, sensor, grad_out, seed, spp, params)
        integrator.sppc, integrator.sppp, integrator.sppi = 0, saved[1], saved[2]
        with welded:
            _adjoint(mi_scene, sensor, grad_out, seed, spp, params)
    finally:
        integrator.sppc, integrator.sppp, integrator.sppi = saved


def _clear_grads(params: dict) -> None:
    for value in params.values():
        dr.clear_grad(value)


_PASSES: weakref.WeakKeyDictionary[Scene, RenderPasses] = weakref.WeakKeyDictionary()


def passes(scene: Scene) -> RenderPasses:
    """The (cached) render passes of ``scene``."""
    if scene not in _PASSES:
        _PASSES[scene] = RenderPasses(scene)
    return _PASSES[scene]
