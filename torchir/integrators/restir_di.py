"""ReSTIR direct illumination for inverse rendering, with reservoirs reused across gradient steps.

Wang et al. 2023, "Amortizing samples in physics-based inverse rendering using ReSTIR" (SIGGRAPH
Asia): each camera sample resamples its light sample from streaming RIS over ``candidates`` light
candidates and, with reuse, from the reservoirs of the previous step (temporal) or of nearby
samples (spatial), combined with Bitterli et al.'s unbiased ``1/Z`` weights. Options (what each
does, their defaults and named configurations) are one :class:`~torchir.integrators.restir_options.ReSTIROptions`;
``mi.load_dict({"type": "restir_di", "candidates": 4})`` sets them too.

Layout: this module is the step (:meth:`ReSTIRDirectIntegrator.step`: burn-in, one resampling
pass, the chains advanced) and its backward (:meth:`ReSTIRDirectIntegrator.backward`); the pass
itself is :mod:`._restir_pass`, the chains and their checkpoint form :mod:`._restir_state`, the
boundary terms of shape gradients :mod:`._restir_boundary`.

The gradient is the interior term: ``W``, the chosen light sample and its visibility are
constants, ``Le * fs * g`` is differentiated. That covers the gradient only where
``p̂ = lum(f) > 0``; where ``f = 0`` but its gradient is not (a black texel, a switched-off
light), each lane keeps the first of its fresh candidates with ``p̂ = 0`` and adds
``df(y0) * n0 / (M p_c(y0))`` to the gradient (``n0`` of the ``M`` candidates had ``p̂ = 0``; one
shadow ray tests ``y0``). Its value is 0, so the image is unchanged, and it is unbiased for the
remainder ``∫ df 1[p̂ = 0]``. That remainder is non-zero only where a differentiated value is
exactly 0 (a light's cone or a one-sided emitter zeroes ``f`` *and* its derivative), so
``step(zero_remainder=False)`` skips it: torchir's ``render`` does when no differentiated
material or emitter value has a 0 entry.

Direct illumination at the first hit only: emission seen by the camera plus one resampled light
vertex (point, spot and area emitters). RGB variants; no media, no environment emitters, a box
pixel filter (:func:`check_scene` refuses the rest).
"""
from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from .._frozen import freeze as guarded_freeze
from ..scene import is_geometry_key
from . import _knn, _light_guide
from ._light import eval_target, rebuild_interaction
from ._restir_boundary import BoundaryTerms
from ._restir_pass import PassSettings, ResamplingPass, footprints, tic
from ._restir_state import (LOADED, STORE, PassStats, SensorState, StepCache, carry_over, chain, chain_from_dict,
                            chain_to_dict, project, reservoir_stats)
from ._scene_watch import EmitterWatch, GeometryWatch, ValueReader
from .restir_options import ReSTIROptions

__all__ = ["ReSTIRDirectIntegrator", "ReSTIROptions", "check_scene", "StepCache"]

CHAIN_CAP = 64  # default M cap of a lane's own chain, in candidates (ReSTIROptions.m_cap)
# lane chains with light guides burn in with two passes: this share of the burn-in's candidates
# learns the guides (drawn as without them), the rest draws from them
GUIDE_LEARNING_SHARE = 0.25


def check_scene(scene: mi.Scene) -> None:
    """Raise ``ValueError`` for what ReSTIR DI does not handle (instead of wrong results)."""
    variant = mi.variant()
    if "rgb" not in variant or "polarized" in variant:
        raise ValueError(f"ReSTIR direct illumination supports RGB variants only, not {variant!r}")
    for em in scene.emitters():
        if em.flags() & int(mi.EmitterFlags.Infinite):
            raise ValueError("ReSTIR direct illumination does not support environment emitters (envmap, constant) yet")
    for sh in scene.shapes():
        if sh.interior_medium() is not None or sh.exterior_medium() is not None:
            raise ValueError("ReSTIR direct illumination does not support participating media (volumes)")
    for sensor in scene.sensors():
        if not sensor.film().rfilter().is_box_filter():
            raise ValueError("ReSTIR direct illumination needs a box reconstruction filter on every film")
    depth = getattr(scene.integrator(), "max_depth", None)
    if depth is not None and (depth < 0 or depth > 2):
        raise ValueError(
            f"the scene's integrator renders indirect light (max_depth={depth}); ReSTIR handles direct "
            f"illumination only: use a direct-illumination scene (max_depth=2, e.g. 'painting', 'oxalis_lite')"
        )


