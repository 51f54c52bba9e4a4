"""ReSTIR direct illumination with reservoirs reused across gradient steps (paper 004).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Meaning
     - Default
   * - ``candidates``
     - int
     - M, light candidates per camera sample (streaming RIS, Alg. A1). 1 without reuse = B.1.
     - 16
   * - ``neighbors``
     - int
     - k, reservoirs combined per camera sample (exact k-NN in world space). 16 and 8
       (with ``m_cap`` 32) measured 2.4-3.5x lower error x time than 8 and 4 on
       ``ajar_painting``, ``many_lights`` and ``oxalis_lite`` at 128^2 (``bench restir``).
     - 8
   * - ``radius``
     - float
     - R, neighbour search radius in world units; 0 = 2x the median pixel footprint (D3).
     - 0
   * - ``normal_threshold``
     - float
     - τ_n, neighbours with ``n . n' < τ_n`` are dropped.
     - 0.9
   * - ``m_cap``
     - int
     - cap on a neighbour's and a stored reservoir's M (D2); 0 = 2 * candidates for reservoirs
       found by a search, 64 * candidates for a lane's own chain (``offset_lifetime``). Any
       move of a shading point lets a long memory count in Z (R8) where its sample is hidden
       from the new point: rare lanes go dark or bright for as many steps as the memory lasts
       (measured at 128², ``ajar_painting``: a 20 * candidates cap with searched neighbours
       2.4x the gradient error of 2 *; a lane's chain whose offset walks 0.05 pixel a step,
       4.5x (7.8x on ``many_lights``) the error of a fixed one). A chain at a fixed shading
       point has no such events, so it keeps 64 *.
     - 0
   * - ``offset_lifetime``
     - float
     - steps a camera sample keeps its offset in the pixel, on average (each step a lane's
       offset is redrawn with probability 1 / lifetime, chosen by the seed alone, not by the
       offsets or their hits, so every step's offsets stay uniform and its estimate unbiased;
       ``RedrawnLanes``: a fixed count of lanes a step); 0 = a fresh offset every
       step; ``inf`` = until the sensor or the geometry changes. With ``temporal`` and without
       ``spatial`` a kept lane resamples with its own previous reservoir, at the same shading
       point; a redrawn lane starts afresh, its first RIS running over ``burn_in x candidates``
       more candidates (in the same pass, on helper streams; else such young lanes dominate
       the error: see ``_pass``). See ``preset="persistent"`` of ``ReSTIRSampler``.
     - 0
   * - ``light_guide``
     - float
     - with lane chains (``offset_lifetime``, temporal reuse only): the share of each lane's
       candidates drawn from a guide it learns at its kept shading point (two marginal
       histograms over the primary sample of the light it sees lit; ``_light_guide``). The
       rest are drawn as usual, and RIS weights use the mixture's density, so the estimate
       stays unbiased. 0 = off.
     - 0
   * - ``temporal`` / ``spatial``
     - bool
     - both: the k nearest reservoirs of the previous step (the paper); temporal only: the
       nearest one; spatial only: the k nearest fresh reservoirs of the same step; neither:
       plain RIS (B.2).
     - True / True
   * - ``burn_in``
     - int
     - forward-only reuse passes run before a sensor's first step (§3.9); lane chains
       (kept offsets, no spatial reuse) run one pass over ``burn_in`` x ``candidates``.
     - 32
   * - ``grad_paths``
     - str
     - ``decorrelated``: a second resampling pass with ``seed_grad``; with temporal reuse it
       is a step of the gradient's own chain (reservoirs, kept offsets and guides of earlier
       gradient passes, burned in like the image's chain; saved with it), so the image and its
       gradient are independent and the gradient unbiased for any loss. ``shared``: the
       gradient re-evaluates the primal's paths (paper, Alg. P4; no second pass), unbiased
       only for a loss linear in the image: for L2,
       ``E[2 (I - T) dI] = 2 (E[I] - T) E[dI] + 2 Cov(I, dI)``, so the fit is pulled off the
       truth in proportion to the image's variance (docs/restir.md, "Gradient paths").
     - decorrelated
   * - ``forward_only``
     - bool
     - ablation: reuse for the image, plain RIS (``seed_grad``) for the gradient.
     - False
   * - ``nn_backend``
     - str
     - ``auto`` (the fastest on the first reuse steps, timed) | ``kdtree`` (scipy) | ``grid``
       (Dr.Jit) | ``screen`` (the previous step's samples of the surrounding pixels, for a
       sensor that has not moved; else the others). All find the same neighbours where the
       screen window (radius / 5th-percentile pixel footprint, 1-3 pixels) covers the radius.
     - auto
   * - ``spp_chains``
     - bool
     - at ``spp > 1``, sample ``s`` of a pixel reuses only samples ``s`` of its neighbours (``spp``
       interleaved chains; the screen search scans ``spp`` times fewer samples; a pixel's
       samples stay independent). Measured at 128², 4 spp: 0.66x / 0.59x the step time and
       lower gradient error (``oxalis_lite`` 0.028 vs 0.038, ``ajar_painting`` 0.029 vs 0.031).
     - True
   * - ``target``
     - str
     - ``shadowed``: p̂ includes visibility, one shadow ray per candidate and per neighbour
       (the paper, R14); ``unshadowed`` (Bitterli et al. 2020, unbiased variant): candidates
       and neighbour samples are weighted without shadow rays, one shadow ray tests the chosen
       sample (W = 0 when occluded), the support test Z keeps its shadow rays.
     - shadowed
   * - ``freeze``
     - bool
     - trace the resampling pass once per configuration and replay it (``dr.freeze``): no
       Python tracing or code generation per step. Used without reuse, and with reuse when the
       neighbours can come from the ``screen`` search (the sensor has not moved; ``nn_backend``
       ``auto`` or ``screen``); other steps run unfrozen. Per-stage timings are then the whole
       pass only.
     - True

Only direct illumination at the first hit: emission seen by the camera plus one resampled
light vertex (point, spot and area emitters). The gradient is the interior term (R17, R18):
``W``, the chosen light sample and visibility are constants, ``Le * fs * g`` is differentiated.
That covers the gradient only where ``p̂ = lum(f) > 0``; where ``f = 0`` but its gradient is not
(a black texel, a switched-off light: spec §3.5 left these at exactly 0), each lane keeps the
first of its fresh candidates with ``p̂ = 0`` and adds ``df(y0) * n0 / (M p_c(y0))`` to the
gradient (``n0`` of the ``M`` candidates had ``p̂ = 0``; one shadow ray tests ``y0``). Its value
is 0, so the image is unchanged, and it is unbiased for the remainder ``∫ df 1[p̂ = 0]``. That
remainder is non-zero only where a differentiated value is exactly 0 (a light's cone or a
one-sided emitter zeroes ``f`` *and* its derivative), so ``step(zero_remainder=False)`` skips
it: torchir's ``render`` does when no differentiated material or emitter value has a 0 entry
(measured: the remainder costs a third of a step on ``ajar_painting``).
RGB variants only; no media, no environment emitters, a box pixel filter.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.python.ad.integrators.common import RBIntegrator

from .. import backend
from .._frozen import freeze as guarded_freeze
from ..scene import is_geometry_key
from ..welding import WeldedFaces, moving_meshes
from . import _knn, _light_guide, _shading_bands, _shadow_edges, _silhouettes
from ._film import develop
from ._light import (FORWARD_FLAGS, LightSample, Reservoirs, eval_target, fresh_reservoirs, rebuild_interaction,
                     sample_candidate)
from ._mesh_edges import edges_of, mitsuba_silhouettes_wrong
from ._scene_watch import EmitterWatch, GeometryWatch, as_tuples
from .restir_options import ReSTIROptions

__all__ = ["ReSTIRDirectIntegrator", "ReSTIROptions", "check_scene", "StepCache"]

STORE = -1  # the state key of the one reservoir store of multiview="carry_over"
LOADED = ("loaded",)  # SensorState.geometry of reservoirs loaded from a state dict


CHAIN_CAP = 64  # default M cap of a lane's own chain, in candidates (m_cap: 2; see the m_cap row above)
# lane chains with light guides burn in with two passes: this share of the burn-in's candidates
# learns the guides (drawn as without them), the rest draws from them
GUIDE_LEARNING_SHARE = 0.25
GUIDE_LEARNING_PER_STEP = 4  # candidates a step's guides learn from (unrolled streams; longer ones: all)
UNROLLED_CANDIDATES = 32  # more candidates: a symbolic loop (kernel size and compile time)
# Unguided wavefronts of up to this many lanes run the candidates as a symbolic loop: unrolling
# halves nothing there but doubles the compile (painting, 16 candidates, 3 steps: 8.1 s -> 4.0 s
# at 16²; a step 15 vs 16 ms at 16², 70 vs 71 ms at 128²); from 256² on it pays (207 vs 233 ms)
SYMBOLIC_UP_TO_LANES = 128 * 128


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


def _signature(scene: mi.Scene) -> tuple:
    """Changes when the topology or the emitter count changes (automatic reset)."""
    return len(scene.emitters()), tuple(int(s.primitive_count()) for s in scene.shapes())


@dataclass
class SensorState:
    prev: Any = None  # Reservoirs of the last step (or None)
    radius: float = 0.0  # resolved neighbour radius
    window: int = 2  # screen-space search half-width in pixels (radius / small footprint)
    steps: int = 0
    signature: tuple = ()
    camera: tuple | None = None  # (sensor matrix, width, height, spp) of ``prev``
    lights: tuple | None = None  # EmitterWatch state when ``prev`` was made
    geometry: tuple | None = None  # GeometryWatch state when ``prev`` was made
    guide: Any = None  # the lanes' light guides (_light_guide.LightGuide; light_guide > 0)


@dataclass
class StepCache:
    """What a step's backward needs: its paths and the reservoirs it reused."""

    sensor: int
    spp: int
    lanes: Any  # Reservoirs of the step (y, W, shading point)
    ray_weight: Any
    prev: Any  # the reservoirs the step combined with (for the decorrelated pass)
    prev_camera: tuple | None = None  # the camera that rendered ``prev``
    zero: Any = None  # (LightSample y0, Float w0): the p̂ = 0 remainder of the gradient


