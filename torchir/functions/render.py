"""``render``: a full Mitsuba render as a torch autograd Function."""
from __future__ import annotations

from collections.abc import Mapping

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from ..scene import Scene
from . import _args
from ._bound_op import BoundRenderOp
from ._passes import passes
from ._wrap import torch_to_drjit
from ._sampler_op import RenderSampler, render_with_sampler_drjit

__all__ = ["render"]


class _RenderOp(BoundRenderOp):
    """Primal: ``integrator.render``; adjoint: ``integrator.render_backward`` (path replay),
    both through the scene's (frozen) :class:`~torchir.functions._passes.RenderPasses`."""

    def primal(self) -> mi.TensorXf:
        s: _args.RenderSettings = self.settings
        return passes(self.scene).primal(s.sensor, s.seed, s.spp)

    def adjoint(self, grad_out: mi.TensorXf) -> None:
        s: _args.RenderSettings = self.settings
        passes(self.scene).adjoint(s.sensor, grad_out, s.seed_grad, s.spp_grad, self.fresh)


@torch_to_drjit
def _render_drjit(scene: Scene, values: dict, grad_names: frozenset, settings: _args.RenderSettings):
    native = {name: scene.to_drjit(name, value) for name, value in values.items()}
    return dr.custom(_RenderOp, scene, native, grad_names, settings)


def _check_sampler(scene: Scene, sampler: object, grad_names: frozenset[str]) -> None:
    if not isinstance(sampler, RenderSampler):
        raise TypeError(
            f"render(sampler=...) takes a sampler with its own integrator, such as "
            f"torchir.samplers.ReSTIRSampler, got {type(sampler).__name__} (pixel samplers go through render_pixels)"
        )
    if sampler.scene is not scene:
        raise ValueError(f"the {type(sampler).__name__} was built for another Scene: build one per scene")
    sampler.check_gradients(grad_names)


def render(
    scene: Scene,
    params: Mapping[str, torch.Tensor] | None = None,
    spp: int = 4,
    seed: int = 0,
    sensor: int | mi.Sensor = 0,
    spp_grad: int | None = None,
    seed_grad: int | None = None,
    sampler: object | None = None,
) -> torch.Tensor:
    """Render ``scene`` with ``params`` bound, differentiably, as a torch tensor.

    The image is differentiable w.r.t. every tensor of ``params`` that requires grad (and only
    those: the others are bound as constants, so Dr.Jit does not track them). Parameters not in
    ``params`` keep their loaded value. The backward pass replays paths with ``seed_grad`` and
    ``spp_grad`` samples (Mitsuba's path replay) and always uses the parameter values of *this*
    render, even when other renders ran before it.

    Args:
        scene: a :class:`torchir.Scene`.
        params: ``{Mitsuba key: float32 tensor}`` in the shapes of :mod:`torchir.scene`
            (a texture is ``(H, W, C)``).
        spp: samples per pixel of the primal image, >= 1.
        seed: seed of the primal image; a fresh seed per step gives independent images.
        sensor: the sensor to render from: its index, or one of the scene's own ``mi.Sensor``
            objects (a sensor the scene was not loaded with is an error: load it with
            ``Scene.from_dict(d, sensors=sensors)``).
        spp_grad: samples per pixel of the gradient pass (default: ``spp``).
        seed_grad: seed of the gradient pass (default: a hash of ``seed``; must differ from it,
            so that the gradient is independent of the image noise).
        sampler: a sampler of this scene with its own stateful integrator
            (:class:`~torchir.functions._sampler_op.RenderSampler`), e.g. a
            :class:`torchir.samplers.ReSTIRSampler`: render direct illumination by ReSTIR (its
            reservoirs advance by one step) and back-propagate its interior-term gradient
            (Wang et al. 2023, "Amortizing Samples in Physics-Based Inverse Rendering using ReSTIR").
            ``None``: the scene's integrator.

    Returns:
        ``(C, H, W)`` float32 linear radiance (C = 3 for RGB films).

    Example:
        >>> scene = torchir.Scene.builtin("cbox", resolution=32)
        >>> red = scene.get("red.reflectance.value").requires_grad_()
        >>> img = render(scene, {"red.reflectance.value": red}, spp=4, seed=0)
        >>> img.mean().backward(); red.grad.shape
        torch.Size([3])
    """
    scene = _args.check_scene(scene)
    settings = _args.render_settings(scene, sensor, spp, seed, spp_grad, seed_grad)
    values, grad_names = _args.split_params(scene, params)
    if sampler is not None:
        _check_sampler(scene, sampler, grad_names)
        prepare = getattr(sampler, "prepare", None)  # e.g. ReSTIRSampler(preset="auto") probes the scene once
        if prepare is not None:
            prepare(values, grad_names, settings.sensor, settings.spp, settings.seed)
        image = render_with_sampler_drjit(scene, values, grad_names, settings, sampler)  # (H, W, C)
        return image.permute(2, 0, 1)
    _check_projective_silhouettes(scene, grad_names, settings.sensor)
    image = _render_drjit(scene, values, grad_names, settings)  # (H, W, C)
    return image.permute(2, 0, 1)