class ReSTIRDirectIntegrator(BoundaryTerms):
    __doc__ = __doc__
    zero_remainder = True  # step() takes zero_remainder= (torchir's render sets it per step)

    def __init__(self, props: mi.Properties | None = None, options: ReSTIROptions | None = None, **changes: Any) -> None:
        """``options`` (default ``ReSTIROptions()``), with ``changes`` applied; a Mitsuba
        ``props`` (``mi.load_dict({"type": "restir_di", "candidates": 4})``) sets options too."""
        props = mi.Properties() if props is None else props
        super().__init__(props)
        if "max_depth" in props and props["max_depth"] != 2:
            raise ValueError("ReSTIR direct illumination renders direct light only: max_depth must be 2")
        if options is not None and not isinstance(options, ReSTIROptions):
            raise TypeError(f"options must be a ReSTIROptions, got {type(options).__name__}")
        from_props = {f.name: props[f.name] for f in dataclasses.fields(ReSTIROptions) if f.name in props}
        options = (options or ReSTIROptions()).replace(**{**from_props, **changes})
        if options.nn_backend == "kdtree" and not _knn.have_scipy():
            raise ValueError("nn_backend='kdtree' needs scipy (pip install scipy); use 'grid' or 'auto'")
        self.options = options
        self._reuse_suspended = False  # the gradient pass of forward_only: plain RIS
        self.m_cap = float(options.m_cap if options.m_cap > 0 else 2 * options.candidates)
        self.chain_cap = float(options.m_cap if options.m_cap > 0 else CHAIN_CAP * options.candidates)
        self._neighbour_search = _knn.NeighbourSearch(self.nn_backend)
        self._resampler = ResamplingPass(self._neighbour_search)
        self._emitter_watch = EmitterWatch()
        self.freeze = backend.frozen_renders() if options.freeze is None else options.freeze  # off after a failed replay
        self._frozen_pass = None
        self._init_boundary_terms()
        self._geometry_watch = GeometryWatch()
        self._camera_read = ValueReader()  # the camera's transform, read from the device only when it changes
        self._geometry_seen: tuple | None = None  # geometry at the last step
        self._geometry_frozen: tuple | None = None  # geometry the frozen pass was recorded with
        self.last_pass_frozen = False
        self.states: dict[int, SensorState] = {}
        self.grad_states: dict[int, SensorState] = {}  # the gradient's own chains (decorrelated paths)
        self.last: dict[int, StepCache] = {}
        self._last_pass = None
        self.timings: dict[str, float] = {}

    @property
    def stats(self) -> dict[str, float]:
        """Reservoir statistics of the last step (computed when asked: they sync the host)."""
        if self._last_pass is None:
            return {}
        out, stats = self._last_pass
        return reservoir_stats(out, stats)

    def carries_over(self, scene: mi.Scene) -> bool:
        """One store for all views (Alg. 8): ``carry_over``, or ``auto`` with several sensors."""
        return self.multiview == "carry_over" or (self.multiview == "auto" and len(scene.sensors()) > 1)

    @property
    def temporal(self) -> bool:
        return self.options.temporal and not self._reuse_suspended

    @property
    def spatial(self) -> bool:
        return self.options.spatial and not self._reuse_suspended

    @property
    def shadowed(self) -> bool:
        return self.target == "shadowed"

    @property
    def lane_chains(self) -> bool:
        """Whether each camera sample resamples with its own previous reservoir at a kept
        shading point (temporal reuse with kept offsets, no spatial reuse)."""
        return self.temporal and not self.spatial and self.offset_lifetime > 0

    @property
    def reuse(self) -> bool:
        return self.temporal or self.spatial

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        """Forget every sensor's reservoirs (the next step burns in again)."""
        self.states.clear()
        self.grad_states.clear()
        self.last.clear()
        self._reset_boundary_terms()

    def state(self, scene: mi.Scene, sensor: int) -> SensorState:
        """The image's chain for ``sensor`` (a fresh one after the scene's topology changed)."""
        return chain(self.states, scene, sensor)

    def grad_state(self, scene: mi.Scene, sensor: int) -> SensorState:
        """The gradient's own chain for ``sensor`` (``grad_paths="decorrelated"`` with reuse)."""
        return chain(self.grad_states, scene, sensor)

    # ------------------------------------------------------------------ Mitsuba API
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        index, sensor_obj = _sensor(scene, sensor)
        spp = spp or sensor_obj.sampler().sample_count()
        image, cache = self.step(scene, index, int(seed), int(spp))
        self.last[index] = cache
        return image

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        index, sensor_obj = _sensor(scene, sensor)
        if index not in self.last:
            raise RuntimeError("render_backward() needs a render() of the same sensor first")
        spp = spp or sensor_obj.sampler().sample_count()
        # moving geometry needs the attached shading points and the boundary terms, as through
        # torchir's render (functions/_sampler_op.py); the moving values must be leaves there:
        # each pass back-propagates on its own, and the first clears the graph above them
        geometry = any(is_geometry_key(k) and dr.grad_enabled(v) for k, v in (params or {}).items())
        self.backward(scene, self.last.pop(index), grad_in, int(seed), int(spp), geometry=geometry,
                      params=params if geometry else None)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        raise NotImplementedError("ReSTIR DI implements reverse mode only (render_backward)")

    # ------------------------------------------------------------------ one step
    def step(self, scene: mi.Scene, sensor: int, seed: int, spp: int, zero_remainder: bool = True):
        """Render one image with reuse and advance sensor ``sensor``'s reservoirs.
        ``zero_remainder``: keep the ``p̂ = 0`` remainder of the gradient (module docstring).

        Returns ``(image (H, W, 3) TensorXf, StepCache)``."""
        st = self.state(scene, STORE if self.carries_over(scene) else sensor)
        t0 = tic()
        self._burn_in(scene, sensor, seed, spp, st)
        t_burn = tic() - t0
        prev_camera = st.camera
        (ray_weight, image), out, stats, prev = self._advance(scene, sensor, seed, spp, st, zero_remainder)
        self.timings = {"burn_in": t_burn, **stats.timings}
        self._last_pass = (out, stats)  # statistics computed on demand (host syncs)
        return image, StepCache(sensor, spp, out, ray_weight, prev, prev_camera, stats.zero)

    def _burn_in(self, scene: mi.Scene, sensor: int, seed: int, spp: int, st: SensorState) -> None:
        """Before a chain's first step: ``burn_in`` forward-only reuse passes into ``st``."""
        if st.prev is not None or not self.temporal or self.burn_in <= 0:
            return
        st.lights = self._emitter_watch(scene)
        # lane chains resample at one shading point each: their burn-in is one RIS over all of
        # its passes' candidates (the same reservoirs in distribution, one camera ray and one
        # pass instead of burn_in; measured at 128², burn-in 32: 2.0 s -> 0.49 s on many_lights)
        one_pass = self.lane_chains and not self.carries_over(scene)
        passes = [1] * self.burn_in
        if one_pass:  # with light guides, two: the first learns them, the second draws from them
            learn = max(1, round(self.burn_in * GUIDE_LEARNING_SHARE)) if self.light_guide > 0 else self.burn_in
            passes = [learn, self.burn_in - learn] if self.burn_in > learn else [self.burn_in]
        for i, count in enumerate(passes):
            extra = {"candidates": count * self.candidates} if one_pass else {}
            burn_seed = int(mi.sample_tea_32(seed, 0x5EED0000 + i)[0])
            _, st.prev, burn = self.sample_paths(scene, sensor, burn_seed, spp, st.prev, st, st.camera, **extra)
            st.camera, st.geometry, st.guide = burn.camera, burn.geometry, burn.guide

    def _advance(self, scene: mi.Scene, sensor: int, seed: int, spp: int, st: SensorState, zero_remainder: bool):
        """One pass of the chain ``st`` (reusing its last reservoirs) that then holds the pass's
        reservoirs. Returns ``((ray_weight, image), reservoirs, PassStats, the reservoirs reused)``."""
        lights = self._emitter_watch(scene) if self.temporal else None  # only temporal reuse needs it
        prev = st.prev
        if prev is not None and not self._emitter_watch.same_support(st.lights, lights):
            prev = None  # a light came on or moved: the old reservoirs cannot hold its samples
        paths, out, stats = self.sample_paths(scene, sensor, seed, spp, prev, st, st.camera, zero_remainder)
        if self.temporal and self.carries_over(scene):  # one store for all views (Wang et al. 2023, Alg. 8)
            st.prev, st.camera, st.lights = carry_over(scene, sensor, out, prev), None, lights
        elif self.temporal:
            st.prev, st.camera, st.lights, st.geometry, st.guide = out, stats.camera, lights, stats.geometry, stats.guide
        st.steps += 1
        return paths, out, stats, prev

    def sample_paths(self, scene: mi.Scene, sensor: int, seed: int, spp: int, prev, st: SensorState,
                     prev_camera: tuple | None = None, zero_remainder: bool = False, candidates: int | None = None):
        """One non-differentiable resampling pass (the path sampling of Wang et al. 2023, Alg. 4) against the
        reservoirs ``prev``, rendered by a camera ``prev_camera`` (``SensorState.camera``);
        ``zero_remainder``: also draw the ``p̂ = 0`` remainder's samples (``PassStats.zero``);
        ``candidates``: light candidates per camera sample (None: the integrator's; another
        count runs unfrozen).

        Returns ``((ray_weight, image), reservoirs, PassStats)``."""
        with dr.suspend_grad():
            return self._sample_paths(scene, sensor, seed, spp, prev, st, prev_camera, zero_remainder,
                                      self.candidates if candidates is None else int(candidates))

    def _sample_paths(self, scene, sensor, seed, spp, prev, st, prev_camera, zero_remainder, candidates):
        sensor_obj = scene.sensors()[sensor]
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        camera = (self._camera_read(f"sensor{sensor}", sensor_obj.world_transform()), w, h, spp)
        if st.radius <= 0:
            auto_radius, small_footprint = footprints(scene, sensor_obj, seed, spp, w, h)
            st.radius = self.radius if self.radius > 0 else auto_radius
            st.window = int(min(3, max(1, np.ceil(st.radius / small_footprint))))  # the cap of the per-query windows
        source = "temporal" if self.temporal else ("spatial" if self.spatial else "none")
        if source == "temporal" and prev is None:
            source = "none"
        k = self.neighbors if self.spatial else 1
        static = source != "temporal" or prev_camera == camera  # same view, same lane layout
        layout = _knn.ScreenLayout(w, h, spp, st.window, self.spp_chains) if static else None
        reproject = source == "temporal" and self.carries_over(scene)  # the store: any views
        # the previous step's lanes are this step's (same camera and layout, same geometry, so
        # the same shading points): offsets persist
        geometry = self._geometry_watch(scene)
        if st.geometry == LOADED:  # reservoirs from a checkpoint: of this scene's geometry
            st.geometry = geometry
        keep_offsets = (self.offset_lifetime > 0 and source == "temporal" and static and not reproject
                        and geometry == st.geometry)
        # the geometry moved since the reservoirs were made (a shape being optimised): a short
        # memory, or the image's error follows the moved shadow for many steps (measured on the
        # blocker's pose, Adam at 3 degrees a step: the angle wandered +-4-7 degrees with the M cap
        # 32, +-1.5-1.9 with 4, and converged from 4 of 4 starts instead of 2)
        m_cap = self.m_cap
        if source == "temporal" and geometry != st.geometry and self.moving_geometry_m_cap > 0:
            m_cap = min(m_cap, float(self.moving_geometry_m_cap))
        freeze = self.freeze and candidates == self.candidates and (
            source == "none" or reproject or (layout is not None and self.nn_backend in ("auto", "screen")))
        if freeze:
            freeze = self._frozen_pass_ready(scene, geometry)
        stats = PassStats(camera=camera, k=k if source != "none" else 0, geometry=geometry)
        # the store's points bucketed by their pixel in this film (traced: see bucket_by_pixel)
        buckets = _knn.bucket_by_pixel(*project(sensor_obj, prev), w * h) if reproject else None
        guide = None
        if self.light_guide > 0 and self.lane_chains:
            # the lanes' guides are for their kept shading points: fresh ones where the lanes
            # are new (no kept offsets) or the guides are another film's or emitter count's
            n, lights = w * h * spp, _light_guide.guided_lights(scene)
            guide = st.guide
            if (not keep_offsets or guide is None or dr.width(guide.light) != n
                    or dr.width(guide.mass_l) != n * lights):
                guide = _light_guide.empty_guide(n, lights)
        settings = self._pass_settings(sensor, spp, source, k, float(st.radius), layout, bool(zero_remainder),
                                       keep_offsets, candidates, m_cap)
        args = (scene, settings, prev, buckets, guide)
        t0 = tic()
        if freeze:  # traced once per configuration, then replayed (no Python tracing, no codegen)
            try:
                ray_weight, image, r, n_ok, zero, guide = self._frozen_pass(dr.opaque(mi.UInt32, seed), *args, None)
                dr.eval(image, r, zero if zero is not None else ())
            except Exception as error:  # noqa: BLE001 - fall back, loudly, as torchir's frozen renders do
                self.freeze = freeze = False
                warnings.warn(f"frozen ReSTIR pass failed ({error!r}); this integrator now runs unfrozen", stacklevel=2)
        if freeze:
            stats.timings = {"pass": tic() - t0}
            self._neighbour_search.last = (None if source == "none" else "reprojected" if reproject
                                           else "lane" if keep_offsets and self.lane_chains else "screen")
        else:
            timings: dict[str, float] = {}
            # an opaque seed, as the frozen pass gets: a literal one compiles new kernels every
            # step wherever the seed enters a kernel (the offsets' redraw hash did: 2 s a step)
            ray_weight, image, r, n_ok, zero, guide = self._resampler.run(dr.opaque(mi.UInt32, seed), *args, timings)
            stats.timings = timings
        stats.zero, stats.guide = zero, guide
        if source != "none":
            stats.neighbor_count = n_ok
        self.last_pass_frozen = freeze
        return (ray_weight, image), r, stats

    def _pass_settings(self, sensor: int, spp: int, source: str, k: int, radius: float, layout: Any,
                       zero_remainder: bool, keep_offsets: bool, candidates: int, m_cap: float) -> PassSettings:
        """The pass's settings: these, and the integrator's options as they apply to it."""
        step_pass = candidates == self.candidates  # not a burn-in pass over its own count
        # a redrawn lane's RIS continues over the burn-in's count of candidates (a young chain)
        young = self.lane_chains and self.burn_in > 0 and step_pass
        return PassSettings(
            sensor=sensor, spp=spp, source=source, k=k, radius=radius, layout=layout, zero_remainder=zero_remainder,
            keep_offsets=keep_offsets, candidates=candidates, m_cap=m_cap, shadowed=self.shadowed,
            lane_chains=self.lane_chains, chain_cap=self.chain_cap, normal_threshold=self.normal_threshold,
            offset_lifetime=self.offset_lifetime, light_guide=self.light_guide,
            young_candidates=self.burn_in * self.candidates if young else 0,
            learn=not keep_offsets or step_pass, same_point=self.shadowed)

    def _frozen_pass_ready(self, scene: mi.Scene, now: tuple) -> bool:
        """Whether the frozen pass may run now, with the scene's geometry ``now`` (GeometryWatch).
        A replay reuses the acceleration structure it was recorded with, so once geometry
        changes (a mesh's vertices, a shape's transform) the steps run unfrozen; after a step
        with unchanged geometry the pass is recorded anew. Vertices bound by each render (shape
        optimisation) are a new variable every step, so such runs stay unfrozen. A replay after a
        geometry edit renders wrong (measurements: docs/restir-measurements.md, "Frozen passes")."""
        steady = self._geometry_seen is None or now == self._geometry_seen
        self._geometry_seen = now
        if self._frozen_pass is not None and now == self._geometry_frozen:
            return True
        self._frozen_pass = None  # recorded against an acceleration structure that is gone
        if not steady:
            return False
        # one recording per sensor and pass kind (fresh RIS, reuse) is expected
        recordings = backend.frozen_recordings(len(scene.sensors()))
        self._frozen_pass, self._geometry_frozen = guarded_freeze(self._resampler.run, warn_after=recordings), now
        return True

    # ------------------------------------------------------------------ gradient
    def backward(
        self,
        scene: mi.Scene,
        cache: StepCache,
        grad_in: mi.TensorXf,
        seed_grad: int,
        spp_grad: int,
        geometry: bool = False,
        params: Any = None,
    ) -> None:
        """Gradient of the step ``cache`` for the image adjoint ``grad_in``.

        Interior term (Wang et al. 2023, §4: ``W`` and the light sample held constant) on the step's
        paths (``shared``) or on a second resampling pass (``decorrelated``, ``forward_only``).
        ``geometry`` (shape parameters):
        the shading point follows the camera ray (attached re-intersection), and the
        visibility-boundary terms are added without reuse (:meth:`_boundary_backward`);
        ``params`` are the grad-enabled values they differentiate.
        """
        t0 = tic()
        key = STORE if self.carries_over(scene) else cache.sensor
        lanes, ray_weight, spp, zero = cache.lanes, cache.ray_weight, cache.spp, cache.zero
        if self.forward_only:  # plain RIS with seed_grad
            self._reuse_suspended = True
            try:
                (ray_weight, _), lanes, stats = self.sample_paths(
                    scene, cache.sensor, seed_grad, spp_grad, None, self.state(scene, key), None, zero is not None)
            finally:
                self._reuse_suspended = False
            spp, zero = spp_grad, stats.zero
        elif self.grad_paths == "decorrelated":
            # the gradient's own chain: reservoirs, kept offsets and guides reused from earlier
            # gradient passes only, so that nothing the image reused is reused here (resampling
            # against the image's reservoirs left Cov(I, dI) in the L2 gradient: z = 7.9 and 12
            # for the spatiotemporal and persistent presets on ajar_painting)
            gst = self.grad_state(scene, key)  # its burn-in: as a first step on seed_grad would
            self._burn_in(scene, cache.sensor, seed_grad, spp_grad, gst)
            (ray_weight, _), lanes, stats, _ = self._advance(scene, cache.sensor, seed_grad, spp_grad, gst, zero is not None)
            spp, zero = spp_grad, stats.zero
        band = self._band_objective(scene, params, grad_in, cache.sensor, seed_grad, spp_grad) if geometry else None
        n = dr.width(lanes.valid)
        with dr.resume_grad():
            if geometry:  # ray-following shading point, as direct_projective
                si = scene.ray_intersect(mi.Ray3f(lanes.o, lanes.d), mi.RayFlags.All, True, lanes.valid)
            else:  # material point rebuilt from (shape, prim, prim_uv): exact, no BVH traversal
                si = rebuild_interaction(scene, lanes, lanes.valid)
            f, _ = eval_target(scene, si, lanes.y, lanes.valid & (lanes.W > 0), visibility=False)
            le = si.emitter(scene).eval(si, lanes.valid)
            contrib = ray_weight * (le + f * lanes.W)  # W detached: only the path contribution is differentiated
            if zero is not None:  # the p̂ = 0 remainder: value 0, gradient df(y0) w0
                y0, w0 = zero
                f0, _ = eval_target(scene, si, y0, lanes.valid & (w0 > 0), visibility=False, positive_only=False)
                contrib += ray_weight * f0 * w0
            pix = dr.arange(mi.UInt32, n) // spp
            delta_l = dr.gather(mi.Color3f, grad_in.array, pix) / spp
            if band is None:
                dr.backward(dr.dot(contrib, delta_l))
            else:  # one pass: both go through the normals computed from the vertices
                dr.backward(dr.sum(dr.dot(contrib, delta_l)) + band)
        if geometry:
            self._boundary_backward(scene, params, grad_in, cache.sensor, seed_grad, spp_grad)
        self.timings["backward"] = tic() - t0


    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        out = {sensor: chain_to_dict(st) for sensor, st in self.states.items()}
        for sensor, st in self.grad_states.items():  # the gradient's chain beside the image's
            out.setdefault(sensor, {})["grad_chain"] = chain_to_dict(st)
        return out

    def load_state_dict(self, state: dict) -> None:
        self.reset()
        for sensor, d in state.items():
            if "reservoirs" in d:
                self.states[int(sensor)] = chain_from_dict(d)
            if d.get("grad_chain") is not None:
                self.grad_states[int(sensor)] = chain_from_dict(d["grad_chain"])

    def to_string(self) -> str:
        return (
            f"ReSTIRDirectIntegrator[candidates={self.candidates}, neighbors={self.neighbors}, "
            f"temporal={self.temporal}, spatial={self.spatial}, grad_paths={self.grad_paths!r}]"
        )