@dataclass
class PassStats:
    neighbor_count: Any = None  # UInt32 per lane: neighbours combined (None: no reuse)
    k: int = 0
    camera: tuple | None = None  # the pass's (sensor matrix, width, height, spp)
    geometry: tuple | None = None  # the scene's geometry (GeometryWatch) during the pass
    zero: Any = None  # (LightSample y0, Float w0) per lane: see the module docstring
    guide: Any = None  # the lanes' light guides after the pass (light_guide), or None
    timings: dict = field(default_factory=dict)


def _tic() -> float:
    dr.sync_thread()
    return time.perf_counter()


EDGE_PAIRS_PER_SAMPLE = 4.0  # above this many (edge, light) pairs per shadow-edge sample, "auto" chains by length (edge_strategy)


class ReSTIRDirectIntegrator(RBIntegrator):
    __doc__ = __doc__
    zero_remainder = True  # step() takes zero_remainder= (torchir's render sets it per step)
    young_lane_burn_in = True  # a redrawn lane continues its first RIS over burn_in x candidates (see _pass; False: as before, for measurements)
    same_point_visibility = True  # a lane's own chain reuses its sample's visibility (see _combine; False: traced, for tests)

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
        self._emitter_watch = EmitterWatch()
        self.freeze = backend.frozen_renders() if options.freeze is None else options.freeze  # off after a failed replay
        self._frozen_pass = None
        self._boundary_integrators: dict[tuple[bool, bool], mi.Integrator] = {}  # direct_projective, by (secondary, primary)
        self._band_warned = False  # warned once that the shading-horizon term cannot run (see _band_objective)
        self._scene_params: tuple[mi.Scene, Any] | None = None  # (scene, mi.traverse(scene)) of _traversed
        self._edge_guides: dict[str, np.ndarray] = {}  # per mesh, see _shadow_edges.shadow_edge_backward
        self._edge_chains: dict[int, dict[str, Any]] = {}  # per sensor and mesh, likewise
        self._geometry_watch = GeometryWatch()
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
        return _reservoir_stats(out, stats)

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
        self._edge_guides.clear()
        self._edge_chains.clear()

    def state(self, scene: mi.Scene, sensor: int) -> SensorState:
        """The image's chain for ``sensor`` (a fresh one after the scene's topology changed)."""
        return _chain(self.states, scene, sensor)

    def grad_state(self, scene: mi.Scene, sensor: int) -> SensorState:
        """The gradient's own chain for ``sensor`` (``grad_paths="decorrelated"`` with reuse)."""
        return _chain(self.grad_states, scene, sensor)

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
        t0 = _tic()
        self._burn_in(scene, sensor, seed, spp, st)
        t_burn = _tic() - t0
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
        if self.temporal and self.carries_over(scene):  # Alg. A8: one store for all views
            st.prev, st.camera, st.lights = carry_over(scene, sensor, out, prev), None, lights
        elif self.temporal:
            st.prev, st.camera, st.lights, st.geometry, st.guide = out, stats.camera, lights, stats.geometry, stats.guide
        st.steps += 1
        return paths, out, stats, prev

    def sample_paths(self, scene: mi.Scene, sensor: int, seed: int, spp: int, prev, st: SensorState,
                     prev_camera: tuple | None = None, zero_remainder: bool = False, candidates: int | None = None):
        """One non-differentiable resampling pass (Alg. A4 without the backward) against the
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
        camera = (tuple(np.array(sensor_obj.world_transform().matrix).ravel().tolist()), w, h, spp)
        if st.radius <= 0:
            auto_radius, small_footprint = _footprints(scene, sensor_obj, seed, spp, w, h)
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
        args = (scene, sensor, spp, prev, float(st.radius), source, k, layout, bool(zero_remainder), buckets, keep_offsets,
                candidates, m_cap, guide)
        t0 = _tic()
        if freeze:  # traced once per configuration, then replayed (no Python tracing, no codegen)
            try:
                ray_weight, image, r, n_ok, zero, guide = self._frozen_pass(dr.opaque(mi.UInt32, seed), *args, None)
                dr.eval(image, r, zero if zero is not None else ())
            except Exception as error:  # noqa: BLE001 - fall back, loudly, as torchir's frozen renders do
                self.freeze = freeze = False
                warnings.warn(f"frozen ReSTIR pass failed ({error!r}); this integrator now runs unfrozen", stacklevel=2)
        if freeze:
            stats.timings = {"pass": _tic() - t0}
            self._neighbour_search.last = (None if source == "none" else "reprojected" if reproject
                                           else "lane" if keep_offsets and self.lane_chains else "screen")
        else:
            timings: dict[str, float] = {}
            # an opaque seed, as the frozen pass gets: a literal one compiles new kernels every
            # step wherever the seed enters a kernel (the offsets' redraw hash did: 2 s a step)
            ray_weight, image, r, n_ok, zero, guide = self._pass(dr.opaque(mi.UInt32, seed), *args, timings)
            stats.timings = timings
        stats.zero, stats.guide = zero, guide
        if source != "none":
            stats.neighbor_count = n_ok
        self.last_pass_frozen = freeze
        return (ray_weight, image), r, stats

    def _frozen_pass_ready(self, scene: mi.Scene, now: tuple) -> bool:
        """Whether the frozen pass may run now, with the scene's geometry ``now`` (GeometryWatch). A replay reuses the acceleration structure it
        was recorded with, so once geometry changes (a mesh's vertices, a shape's transform)
        the steps run unfrozen; after a step with unchanged geometry the pass is recorded
        anew. Vertices bound by each render (shape optimisation) are a new variable every
        step, so such runs stay unfrozen. (Measured: a frozen pass replayed after a vertex
        edit rendered 0.)"""
        steady = self._geometry_seen is None or now == self._geometry_seen
        self._geometry_seen = now
        if self._frozen_pass is not None and now == self._geometry_frozen:
            return True
        self._frozen_pass = None  # recorded against an acceleration structure that is gone
        if not steady:
            return False
        # one recording per sensor and pass kind (fresh RIS, reuse) is expected
        recordings = backend.frozen_recordings(len(scene.sensors()))
        self._frozen_pass, self._geometry_frozen = guarded_freeze(self._pass, warn_after=recordings), now
        return True

    def _pass(self, seed, scene, sensor, spp, prev, radius, source, k, layout, zero_remainder, buckets, keep_offsets,
              candidates, m_cap, guide, timings):
        """The resampling pass on Dr.Jit values only (so it can be frozen): camera rays,
        streaming RIS, the neighbour search (``screen`` when frozen) and the combination.
        ``keep_offsets``: ``prev`` has this pass's lanes; each lane keeps its camera offset, so
        its shading point, unless redrawn (probability 1 / ``offset_lifetime``), and with
        temporal reuse alone combines with its own previous reservoir (a redrawn lane starts
        afresh). ``guide``: the lanes' light guides (``light_guide``; None: none), learned on.
        ``timings`` (a dict, or None when frozen): seconds per stage, measured with syncs."""

        def tic(name=None, since=None):
            if timings is None:
                return 0.0
            now = _tic()
            if name is not None:
                timings[name] = now - since
            return now

        t0 = tic()
        sensor_obj = scene.sensors()[sensor]
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        n = w * h * spp
        sampler = sensor_obj.sampler().fork()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, n)
        lane = dr.arange(mi.UInt32, n)
        redrawn = None
        if keep_offsets:
            # redrawn independently of the offset and its hit (else offsets would drift towards
            # hits); NaN: no offset stored (an older checkpoint)
            stored = dr.isfinite(prev.offset.x)
            keep = stored
            if math.isfinite(self.offset_lifetime):
                redrawn = RedrawnLanes(n, self.offset_lifetime, seed)
                redrawn_here = redrawn.mask(lane)
                keep = stored & ~redrawn_here
            ray, ray_weight, offset = _sample_rays(sensor_obj, sampler, spp, w, h, prev.offset, keep)
        else:
            ray, ray_weight, offset = _sample_rays(sensor_obj, sampler, spp, w, h)
        pi = scene.ray_intersect_preliminary(mi.Ray3f(ray), coherent=True)
        si = pi.compute_surface_interaction(mi.Ray3f(ray), FORWARD_FLAGS)
        valid = si.is_valid()
        le_vis = si.emitter(scene).eval(si, valid)

        draws = None
        if guide is not None:  # a lane's guide is for its shading point: a redrawn offset forgets it
            draws = _light_guide.GuideDraws(_light_guide.forget(guide, keep) if keep_offsets else guide, self.light_guide)
        # Streaming RIS over light candidates (Alg. A1; paper Eq. 4-6)
        # a burn-in's guided pass (kept offsets, its own count) draws from what its first pass
        # learned, without learning on (the scatters would triple its cost)
        learn = not keep_offsets or candidates == self.candidates
        y, f_sel, phat_sel, w_sum, zero = self._streaming_ris(scene, si, sampler, valid, n, zero_remainder, candidates,
                                                              guide=draws, learn=learn)
        m_fresh = dr.opaque(mi.Float, candidates)  # as the loop's count: one kernel for every count
        if (redrawn is not None and self.lane_chains and self.burn_in > 0 and self.young_lane_burn_in
                and candidates == self.candidates):
            # A redrawn lane starts a new chain at a new point: with this step's candidates only, its
            # estimate is far noisier than its kept neighbours' for as long as its chain is young
            # (measured on ajar_painting, 128², burn-in 512: such lanes, 1 / offset_lifetime of
            # them a step, raised the gradient error from 0.0072 to 0.0098 within 32 steps). So
            # it continues this step's RIS over the burn-in's count of candidates: same point,
            # same candidate density, plain RIS over more candidates (a burn-in pass has that
            # many of its own). Spread over helper streams (see _young_continuation).
            young = valid & redrawn_here & stored
            y2, f2, phat2, w_sum2, m2 = self._young_continuation(scene, sensor_obj, seed, ray, pi, young, redrawn,
                                                                 self.burn_in * self.candidates)
            take = young & (sampler.next_1d(young) * (w_sum + w_sum2) < w_sum2)
            y, f_sel, phat_sel = dr.select(take, y2, y), dr.select(take, f2, f_sel), dr.select(take, phat2, phat_sel)
            w_sum = w_sum + dr.select(young, w_sum2, 0.0)
            m_fresh = dr.select(young, mi.Float(candidates + m2), m_fresh)
        if not self.shadowed:  # one shadow ray for the chosen candidate; W = 0 when occluded
            seen = _visible(scene, si, y, valid & (phat_sel > 0))
            w_sum, f_sel = dr.select(seen, w_sum, 0.0), dr.select(seen, f_sel, 0.0)
        r = fresh_reservoirs(ray, pi, si, valid, y, w_sum, phat_sel, m_fresh, offset)
        # with the guides' learned light: evaluated later, it would draw every candidate again
        # in a kernel of its own (measured: 8 of a guided pass's 23 ms)
        dr.eval(r, f_sel, phat_sel, le_vis, ray_weight, draws.learned if draws is not None else ())
        t1 = tic("ris", t0)

        n_ok, cap = None, m_cap
        if source != "none":
            src = prev if source == "temporal" else r
            exclude_self = source == "spatial"
            # opaque: each sensor state's automatic radius differs (its footprints, its first seed),
            # and as a literal it compiled these kernels again for every view and every new state
            radius_v = dr.opaque(mi.Float, radius)
            # screen window per query: ceil(radius / its pixel footprint), at most layout.window
            footprint = pi.t * dr.norm(ray.d_x - ray.d)
            windows = mi.UInt32(dr.clip(dr.ceil(radius_v / dr.select(footprint > 0, footprint, radius_v)), 1, 3))
            own_chain = keep_offsets and self.lane_chains
            if own_chain:  # the lane's own chain (a search could pick a neighbour's)
                d = src.p - r.p
                # a redrawn lane starts afresh: reused at its new shading point, a long memory
                # counts in Z (R8) where its sample is hidden, darkening or brightening the lane for
                # many steps (measured: worse than a fresh start)
                nbr, ok = [lane], [keep & r.valid & src.valid & (dr.dot(d, d) < radius_v * radius_v)]
                cap = self.chain_cap
                self._neighbour_search.last = "lane"
            elif buckets is not None:  # the store (multiview="carry_over"): reprojected to this film
                nbr, ok = _knn.knn_in_buckets(src.p, buckets, r.p, w, h, spp, k, radius, windows)
                ok = [o & r.valid for o in ok]
                self._neighbour_search.last = "reprojected"
            elif timings is None:  # frozen: the screen search (pure Dr.Jit, no host copies)
                nbr, ok = _knn.knn_screen(src.p, src.valid, r.p, layout, k, radius, exclude_self, windows)
                ok = [o & r.valid for o in ok]
            else:
                nbr, ok = self._neighbour_search(src.p, src.valid, r.p, r.valid, k, radius,
                                                 exclude_self=exclude_self, layout=layout, windows=windows)
            ok = self.normal_test(src, nbr, ok, r.n)
            dr.eval(nbr, ok)
            t2 = tic("nn", t1)
            same_point = own_chain and self.shadowed and self.same_point_visibility
            r, f_sel, phat_sel, n_ok = self._combine(scene, sampler, si, r, f_sel, phat_sel, src, nbr, ok, cap, same_point)
            dr.eval(r, f_sel, n_ok)
            t1 = tic("combine", t2)
        contrib = ray_weight * (le_vis + f_sel * r.W)  # (R16)
        image = develop(contrib, spp, h, w)
        guide = None if draws is None else draws.learned
        dr.eval(image, zero if zero is not None else (), guide if guide is not None else ())
        tic("develop", t1)
        return ray_weight, image, r, n_ok, zero, guide

    def _young_continuation(self, scene, sensor_obj, seed, ray, pi, young: mi.Bool, redrawn: "RedrawnLanes",
                            extra: int):
        """``(y, f, p̂, w_sum, M)`` (lane-wide; 0 but where ``young``) of plain streaming RIS over
        about ``extra`` candidates (``M`` of them) at the first hits ``pi`` of the camera rays
        ``ray`` of the redrawn lanes ``young``.

        Why helpers: looping ``extra`` times in the redrawn lanes alone (8 of 16 384 a step at
        lifetime 2 048) keeps one core's SIMD packets busy with one live lane each: at
        ``extra = 32 768`` that cost 0.15 s a step, 3x the rest of a guided pass (ajar_painting,
        128²). Instead ``P`` helper streams per redrawn lane each run ``c`` candidates at its
        shading point (``P c >= extra``, about one helper per lane of the pass), and one of
        them is chosen in proportion to its ``w_sum`` (exactly streaming RIS over all ``P c``
        candidates: they are i.i.d.). The lanes' light guides were emptied where redrawn, so
        the candidates are plain ones; the guides learn at the next steps."""
        n = dr.width(young)
        slots = redrawn.slots
        per_helper = max(1, math.ceil(extra * slots / n))
        helpers_per_slot = math.ceil(extra / per_helper)
        width = slots * helpers_per_slot
        helper = dr.arange(mi.UInt32, width)
        slot = helper // helpers_per_slot
        target = redrawn.lane_of(slot)
        ray, pi = mi.Ray3f(ray), mi.PreliminaryIntersection3f(pi)
        dr.eval(ray, pi, young)  # one kernel (gathered from unevaluated, each field is one)
        active = dr.gather(mi.Bool, young, target, redrawn.active(slot))
        ray_h = dr.gather(mi.Ray3f, ray, target, active)
        si_h = dr.gather(mi.PreliminaryIntersection3f, pi, target, active).compute_surface_interaction(
            ray_h, FORWARD_FLAGS, active)
        sampler = sensor_obj.sampler().fork()
        sampler.set_sample_count(1)
        sampler.set_samples_per_wavefront(1)
        sampler.seed(seed ^ 0x9E3779B9, width)
        y, f, phat, w_sum, _ = self._streaming_ris(scene, si_h, sampler, active, width, False, per_helper)
        dr.eval(y, f, phat, w_sum)
        # choose one helper per slot in proportion to its w_sum: the helper whose interval
        # [running sum - w_sum, running sum) holds u * total (the last one with mass also takes
        # the total itself, should rounding put u * total there)
        below_and_own = dr.block_prefix_sum(w_sum, helpers_per_slot, exclusive=False)
        total = dr.gather(mi.Float, below_and_own, slot * helpers_per_slot + helpers_per_slot - 1)
        t = mi.sample_tea_float32(slot, seed ^ 0x7A3C1E55) * total
        chosen = active & (w_sum > 0) & (below_and_own - w_sum <= t) & ((t < below_and_own) | (below_and_own >= total))
        y_out, f_out = dr.zeros(LightSample(), n), dr.zeros(mi.Color3f, n)
        phat_out, w_out = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        dr.scatter(y_out, y, target, chosen)
        dr.scatter(f_out, f, target, chosen)
        dr.scatter(phat_out, phat, target, chosen)
        dr.scatter(w_out, total, target, chosen)  # where no helper has mass: w_sum 0, no sample
        return y_out, f_out, phat_out, w_out, helpers_per_slot * per_helper

    def _streaming_ris(self, scene, si, sampler, valid, n: int, zero_remainder: bool, candidates: int,
                       unroll: bool | None = None, guide: _light_guide.GuideDraws | None = None, learn: bool = True):
        """``(y, f, p̂, w_sum, (y0, w0))`` of streaming RIS over ``candidates`` light candidates
        (Alg. A1), with ``y0`` the first candidate whose ``p̂`` is 0 and ``w0 = n0 / (M p_c(y0))``
        (0 where none, or where ``y0`` is occluded): the gradient's ``p̂ = 0`` remainder (None
        without ``zero_remainder``). ``guide``: candidates partly from the lanes' light guides,
        which learn from them unless not ``learn`` (``guide.finish`` is called): from all of a
        symbolic loop's, from the first ``GUIDE_LEARNING_PER_STEP`` of an unrolled one (the
        learning's scatters cost more than the draws: 3x a usual candidate in a loop, against
        1.3x without learning).
        Up to ``UNROLLED_CANDIDATES`` the loop is unrolled into the kernel where that pays: with
        guides, or beyond ``SYMBOLIC_UP_TO_LANES`` lanes (``unroll`` forces either way); else a
        symbolic loop keeps the kernel small (1024 unrolled candidates took minutes to compile;
        16 compile in twice a loop's time). Both draw the same random numbers."""
        y, y0 = dr.zeros(LightSample(), n), dr.zeros(LightSample(), n)
        f_sel, phat_sel = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)
        w_sum, inv_pc0, n0 = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        # continues what an earlier stream of this pass learned (its light)
        light_of_lane = mi.UInt32(guide.learned.light) if guide is not None else mi.UInt32(_light_guide.NO_LIGHT)

        def candidate(y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane, learn_here=True):
            y_m, f_m, phat_m, w_m, inv_pc, *u = sample_candidate(scene, si, sampler, valid, visibility=self.shadowed,
                                                                 with_inv_pc=True, guide=guide)
            if guide is not None and learn and learn_here:
                light_of_lane = guide.learn(light_of_lane, y_m.em, u[0], w_m, ~y_m.delta, valid)
            w_sum = w_sum + w_m
            take = valid & (sampler.next_1d(valid) * w_sum < w_m)  # no division (A1)
            zero = valid & (inv_pc > 0) & (phat_m == 0) if zero_remainder else mi.Bool(False)
            first = zero & (n0 == 0)
            return (dr.select(take, y_m, y), dr.select(take, f_m, f_sel), dr.select(take, phat_m, phat_sel), w_sum,
                    dr.select(first, y_m, y0), dr.select(first, inv_pc, inv_pc0), dr.select(zero, n0 + 1.0, n0),
                    light_of_lane)

        state = (y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane)
        if unroll is None:
            unroll = candidates <= UNROLLED_CANDIDATES and (n > SYMBOLIC_UP_TO_LANES or guide is not None)
        if unroll:
            for i in range(candidates):  # a step's guides learn from a few (their scatters cost)
                state = candidate(*state, learn_here=i < GUIDE_LEARNING_PER_STEP)
        else:
            def body(i, sampler_, *rest):
                return (i + 1, sampler_, *candidate(*rest))

            # lanes without a shading point, or not asked for, exit at once; an opaque count: one
            # kernel for every number of candidates (a burn-in pass, a step, another sampler)
            count = dr.select(valid, dr.opaque(mi.UInt32, candidates), 0)
            _, _, *state = dr.while_loop(
                (dr.zeros(mi.UInt32, n), sampler, *state), lambda i, *rest: i < count, body,
                labels=("i", "sampler", "y", "f", "phat", "w_sum", "y0", "inv_pc0", "n0", "light"),
            )
        y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane = state
        if guide is not None:
            guide.finish(light_of_lane)
        if not zero_remainder:
            return y, f_sel, phat_sel, w_sum, None
        w0 = n0 * inv_pc0 / dr.opaque(mi.Float, candidates)
        w0 = dr.select(_visible(scene, si, y0, valid & (w0 > 0)), w0, 0.0)  # V = 0: no gradient
        return y, f_sel, phat_sel, w_sum, (y0, w0)

    def normal_test(self, source, nbr: list, ok: list, n: mi.Vector3f) -> list:
        """``ok`` without the neighbours ``source[nbr]`` whose normal is off the query normal
        ``n`` by more than ``normal_threshold`` (spec §3.6)."""
        return [o & (dr.dot(dr.gather(mi.Vector3f, source.n, j, o), n) >= self.normal_threshold) for j, o in zip(nbr, ok)]

    def _combine(self, scene, sampler, si, r, f_sel, phat_sel, source, nbr, ok, m_cap: float, same_point: bool = False):
        """Bitterli's unbiased 1/Z combination with M capping at ``m_cap`` (R6-R9; corrects
        Alg. P3, D1). ``same_point``: each neighbour is the lane's own previous reservoir at the
        same shading point in the same geometry (kept offsets), with the shadowed target: its
        sample, if ``W > 0``, was visible from this very point, so neither its shadow ray nor
        the rebuilt point of the support test is traced again (the same answers, 2 rays fewer)."""
        valid = r.valid  # si: the lanes' own shading points (the pass's first hits)
        cap = dr.opaque(mi.Float, m_cap)  # a literal compiled again for every cap (moving geometry lowers it)
        # w_0 = p̂(y_0) W_0 M_0 (R6): r_0.w_sum for a fresh RIS reservoir, and also right for an
        # already combined one, whose w_sum is not M p̂ W (measured: reusing w_sum there made W
        # grow without bound)
        y, m_sum = r.y, mi.Float(r.M)
        w_sum = phat_sel * r.W * m_sum
        neighbours, m_caps = [], []
        n_ok = dr.zeros(mi.UInt32, dr.width(valid))
        from_neighbour = dr.zeros(mi.Bool, dr.width(valid))
        for j, ok_i in zip(nbr, ok):
            ok_i = ok_i & valid
            r_i = dr.gather(Reservoirs(), source, j, ok_i)
            ok_i &= r_i.valid
            m_i = dr.minimum(r_i.M, cap)
            f_i, phat_i = eval_target(scene, si, r_i.y, ok_i & (r_i.W > 0), visibility=self.shadowed and not same_point)
            w_i = phat_i * r_i.W * m_i  # (R6)
            w_sum += w_i
            take = ok_i & (sampler.next_1d(valid) * w_sum < w_i)  # (R7)
            y = dr.select(take, r_i.y, y)
            f_sel, phat_sel = dr.select(take, f_i, f_sel), dr.select(take, phat_i, phat_sel)
            from_neighbour |= take
            m_sum += dr.select(ok_i, m_i, 0.0)
            neighbours.append((r_i, ok_i))
            m_caps.append(m_i)
            n_ok += dr.select(ok_i, 1, 0)
        if not self.shadowed:  # the chosen neighbour sample must be visible here (else W = 0)
            seen = ~from_neighbour | _visible(scene, si, y, from_neighbour & (phat_sel > 0))
            f_sel, phat_sel = dr.select(seen, f_sel, 0.0), dr.select(seen, phat_sel, 0.0)
        # Support test: a neighbour counts where its reservoirs could hold y. Reservoirs hold
        # visible samples only (shadowed target, or W = 0 when occluded), so V is tested too.
        z = mi.Float(r.M)  # the fresh reservoir always counts (R8)
        for (r_i, ok_i), m_i in zip(neighbours, m_caps):
            if same_point:  # the neighbour's point is this one: p̂ there is phat_sel (visibility included)
                z += dr.select(ok_i & (phat_sel > 0), m_i, 0.0)
                continue
            si_i = rebuild_interaction(scene, r_i, ok_i, FORWARD_FLAGS)  # the neighbour's surface point (§6.2)
            _, phat_at_i = eval_target(scene, si_i, y, ok_i & (phat_sel > 0))
            z += dr.select(ok_i & (phat_at_i > 0), m_i, 0.0)
        good = (phat_sel > 0) & (z > 0)
        out = copy.copy(r)  # shallow: new attributes, the fresh reservoirs stay intact
        out.y, out.w_sum = y, w_sum
        out.W = dr.select(good, w_sum / dr.select(good, phat_sel * z, 1.0), 0.0)  # (R9)
        out.M = dr.minimum(m_sum, cap)
        return out, f_sel, phat_sel, n_ok

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

        Interior term (R17, R18) on the step's paths (``shared``) or on a second resampling
        pass (``decorrelated``, ``forward_only``). ``geometry`` (stage v2, shape parameters):
        the shading point follows the camera ray (attached re-intersection), and the
        visibility-boundary terms are added without reuse (:meth:`_boundary_backward`);
        ``params`` are the grad-enabled values they differentiate.
        """
        t0 = _tic()
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
            if geometry:  # ray-following shading point, as direct_projective (spec §6.7)
                si = scene.ray_intersect(mi.Ray3f(lanes.o, lanes.d), mi.RayFlags.All, True, lanes.valid)
            else:  # material point rebuilt from (shape, prim, prim_uv): exact, no BVH traversal
                si = rebuild_interaction(scene, lanes, lanes.valid)
            f, _ = eval_target(scene, si, lanes.y, lanes.valid & (lanes.W > 0), visibility=False)
            le = si.emitter(scene).eval(si, lanes.valid)
            contrib = ray_weight * (le + f * lanes.W)  # W detached (R18)
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
        self.timings["backward"] = _tic() - t0

    def _boundary_backward(self, scene: mi.Scene, params: Any, grad_in: mi.TensorXf, sensor: int, seed: int, spp: int) -> None:
        """The visibility-boundary terms. Shadow edges of the differentiated meshes, where
        :func:`_shadow_edges.supported` (area lights, a perspective sensor), come from edge
        samples on those meshes alone (``spp`` per pixel, guided by the earlier steps' samples
        unless ``edge_guiding`` is off, and with ``edge_temporal`` and temporal reuse each
        sample resampled against the one it kept at the last step, the chain's confidence capped at
        ``edge_chain_cap``, or ``moving_geometry_m_cap`` after the mesh moved; ``"auto"``: see
        :meth:`edge_strategy`); with ``silhouette_sampling``, where
        :func:`_silhouettes.supported` (also a box filter), the primary silhouettes likewise
        (``silhouette_candidates`` RIS light candidates either side, no reuse), and with
        ``shading_bands`` the shading-horizon curves of smooth meshes (:mod:`._shading_bands`;
        the silhouettes' insides are then shaded as the camera sees them); the rest from
        ``direct_projective``. The guides and the edge chains are not saved in checkpoints:
        after a resume they start afresh (the chains' first step is without reuse)."""
        meshes = _differentiated_meshes(scene, params)
        sensor_obj = scene.sensors()[sensor]
        edges = self.shadow_edge_sampling and _shadow_edges.supported(scene, sensor_obj, meshes)
        bands = self.uses_shading_bands(meshes) and _shading_bands.supported(scene, sensor_obj, meshes)  # see _band_objective
        silhouettes = (bands or self.uses_silhouette_sampling(meshes)) and _silhouettes.supported(scene, sensor_obj, meshes)
        if not (edges and silhouettes):
            # Mitsuba's edges come from vertex indices: on meshes that repeat positions (uv seams,
            # flat shading) its pass runs on welded faces (torchir.welding)
            with WeldedFaces(self._traversed(scene), moving_meshes(scene, params)):
                self.boundary_integrator(secondary=not edges, primary=not silhouettes).render_backward(
                    scene, params, grad_in, sensor, seed, spp)
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        if silhouettes:
            _silhouettes.silhouette_backward(self, scene, sensor, grad_in, meshes, spp * w * h, int(mi.sample_tea_32(seed, 11)[0]),
                                             candidates=self.silhouette_candidates, grazing=bands)
        if edges:
            reuse, guided = self.edge_strategy(scene, meshes, spp * w * h)
            guides = self._edge_guides if guided else None
            chains = self._edge_chains.setdefault(sensor, {}) if reuse else None  # per sensor: its own adjoint
            _shadow_edges.shadow_edge_backward(scene, sensor, grad_in, meshes, spp * w * h, int(mi.sample_tea_32(seed, 7)[0]), guides,
                                               self.edge_light_candidates, self.edge_candidates, chains, self.edge_chain_cap,
                                               self.moving_geometry_m_cap if self.moving_geometry_m_cap > 0 else self.edge_chain_cap)

    def _band_objective(self, scene: mi.Scene, params: Any, grad_in: mi.TensorXf, sensor: int, seed: int,
                        spp: int) -> mi.Float | None:
        """The shading-horizon term of the differentiated smooth meshes (``shading_bands``,
        where :func:`_shading_bands.supported`; ``spp`` image lines a pixel) as an objective that
        the interior term's backward pass carries: both reach the vertices through the normals
        computed from them, an edge of the graph that Dr.Jit's default flags delete after one
        pass (:func:`_shading_bands.band_objective`). None where it does not apply."""
        meshes = _differentiated_meshes(scene, params)
        sensor_obj = scene.sensors()[sensor]
        if not self.uses_shading_bands(meshes):
            return None
        if not _shading_bands.supported(scene, sensor_obj, meshes):
            if not self._band_warned:
                self._band_warned = True
                warnings.warn("a moving smooth-shaded mesh: the shading-horizon term needs a pinhole camera with a box "
                              "filter ('rfilter': {'type': 'box'}) and no crop window; without it a vertex beside a "
                              "silhouette gets Mitsuba's biased derivative (see torchir.integrators._shading_bands)",
                              stacklevel=2)
            return None
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        return _shading_bands.band_objective(self, scene, sensor, grad_in, meshes, spp * w * h,
                                             int(mi.sample_tea_32(seed, 13)[0]), candidates=self.silhouette_candidates)

    def uses_silhouette_sampling(self, meshes: list) -> bool:
        """Whether torchir samples the primary silhouettes of ``meshes`` itself (``silhouette_sampling``;
        ``"auto"``: where one is flat-shaded or has an open border, which Mitsuba's estimator gets
        wrong (:func:`mitsuba_silhouettes_wrong`); elsewhere Mitsuba's is right and cheaper)."""
        if self.silhouette_sampling == "auto":
            return any(mitsuba_silhouettes_wrong(m) for m in meshes)
        if not isinstance(self.silhouette_sampling, (bool, np.bool_)):
            raise ValueError(f"silhouette_sampling must be True, False or 'auto', got {self.silhouette_sampling!r}")
        return bool(self.silhouette_sampling)

    def uses_shading_bands(self, meshes: list) -> bool:
        """Whether the shading-horizon term of smooth meshes is added (``shading_bands``;
        ``"auto"``: where a moving mesh is shaded with interpolated vertex normals, whose band
        along the silhouettes moves as they turn: :mod:`._shading_bands`)."""
        if self.shading_bands == "auto":
            return any(_shading_bands.smooth_shaded(m) for m in meshes)
        if not isinstance(self.shading_bands, (bool, np.bool_)):
            raise ValueError(f"shading_bands must be True, False or 'auto', got {self.shading_bands!r}")
        return bool(self.shading_bands)

    def _traversed(self, scene: mi.Scene) -> Any:
        """``mi.traverse(scene)``, kept for the last scene (traversing costs a walk of the scene)."""
        if self._scene_params is None or self._scene_params[0] is not scene:
            self._scene_params = (scene, mi.traverse(scene))
        return self._scene_params[1]

    def edge_strategy(self, scene: mi.Scene, meshes: list, samples: int) -> tuple[bool, bool]:
        """(edge chains, guide) for a step's ``samples`` shadow-edge samples on ``meshes``.

        ``edge_temporal`` / ``edge_guiding`` set them; ``"auto"`` decides by how many (edge,
        light) pairs the step's samples must cover. With few (at most ``EDGE_PAIRS_PER_SAMPLE``
        per sample), the guide learns the pairs on the shadow's outline and fresh guided samples
        are best; with many, it cannot, and chains drawn by length, which keep the outline
        samples they find, are best. Measured through Adam's average (the variance of its first
        moment, beta 0.9; ``occluded_lights``' crown, 64², the pose moving 0.5 degrees a step,
        96-400 steps): at 24 rings (6 600 pairs, 4 096 samples) guided without chains 2.4-3.5x
        below guided chains and 7x below by length; at 48 rings (6.6 pairs a sample) chains by
        length 3.4x below guided samples without chains; at 144 rings (247 000 pairs) chains by
        length 3.5x below by length alone and 7x below guided chains (the guide raised
        by-length's variance 3.5x). Chains also need temporal reuse and not ``forward_only``."""
        for name in ("edge_temporal", "edge_guiding"):
            value = getattr(self, name)
            if not (value == "auto" or isinstance(value, (bool, np.bool_))):
                raise ValueError(f"{name} must be True, False or 'auto', got {value!r}")
        pairs = sum(len(edges_of(m).a) for m in meshes) * len(scene.emitters())
        many = pairs > EDGE_PAIRS_PER_SAMPLE * samples
        chains = many if self.edge_temporal == "auto" else bool(self.edge_temporal)
        guided = (not many) if self.edge_guiding == "auto" else bool(self.edge_guiding)
        return chains and self.can_chain_edges(), guided

    def can_chain_edges(self) -> bool:
        """Whether shadow-edge samples may be kept across steps at all: with temporal reuse, not
        in ``forward_only`` mode (``edge_strategy`` then decides where they are)."""
        return self.temporal and not self.forward_only

    def boundary_integrator(self, secondary: bool = True, primary: bool = True) -> mi.Integrator:
        """Mitsuba's ``direct_projective`` restricted to its boundary terms (``sppc=0``; with
        ``secondary=False`` without the secondary ones, ``sppi=0``; with ``primary=False``
        without the primary ones, ``sppp=0``), without guiding: on
        ``occluded_lights`` (64², the blocker's shadow) the default octree guiding took 5.7 s a
        step against 0.06 s, for the same error x time (relative variance x seconds 0.48
        against 0.42) and the same mean."""
        if (secondary, primary) not in self._boundary_integrators:
            options = {"type": "direct_projective", "sppc": 0, "guiding": "none"}
            if not secondary:
                options["sppi"] = 0
            if not primary:
                options["sppp"] = 0
            self._boundary_integrators[secondary, primary] = mi.load_dict(options)
        return self._boundary_integrators[secondary, primary]

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        out = {sensor: _chain_to_dict(st) for sensor, st in self.states.items()}
        for sensor, st in self.grad_states.items():  # the gradient's chain beside the image's
            out.setdefault(sensor, {})["grad_chain"] = _chain_to_dict(st)
        return out

    def load_state_dict(self, state: dict) -> None:
        self.reset()
        for sensor, d in state.items():
            if "reservoirs" in d:
                self.states[int(sensor)] = _chain_from_dict(d)
            if d.get("grad_chain") is not None:
                self.grad_states[int(sensor)] = _chain_from_dict(d["grad_chain"])

    def to_string(self) -> str:
        return (
            f"ReSTIRDirectIntegrator[candidates={self.candidates}, neighbors={self.neighbors}, "
            f"temporal={self.temporal}, spatial={self.spatial}, grad_paths={self.grad_paths!r}]"
        )


# ---------------------------------------------------------------------- helpers
def project(sensor_obj: mi.Sensor, r) -> tuple[mi.Bool, mi.UInt32]:
    """``(inside, pixel)`` of reservoirs ``r`` in a sensor's film: ``inside`` where the shading
    point projects into the film and faces the camera (its side of the surface: a two-sided
    sheet seen from behind is another reservoir's), ``pixel`` its row-major pixel index."""
    w, h = (int(v) for v in sensor_obj.film().crop_size())
    it = dr.zeros(mi.SurfaceInteraction3f, dr.width(r.valid))
    it.p, it.n = r.p, r.n
    ds, _ = sensor_obj.sample_direction(it, mi.Point2f(0.5), r.valid)
    inside = r.valid & (ds.pdf > 0) & (ds.uv.x >= 0) & (ds.uv.x < w) & (ds.uv.y >= 0) & (ds.uv.y < h)
    inside &= dr.dot(r.n, ds.d) > 0
    pixel = mi.UInt32(dr.clip(mi.Int32(ds.uv.y), 0, h - 1)) * w + mi.UInt32(dr.clip(mi.Int32(ds.uv.x), 0, w - 1))
    return inside, pixel


def seen_by(scene: mi.Scene, sensor: int, r) -> mi.Bool:
    """Which reservoirs ``r`` sensor ``sensor`` sees: they project into its film facing it
    (:func:`project`) and nothing lies between them and the camera (one shadow ray each)."""
    sensor_obj = scene.sensors()[sensor]
    inside, _ = project(sensor_obj, r)
    it = dr.zeros(mi.SurfaceInteraction3f, dr.width(r.valid))
    it.p, it.n = r.p, r.n
    ds, _ = sensor_obj.sample_direction(it, mi.Point2f(0.5), inside)
    return inside & ~scene.ray_test(it.spawn_ray_to(ds.p), inside)


def carry_over(scene: mi.Scene, sensor: int, new, store):
    """Alg. A8's store after sensor ``sensor`` rendered reservoirs ``new``: ``new`` plus the
    valid reservoirs of ``store`` that the sensor does not see (other views' surfaces, or
    surfaces hidden from this view); the ones it sees are replaced by ``new``."""
    if store is None:
        return new
    keep = dr.compress(store.valid & ~seen_by(scene, sensor, store))
    carried = dr.gather(Reservoirs(), store, keep)
    n_new, n_old = dr.width(new.valid), dr.width(keep)
    merged = dr.zeros(Reservoirs(), n_new + n_old)
    dr.scatter(merged, new, dr.arange(mi.UInt32, n_new))
    if n_old:
        dr.scatter(merged, carried, n_new + dr.arange(mi.UInt32, n_old))
    dr.eval(merged)
    return merged


def _visible(scene: mi.Scene, si: mi.SurfaceInteraction3f, y, active: mi.Bool) -> mi.Bool:
    """True where light vertex ``y`` is unoccluded from ``si`` (False where inactive)."""
    return active & ~scene.ray_test(si.spawn_ray_to(y.p), active)


def _chain_to_dict(st: SensorState) -> dict:
    return {
        "radius": st.radius,
        "window": st.window,
        "steps": st.steps,
        "signature": st.signature,
        "camera": st.camera,
        "lights": st.lights,
        "reservoirs": None if st.prev is None else _struct_to_numpy(st.prev),
        "guide": None if st.guide is None else _struct_to_numpy(st.guide),
    }


def _chain_from_dict(d: dict) -> SensorState:
    data = d["reservoirs"]
    if data is not None and "offset" not in data:  # older checkpoints: offsets are redrawn
        data = {**data, "offset": np.full((len(data["W"]), 2), np.nan, np.float32)}
    camera = d.get("camera")  # absent in older checkpoints: the first step searches in world space
    return SensorState(
        prev=None if data is None else _struct_from_numpy(Reservoirs(), data), radius=float(d["radius"]),
        window=int(d.get("window", 2)), steps=int(d["steps"]), signature=tuple(d["signature"]),
        camera=None if camera is None else (tuple(camera[0]), *(int(v) for v in camera[1:])),
        lights=as_tuples(d.get("lights")),  # absent: the first step does not reuse
        geometry=LOADED,
        # absent (older checkpoints): relearned
        guide=None if d.get("guide") is None else _struct_from_numpy(_light_guide.LightGuide, d["guide"]),
    )


def _chain(states: dict[int, SensorState], scene: mi.Scene, sensor: int) -> SensorState:
    sig = _signature(scene)
    st = states.get(sensor)
    if st is None or st.signature != sig:
        st = states[sensor] = SensorState(signature=sig)
    return st


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


class RedrawnLanes:
    """Which of a pass's ``n`` lanes redraw their camera offset this step: ``n / lifetime`` of
    them on average, chosen by the seed alone (never by their offsets or hits), so each lane
    is redrawn with probability ``1 / lifetime``. Exactly ``floor(n / lifetime)`` or one more
    lanes, evenly strided from a random start: a fixed count of slots, so the redrawn lanes'
    work has a fixed shape (frozen passes; see ``_young_continuation``)."""

    def __init__(self, n: int, lifetime: float, seed: mi.UInt32) -> None:
        expected = n / lifetime
        self.n, self.slots = n, max(1, math.ceil(expected))
        self.stride = n // self.slots
        whole = math.floor(expected)
        self.count = whole + mi.UInt32(mi.sample_tea_float32(seed, 0x0FF5E7D0) < expected - whole)
        self.start = mi.sample_tea_32(seed, 0x51EDB0A7)[0] % n

    def lane_of(self, slot: mi.UInt32) -> mi.UInt32:
        return (self.start + slot * self.stride) % self.n

    def active(self, slot: mi.UInt32) -> mi.Bool:
        return slot < self.count

    def mask(self, lane: mi.UInt32) -> mi.Bool:
        """Lane-wide: whether each lane is redrawn."""
        d = (lane + self.n - self.start) % self.n
        return (d % self.stride == 0) & self.active(d // self.stride)


def _sample_rays(sensor: mi.Sensor, sampler: mi.Sampler, spp: int, w: int, h: int, kept: mi.Point2f | None = None,
                 keep: mi.Bool | None = None):
    """``(rays, weights, offsets)``: camera rays, ``spp`` consecutive lanes per pixel, row-major
    (as Mitsuba's ``sample_rays`` with a box filter); ``offsets`` are their positions in the
    pixel, fresh from ``sampler`` except ``kept`` where ``keep``."""
    idx = dr.arange(mi.UInt32, w * h * spp) // spp
    pos = mi.Vector2u(idx % w, idx // w)
    offset = sampler.next_2d()
    if kept is not None:
        offset = dr.select(keep, kept, offset)
    # sample2 of sample_ray is relative to the film crop (as in Mitsuba's sample_rays)
    pos_adj = (mi.Vector2f(pos) + offset) * dr.rcp(mi.ScalarVector2f(w, h))
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    t = sensor.shutter_open()
    if sensor.shutter_open_time() > 0:
        t += sampler.next_1d() * sensor.shutter_open_time()
    ray, weight = sensor.sample_ray_differential(time=t, sample1=0.0, sample2=pos_adj, sample3=aperture)
    return ray, mi.Color3f(weight), offset


def _footprints(scene: mi.Scene, sensor: mi.Sensor, seed: int, spp: int, w: int, h: int) -> tuple[float, float]:
    """``(radius, small footprint)``: 2x the median pixel footprint ``t * |d_x - d|`` of the
    hit lanes (D3), and its 5th percentile (sizes the screen-space search window)."""
    with dr.suspend_grad():
        sampler = sensor.sampler().fork()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, w * h * spp)
        ray, _, _ = _sample_rays(sensor, sampler, spp, w, h)
        pi = scene.ray_intersect_preliminary(mi.Ray3f(ray), coherent=True)
        fp = pi.t * dr.norm(ray.d_x - ray.d)
        vals = np.asarray(dr.gather(mi.Float, fp, dr.compress(pi.is_valid() & dr.isfinite(fp))))
    vals = vals[vals > 0]
    if len(vals) == 0:
        return 1e-2, 5e-3
    return float(2.0 * np.median(vals)), float(np.percentile(vals, 5))


def _reservoir_stats(r, stats: PassStats) -> dict[str, float]:
    v = r.valid
    nv = int(dr.count(v)[0])
    if nv == 0:
        return {"mean_M": 0.0, "max_M": 0.0, "frac_W0": 0.0, "max_W": 0.0, "valid_neighbors": 0.0}
    valid_neighbors = 0.0
    if stats.neighbor_count is not None:
        valid_neighbors = float(dr.sum(stats.neighbor_count)[0]) / (stats.k * nv)
    m = dr.select(v, r.M, 0.0)
    wv = dr.select(v, r.W, 0.0)
    return {
        "mean_M": float(dr.sum(m)[0]) / nv,
        "max_M": float(dr.max(m)[0]),
        "frac_W0": float(dr.count(v & (r.W <= 0))[0]) / nv,
        "max_W": float(dr.max(wv)[0]),
        "valid_neighbors": float(valid_neighbors),
    }


def _leaves(struct_type, prefix=""):
    for name, tp in struct_type.DRJIT_STRUCT.items():
        if hasattr(tp, "DRJIT_STRUCT"):
            yield from _leaves(tp, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", tp


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, path: str, value) -> None:
    parts = path.split(".")
    for part in parts[:-1]:
        obj = getattr(obj, part)
    setattr(obj, parts[-1], value)


def _struct_to_numpy(s) -> dict[str, np.ndarray]:
    out = {}
    for path, tp in _leaves(type(s)):
        v = _get(s, path)
        out[path] = np.array(v, copy=True)
        if dr.size_v(tp) != dr.Dynamic and dr.size_v(tp) > 1:
            out[path] = np.stack([np.array(v[i], copy=True) for i in range(dr.size_v(tp))], 1)
    return out


def _struct_from_numpy(struct_type, data: dict[str, np.ndarray]):
    n = len(next(iter(data.values())))
    s = dr.zeros(struct_type, n)
    for path, tp in _leaves(struct_type):
        arr = data[path]
        if arr.ndim == 2:
            value = tp(*[dr.value_t(tp)(np.ascontiguousarray(arr[:, i])) for i in range(arr.shape[1])])
        else:
            value = tp(np.ascontiguousarray(arr))
        _set(s, path, value)
    dr.eval(s)
    return s


def _differentiated_meshes(scene: mi.Scene, params: Any) -> list:
    """The meshes whose vertex positions ``params`` differentiates; empty when other geometry
    moves too (a transform, a sphere's centre or radius), whose shadow edges only Mitsuba's
    estimator covers."""
    moving = [name for name, value in (params or {}).items() if dr.grad_enabled(value)]
    if any(is_geometry_key(name) and not name.endswith(".vertex_positions") for name in moving):
        return []
    names = {name[: -len(".vertex_positions")] for name in moving if name.endswith(".vertex_positions")}
    return [shape for shape in scene.shapes() if shape.id() in names]
