"""``render_pixels``: radiance of a chosen set of pixels, as a torch autograd Function.

Camera rays are generated for the listed pixels only and traced with the integrator's per-ray
``sample()`` (the path-replay interface of ``prb``, ``prb_basic``, ``prbvolpath``), exactly as
``ADIntegrator.render`` does for a whole image, but without an image block. With a box
reconstruction filter the result is an unbiased estimate of the same pixel values that
:func:`torchir.functions.render` estimates.
"""
from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import torch

from .. import backend
from .._frozen import freeze
from ..scene import Scene
from . import _args
from ._bound_op import BoundRenderOp
from ._passes import _clear_grads, passes
from ._wrap import torch_to_drjit

__all__ = ["render_pixels"]


@dataclass(frozen=True)
class _PixelSettings(_args.RenderSettings):
    index: mi.UInt32  # (N,) flat pixel indices over ``sensors``; not differentiable
    sensors: tuple[int, ...]  # the listed sensors (``(sensor,)`` for one)


def _film_rays(sensors: Sequence[mi.Sensor], x: mi.Float, y: mi.Float, width, height, sampler: mi.Sampler,
               view: mi.UInt32 | None = None):
    """Camera rays through uniformly jittered points of pixel ``(x, y)`` of a ``width x height``
    grid over the film's crop window (the film's own pixels, or a coarser grid), each lane's
    from ``sensors[view]`` (``sensors[0]`` without ``view``). Every lane draws the same random
    numbers whatever its sensor, so a lane's ray and path do not depend on which other views
    share the wavefront. Returns ``(ray, ray weight)``."""
    first = sensors[0]
    pos = mi.Vector2f(x, y) + sampler.next_2d()
    pos_01 = mi.Vector2f(pos.x / width, pos.y / height)
    aperture = sampler.next_2d() if any(s.needs_aperture_sample() for s in sensors) else mi.Vector2f(0.0)
    u_time = sampler.next_1d() if any(s.shutter_open_time() > 0 for s in sensors) else mi.Float(0.0)

    def time(sensor: mi.Sensor) -> mi.Float:  # within each sensor's own shutter interval
        return sensor.shutter_open() + u_time * sensor.shutter_open_time()

    with dr.resume_grad():
        ray, weight = first.sample_ray_differential(time=time(first), sample1=0.0, sample2=pos_01, sample3=aperture)
        for k, sensor in enumerate(sensors[1:], start=1):
            ray_k, weight_k = sensor.sample_ray_differential(time=time(sensor), sample1=0.0, sample2=pos_01, sample3=aperture)
            mine = view == k
            ray, weight = dr.select(mine, ray_k, ray), dr.select(mine, weight_k, weight)
        return ray, weight


def _pixel_rays(sensors: Sequence[mi.Sensor], index: mi.UInt32, sampler: mi.Sampler):
    """Camera rays through the given film pixels: ``index`` is ``k * W * H + y * W + x`` for
    pixel ``(x, y)`` of ``sensors[k]`` (one wavefront over every view; sensors of one size)."""
    width, height = sensors[0].film().crop_size()
    view = index // (width * height) if len(sensors) > 1 else None
    pixel = index if view is None else index - view * (width * height)
    y = pixel // width
    return _film_rays(sensors, mi.Float(pixel - y * width), mi.Float(y), float(width), float(height), sampler, view)


def _per_lane(array_type: type, per_pixel, spp: int):
    """Repeat each entry ``spp`` times: lanes ``[n*spp, (n+1)*spp)`` belong to listed pixel ``n``."""
    lane = dr.arange(mi.UInt32, dr.width(per_pixel) * spp)
    return dr.gather(array_type, per_pixel, lane // dr.opaque(mi.UInt32, spp))


def _seeded_sampler(seed: int, lanes: int) -> mi.Sampler:
    sampler = mi.load_dict({"type": "independent", "sample_count": 1})
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed, lanes)
    return sampler


def _sensors(mi_scene: mi.Scene, sensors: tuple[int, ...]) -> list[mi.Sensor]:
    every = mi_scene.sensors()
    return [every[k] for k in sensors]