def _check_projective_silhouettes(scene: Scene, grad_names: frozenset[str], sensor: int) -> None:
    """Refuse what Mitsuba's projective integrators differentiate wrong: the primary silhouettes
    of a moving mesh the sensor sees that is flat-shaded or shows the back of a one-sided material
    past an open border (:func:`~torchir.integrators._mesh_edges.mitsuba_silhouettes_wrong`);
    warn, once per scene and mesh, where it is smooth-shaded (Mitsuba misses its shading-horizon
    band: :mod:`~torchir.integrators._shading_bands`). Checked once per mesh and sensor: a fit
    moves the surface little."""
    from mitsuba.python.ad.integrators.common import PSIntegrator

    names = [n[: -len(".vertex_positions")] for n in grad_names if n.endswith(".vertex_positions")]
    if not names or not isinstance(scene.integrator, PSIntegrator):
        return
    for shape in scene.mi_scene.shapes():
        if isinstance(shape, mi.Mesh) and shape.id() in names:
            refused, banded = scene.verdict(("projective silhouettes", shape.id(), sensor),
                                            lambda: _silhouette_verdict(scene, shape, sensor))
            if banded:
                scene.warn_once(
                    f"band-{shape.id()}",
                    f"{shape.id()!r} is smooth-shaded: {type(scene.integrator).__name__} misses the shading-horizon band "
                    f"inside its silhouettes, whose inner edge moves as the vertex normals turn, so a vertex beside a "
                    f"silhouette gets a wrong derivative (translations are right; docs/shape-gradients.md, \"Smooth-shaded "
                    f"meshes\"). {_band_advice(scene, shape, sensor)}",
                )
            if refused:
                reason, remedy = refused
                raise ValueError(
                    f"{shape.id()!r}: {reason}; {type(scene.integrator).__name__}'s primary silhouette term would be "
                    f"wrong there. {_restir_advice(scene)}{remedy}."
                )


def _silhouette_verdict(scene: Scene, mesh: mi.Mesh, sensor: int) -> tuple[tuple[str, str] | None, bool]:
    """``(why and what fixes it, or None; whether the shading-horizon band warning applies)``."""
    refused = _projective_silhouette_problem(scene, mesh, sensor)
    return refused, not refused and _smooth_and_seen(scene, mesh, sensor)


def _restir_advice(scene: Scene) -> str:
    """"Render through ReSTIR, or" where ReSTIR takes the scene, else why it cannot."""
    from ..integrators.restir_di import check_scene

    try:
        check_scene(scene.mi_scene)
    except ValueError as refusal:
        return f"torchir's ReSTIR sampler, which samples these silhouettes itself, cannot take this scene ({refusal}): "
    return ("Render through ReSTIR (render(..., sampler=torchir.samplers.ReSTIRSampler(scene)): it samples these "
            "silhouettes itself), or ")