# ---------------------------------------------------------------------- helpers
class _OptionAttribute:
    """``integrator.<name>`` reads ``integrator.options.<name>``; setting it is refused (one channel:
    the options)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.__doc__ = f"``options.{name}`` (read-only)"

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(obj.options, self.name)

    def __set__(self, obj: Any, value: Any) -> None:
        raise AttributeError(f"ReSTIR options are set when the sampler is made, not on its integrator: "
                             f"ReSTIRSampler(scene, {self.name}={value!r}) or ReSTIROptions({self.name}={value!r})")


for _name in ("candidates", "neighbors", "radius", "normal_threshold", "burn_in", "grad_paths", "forward_only",
              "nn_backend", "target", "multiview", "spp_chains", "offset_lifetime", "light_guide",
              "shadow_edge_sampling", "edge_guiding", "edge_temporal", "edge_light_candidates", "edge_candidates",
              "edge_chain_cap", "silhouette_sampling", "silhouette_candidates", "shading_bands", "moving_geometry_m_cap"):
    setattr(ReSTIRDirectIntegrator, _name, _OptionAttribute(_name))
del _name


def _sensor(scene: mi.Scene, sensor) -> tuple[int, mi.Sensor]:
    sensors = scene.sensors()
    if isinstance(sensor, (int, np.integer)):
        return int(sensor), sensors[int(sensor)]
    for i, s in enumerate(sensors):
        if s is sensor:
            return i, s
    raise ValueError("the sensor does not belong to the scene")