def _primal_pass(mi_scene: mi.Scene, sensors: tuple[int, ...], index: mi.UInt32, seed: Any, spp: int, count: int) -> mi.Color3f:
    """Mean radiance of ``spp`` paths through each of the ``count`` listed pixels (of ``sensors``:
    see :func:`_pixel_rays`)."""
    lanes = _per_lane(mi.UInt32, index, spp)
    sampler = _seeded_sampler(seed, count * spp)
    ray, weight = _pixel_rays(_sensors(mi_scene, sensors), lanes, sampler)
    L, _, _, _ = mi_scene.integrator().sample(
        mode=dr.ADMode.Primal, scene=mi_scene, sampler=sampler, ray=ray,
        depth=mi.UInt32(0), δL=None, δaovs=None, state_in=None, active=mi.Bool(True),
    )
    return dr.block_sum(mi.Color3f(L * weight), spp) / spp


def _adjoint_pass(mi_scene: mi.Scene, sensors: tuple[int, ...], index: mi.UInt32, δ_pixel: mi.Color3f, seed: Any, spp: int, count: int, params: dict) -> None:
    """Primal + path-replay Backward pass of ``spp`` fresh paths per listed pixel, adjoint ``δ_pixel``."""
    lanes = _per_lane(mi.UInt32, index, spp)
    sampler = _seeded_sampler(seed, count * spp)
    with dr.suspend_grad():
        ray, weight = _pixel_rays(_sensors(mi_scene, sensors), lanes, sampler)
        δL = _per_lane(mi.Color3f, δ_pixel, spp) * weight / spp
        integrator = mi_scene.integrator()
        L, _, _, state = integrator.sample(
            mode=dr.ADMode.Primal, scene=mi_scene, sampler=sampler.clone(), ray=ray,
            depth=mi.UInt32(0), δL=None, δaovs=None, state_in=None, active=mi.Bool(True),
        )
        integrator.sample(
            mode=dr.ADMode.Backward, scene=mi_scene, sampler=sampler, ray=ray,
            depth=mi.UInt32(0), δL=δL, δaovs=None, state_in=state, active=mi.Bool(True),
        )


def _one_path_pass(mi_scene: mi.Scene, sensor: int, x: mi.Float, y: mi.Float, w: mi.Float, h: mi.Float, seed: Any, count: int) -> mi.Color3f:
    """Radiance (times the ray weight) of one path per lane through pixel ``(x, y)`` of a
    ``w x h`` grid (Stage-1 probes of :mod:`torchir.functions.probe`)."""
    sampler = _seeded_sampler(seed, count)
    with dr.suspend_grad():
        ray, weight = _film_rays([mi_scene.sensors()[sensor]], x, y, w, h, sampler)
        L, _, _, _ = mi_scene.integrator().sample(
            mode=dr.ADMode.Primal, scene=mi_scene, sampler=sampler, ray=ray,
            depth=mi.UInt32(0), δL=None, δaovs=None, state_in=None, active=mi.Bool(True),
        )
        return mi.Color3f(L * weight)