def _band_advice(scene: Scene, mesh: mi.Mesh, sensor: int) -> str:
    """What removes the shading-horizon band's error for this scene: ReSTIR's B.2 preset where
    ReSTIR and its band term take the scene, else why not and what is left to do."""
    from ..integrators._silhouettes import supported
    from ..integrators.restir_di import check_scene

    try:
        check_scene(scene.mi_scene)
    except ValueError as refusal:
        reason = str(refusal)
    else:
        if supported(scene.mi_scene, scene.mi_scene.sensors()[sensor], [mesh]):
            return "render(..., sampler=torchir.samplers.ReSTIRSampler(scene, preset='b2')) adds that term."
        reason = "its band term needs a pinhole camera with a box filter and no crop window, seeing the mesh whole"
    if mesh.id() in scene.spread_steps:  # the run does what the advice would say
        spread = ("this mesh's Large Steps parametrization spreads each vertex's step over its neighbours, as in "
                  "Mitsuba's shape tutorial, which converges with it")
    else:
        spread = ("Mitsuba's shape tutorial converges with it, because its Large Steps parametrization (torchir: "
                  "parametrization: {type: large_steps}) spreads each vertex's step over its neighbours")
    return (f"torchir's ReSTIR sampler, which adds that term, cannot take this scene ({reason}). The error is "
            f"confined to the vertices beside silhouettes; {spread}. "
            f"warnings.filterwarnings('ignore', message='.*shading-horizon band') silences this warning.")


def _smooth_and_seen(scene: Scene, mesh: mi.Mesh, sensor: int) -> bool:
    """Whether ``mesh`` has interpolated vertex normals and a vertex in the view of ``sensor``."""
    from ..integrators._shading_bands import smooth_shaded

    if not smooth_shaded(mesh):
        return False
    return _in_view(scene.mi_scene.sensors()[sensor], mesh)


def _in_view(sensor_obj: mi.Sensor, mesh: mi.Mesh) -> bool:
    it = dr.zeros(mi.Interaction3f, mesh.vertex_count())
    it.p = dr.unravel(mi.Point3f, dr.detach(mesh.vertex_positions_buffer()))
    ds, _ = sensor_obj.sample_direction(it, mi.Point2f(0.5))
    return bool(dr.any(ds.pdf > 0))


def _projective_silhouette_problem(scene: Scene, mesh: mi.Mesh, sensor: int) -> tuple[str, str] | None:
    """``(why, what fixes it)`` where Mitsuba's primary silhouettes of ``mesh`` seen by ``sensor``
    are wrong, else None."""
    from ..integrators._mesh_edges import back_seen_past_border, edges_of, mitsuba_silhouettes_wrong

    if not mitsuba_silhouettes_wrong(mesh):
        return None
    sensor_obj = scene.mi_scene.sensors()[sensor]
    if not _in_view(sensor_obj, mesh):
        return None  # outside the view: only its shadow is seen
    if edges_of(mesh).crease.any():
        return ("the sensor sees this flat-shaded or hard-edged mesh, whose shading jumps at its creases, which Mitsuba's "
                "estimator does not sample (measured on a cube's pixels: -7.8 against -4.6 by finite differences)",
                "give the mesh smooth vertex normals (one normal per position, as a smooth-shaded export writes them)")
    bsdf = mesh.bsdf()
    one_sided = bsdf is None or not bsdf.flags() & int(mi.BSDFFlags.BackSide)
    viewpoint = np.array(sensor_obj.world_transform() @ mi.ScalarPoint3f(0.0))
    if one_sided and back_seen_past_border(mesh, viewpoint, scene.mi_scene):
        return ("the sensor sees the back of its one-sided material past an open border, which Mitsuba shades as "
                "the front", "give the mesh a two-sided material ('twosided' BSDF) or close its surface")
    return None