class _PixelPasses:
    """The pixel passes of one scene (subset primal and replay, Stage-1 probes), frozen
    (``dr.freeze``) for lane counts seen before.

    Tracing the integrator in Python dominates a subset render of a few hundred pixels, far
    above its kernels' time (measured: docs/pixel-sampling.md, "Measurements behind the
    design"). A frozen pass bakes the lane count into its recording (a replay with another count
    silently keeps the old one), so the count is a Python argument, which keys the recordings,
    and a count is frozen only from its second use: a constant per-step budget replays, while
    the varying per-view counts of a multi-view minibatch stay unfrozen instead of re-recording
    every step.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = weakref.proxy(scene)
        self.full_passes = passes(scene)  # whose rules say which bindings replay correctly
        self.seen: dict[tuple, int] = {}
        self.limit = limit = backend.frozen_recordings(scene.sensor_count)
        self._primal = freeze(_primal_pass, limit=limit, warn_after=limit)
        self._adjoint = freeze(_adjoint_pass, limit=limit, warn_after=limit)
        self._one_path = freeze(_one_path_pass, limit=limit, warn_after=limit)

    def _frozen(self, key: tuple) -> bool:
        if key not in self.seen and len(self.seen) >= 4 * self.limit:  # forget counts used once
            self.seen = {k: v for k, v in self.seen.items() if v > 1}
        uses = self.seen[key] = self.seen.get(key, 0) + 1
        return uses > 1 and self.full_passes._replayable()

    def primal(self, sensors: tuple[int, ...], index: mi.UInt32, seed: int, spp: int) -> mi.Color3f:
        count = dr.width(index)
        if self._frozen(("primal", sensors, count, spp)):
            try:
                return self._primal(self.scene.mi_scene, sensors, index, dr.opaque(mi.UInt32, seed), spp, count)
            except Exception as error:  # noqa: BLE001 - as RenderPasses: fall back, loudly
                self.full_passes._unfreeze(error)
        return _primal_pass(self.scene.mi_scene, sensors, index, seed, spp, count)

    def one_path(self, sensor: int, lanes: tuple[mi.Float, mi.Float, mi.Float, mi.Float], seed: int) -> mi.Color3f:
        count = dr.width(lanes[0])
        if self._frozen(("one_path", sensor, count)):
            try:
                return self._one_path(self.scene.mi_scene, sensor, *lanes, dr.opaque(mi.UInt32, seed), count)
            except Exception as error:  # noqa: BLE001
                self.full_passes._unfreeze(error)
        return _one_path_pass(self.scene.mi_scene, sensor, *lanes, seed, count)

    def adjoint(self, sensors: tuple[int, ...], index: mi.UInt32, δ_pixel: mi.Color3f, seed: int, spp: int, params: dict) -> None:
        count = dr.width(index)
        if self._frozen(("adjoint", sensors, count, spp)):
            try:
                self._adjoint(self.scene.mi_scene, sensors, index, δ_pixel, dr.opaque(mi.UInt32, seed), spp, count, params)
            except Exception as error:  # noqa: BLE001
                self.full_passes._unfreeze(error)
                _clear_grads(params)  # a failed recording may have accumulated part of the gradient
                _adjoint_pass(self.scene.mi_scene, sensors, index, δ_pixel, seed, spp, count, params)
        else:
            _adjoint_pass(self.scene.mi_scene, sensors, index, δ_pixel, seed, spp, count, params)
        dr.eval()


_PIXEL_PASSES: weakref.WeakKeyDictionary[Scene, _PixelPasses] = weakref.WeakKeyDictionary()


def _pixel_passes(scene: Scene) -> _PixelPasses:
    if scene not in _PIXEL_PASSES:
        _PIXEL_PASSES[scene] = _PixelPasses(scene)
    return _PIXEL_PASSES[scene]


class _PixelRenderOp(BoundRenderOp):
    """Primal: per-ray ``sample(Primal)``; adjoint: ``sample(Primal)`` + ``sample(Backward)``
    replay with an independent seed (the two-path estimator of Yan et al. 2025, Eq. 4: independent paths for
    the loss adjoint and for the pixel derivative)."""

    def primal(self) -> mi.TensorXf:
        s: _PixelSettings = self.settings
        mean = _pixel_passes(self.scene).primal(s.sensors, s.index, s.seed, s.spp)
        return mi.TensorXf(dr.ravel(mean), (dr.width(s.index), 3))

    def adjoint(self, grad_out: mi.TensorXf) -> None:
        s: _PixelSettings = self.settings
        δ_pixel = dr.unravel(mi.Color3f, grad_out.array)
        _pixel_passes(self.scene).adjoint(s.sensors, s.index, δ_pixel, s.seed_grad, s.spp_grad, self.fresh)


@torch_to_drjit
def _render_pixels_drjit(scene: Scene, values: dict, index, grad_names: frozenset, settings: _args.RenderSettings,
                         sensors: tuple[int, ...]):
    native = {name: scene.to_drjit(name, value) for name, value in values.items()}
    fields = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)}  # flat: asdict's deep copy costs 5x
    pixel_settings = _PixelSettings(**fields, index=mi.UInt32(index.array), sensors=sensors)
    return dr.custom(_PixelRenderOp, scene, native, grad_names, pixel_settings)


def integrator_problem(scene: Scene) -> str | None:
    """Why ``render_pixels`` cannot render ``scene``'s integrator, or None: it replays paths
    (``prb``, ``prb_basic``, ``prbvolpath``); a projective integrator's boundary terms are not
    restricted to pixels (``torchir tune`` leaves pixel sampling out for them)."""
    from mitsuba.python.ad.integrators.common import RBIntegrator

    integrator = scene.integrator
    if isinstance(integrator, RBIntegrator):
        return None
    return (f"render_pixels needs a path-replay integrator (prb, prb_basic, prbvolpath); the scene "
            f"uses {type(integrator).__name__}")


def _check_integrator(scene: Scene) -> None:
    problem = integrator_problem(scene)
    if problem is not None:
        raise TypeError(problem)


def _check_box_filter(scene: Scene, sensor: int) -> None:
    rfilter = scene.sensor(sensor).film().rfilter()
    if not type(rfilter).__name__.lower().startswith("box") and "BoxFilter" not in str(rfilter):
        scene.warn_once(
            f"rfilter{sensor}",
            f"sensor {sensor} uses a {type(rfilter).__name__} reconstruction filter: render_pixels "
            f"estimates box-filtered pixels, which differ from this film's pixels. Use "
            f"rfilter={{'type': 'box'}} (all built-in scenes do).",
        )


def _check_index(index: object, pixel_count: int, sensors: int = 1) -> torch.Tensor:
    if not isinstance(index, torch.Tensor):
        raise TypeError(f"index must be a torch.LongTensor of pixel indices, got {type(index).__name__}")
    if index.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"index must be an integer tensor (int64 or int32), got {index.dtype}")
    if index.dim() != 1 or index.numel() == 0:
        raise ValueError(f"index must be a non-empty 1-D tensor, got shape {tuple(index.shape)}")
    lo, hi = (int(v) for v in torch.aminmax(index))
    if lo < 0 or hi >= pixel_count:
        layout = (f"the sensor has {pixel_count} pixels (y * W + x)" if sensors == 1 else
                  f"the {sensors} sensors have {pixel_count} pixels (k * H * W + y * W + x)")
        raise IndexError(f"pixel index out of range: got [{lo}, {hi}], {layout}")
    # on the render device: Dr.Jit takes a host tensor as an LLVM array, which a CUDA variant cannot trace
    return index.to(device=backend.device(), dtype=torch.int32)


def render_pixels(
    scene: Scene,
    params: Mapping[str, torch.Tensor] | None,
    index: torch.Tensor,
    spp: int = 1,
    seed: int = 0,
    sensor: int | mi.Sensor | Sequence[int | mi.Sensor] = 0,
    spp_grad: int | None = None,
    seed_grad: int | None = None,
) -> torch.Tensor:
    """Render only the pixels ``index`` of sensor ``sensor``, differentiably.

    Each entry of ``index`` is traced independently with ``spp`` paths (repeated indices are
    independent draws, as an i.i.d. pixel sampler needs). Gradients replay independent paths
    (``seed_grad``), so that a pixel-sampling estimator built on it stays unbiased.

    Args:
        scene: a :class:`torchir.Scene` whose integrator is ``prb``, ``prb_basic`` or ``prbvolpath``.
        params: as for :func:`render`.
        index: ``(N,)`` integer tensor of flat pixel indices ``y * W + x``; with a list of
            sensors, ``k * H * W + y * W + x`` for pixel ``(x, y)`` of ``sensor[k]``.
        spp: paths per listed pixel, >= 1.
        sensor: a sensor (its index or one of the scene's ``mi.Sensor`` objects, as for
            :func:`render`), or a list of sensors of one resolution whose pixels are traced in
            one wavefront (a multi-view pixel batch in one pass instead of one per view).
        seed, seed_grad, spp_grad: as for :func:`render`.

    Returns:
        ``(N, 3)`` float32 radiance of the listed pixels.

    Example:
        >>> idx = torch.tensor([0, 5, 5, 1023])
        >>> render_pixels(scene, {}, idx, spp=4, seed=0).shape
        torch.Size([4, 3])
    """
    scene = _args.check_scene(scene)
    sensors = _check_sensors(scene, sensor)
    settings = _args.render_settings(scene, sensors[0], spp, seed, spp_grad, seed_grad)
    h, w = scene.sensor_resolution(sensors[0])
    index = _check_index(index, len(sensors) * h * w, len(sensors))
    _check_integrator(scene)
    for k in sensors:
        _check_box_filter(scene, k)
    values, grad_names = _args.split_params(scene, params)
    return _render_pixels_drjit(scene, values, index, grad_names, settings, sensors)


def _check_sensors(scene: Scene, sensor: object) -> tuple[int, ...]:
    """``sensor`` (indices or the scene's ``mi.Sensor`` objects) as a non-empty tuple of valid
    sensor indices of one resolution."""
    if isinstance(sensor, (list, tuple)):
        if not sensor:
            raise ValueError("sensor must be a sensor index or a non-empty list of them, got []")
        sensors = tuple(sensor)
    else:
        sensors = (sensor,)
    for k in sensors:
        if isinstance(k, bool) or not isinstance(k, (int, mi.Sensor)):
            raise TypeError(f"sensor must be an int, an mi.Sensor of the scene or a list of ints / sensors, got {sensor!r}")
    sensors = tuple(scene.sensor_index(k) for k in sensors)  # range check / membership, with the scene's own message
    sizes = {scene.sensor_resolution(k) for k in sensors}
    if len(sizes) > 1:
        raise ValueError(f"sensors {list(sensors)} differ in resolution ({sorted(sizes)}): one wavefront needs one film size")
    return sensors
