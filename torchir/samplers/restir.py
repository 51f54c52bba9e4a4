"""``ReSTIRSampler``: reservoirs reused across gradient steps (paper 004) for ``render``.

The sampler owns the per-sensor reservoir state and the Dr.Jit integrator that reads and
updates it; ``render(scene, params, spp, seed, sampler=r)`` then renders direct illumination
by ReSTIR and back-propagates its interior-term gradient (W constant, only ``Le * fs * g``
differentiated). Reservoirs are keyed by world-space shading points (shape, primitive,
barycentrics), so they survive parameter changes and every sensor keeps its own chain.

Presets (one flag for the paper's equal-time comparisons, spec §6.3):

=================  ====================================================================
``preset``         meaning
=================  ====================================================================
``"restir"``       the options as given (default: spatiotemporal reuse, decorrelated
                   gradient paths: see ``grad_paths``)
``"persistent"``   temporal reuse of each camera sample's own reservoir at a kept shading
                   point: ``spatial=False``, ``offset_lifetime=2048`` unless given, the
                   chain's M capped at 64 x ``candidates``, per-sensor chains. For
                   light-bound scenes whose texels span several pixels (each sample
                   point stays put for ~2048 steps)
``"b1"``           B.1: one light sample per camera ray, no reuse (``candidates=1``)
``"b2"``           B.2: streaming RIS with ``candidates``, no reuse
``"forward_only"`` ablation: reuse for the image, plain RIS for the gradient
=================  ====================================================================
"""
from __future__ import annotations

import copy
from typing import Any

from ..scene import Scene, is_geometry_key

__all__ = ["ReSTIRSampler"]

_PRESETS = ("restir", "persistent", "b1", "b2", "forward_only")
PERSISTENT_LIFETIME = 2048.0  # preset "persistent": mean steps a lane keeps its camera offset (512: 21 % more gradient error, scripts/sweep_restir.py)


class ReSTIRSampler:
    """ReSTIR reservoir state for one scene (all its sensors).

    Args:
        scene: a :class:`torchir.Scene` with direct illumination only (point, spot and area
            emitters, no media, box filter).
        candidates: M, light candidates per camera sample (streaming RIS).
        neighbors: k, reservoirs of the previous step combined per camera sample (8 and 16
            candidates: the lowest error x time of k in 2-16, M in 8-16 at 128², docs/restir-measurements.md).
        radius: neighbour search radius in world units (``None``: 2 pixel footprints).
        m_cap: cap on M (``None``: 2 * candidates for searched neighbours, 64 * candidates
            for a lane's own chain; spec D2's 20 * candidates measured worse with searched
            neighbours: a moved shading point can hide a long memory's sample, see
            ``integrators/restir_di.py`` and ``scripts/sweep_restir.py``).
        temporal, spatial: reuse switches (both: the paper's spatiotemporal reuse of the
            previous step; neither: plain RIS).
        burn_in: forward-only reuse passes before a sensor's first step (kept offsets without
            spatial reuse, e.g. ``preset="persistent"``: one pass over ``burn_in x candidates``).
        grad_paths: ``"decorrelated"`` (the default: a second resampling pass with
            ``seed_grad``/``spp_grad``, with temporal reuse a step of the gradient's own chain,
            which never reuses what the image reused) or ``"shared"``
            (the paper: the gradient re-evaluates the image's paths, so ``render``'s
            ``seed_grad``/``spp_grad`` are unused and the second pass is saved). Shared paths
            are unbiased only for a loss linear in the image: for L2,
            ``E[2 (I - T) dI] = 2 (E[I] - T) E[dI] + 2 Cov(I, dI)``, and the covariance term
            pulls the fit off the truth in proportion to the image's variance, which is largest
            where light sampling is hard (docs/restir.md, "Gradient paths"). Decorrelated paths remove
            that term for every preset (``tests/test_restir_grad_paths.py``); with reuse the
            gradient's chain burns in too, once, at the first backward.
        nn_backend: ``"auto"`` (timed) | ``"kdtree"`` (scipy) | ``"grid"`` (Dr.Jit) | ``"screen"``
            (the previous step's samples in the surrounding pixels; a sensor that has not moved).
        seed: mixed into every render seed (0: the render seed is used as is).
        normal_threshold: neighbours with ``n . n' <`` this are dropped.
        preset: ``"restir"`` | ``"persistent"`` | ``"b1"`` | ``"b2"`` | ``"forward_only"`` (table
            above).
        target: ``"shadowed"`` (p̂ includes visibility: a shadow ray per candidate and per
            neighbour; the paper) or ``"unshadowed"`` (Bitterli's unbiased variant: one shadow
            ray for the chosen sample, W = 0 when it is occluded; the support test keeps its rays).
            With either, a black texel or a switched-off light (f = 0, so p̂ = 0) still gets its
            unbiased gradient, from the fresh candidates (``integrators/restir_di.py``).
        freeze: replay the traced resampling pass (``dr.freeze``) where it can (no reuse, or
            screen-space neighbours of a sensor that has not moved): far less Python per step.
            ``None``: as torchir's other renders (:func:`torchir.backend.frozen_renders`, on
            unless ``TORCHIR_FREEZE=0``).
        multiview: ``"per_sensor"`` (one reservoir chain per sensor), ``"carry_over"`` (the
            paper's Alg. 8: one store for all views; a view reuses every view's reservoirs near
            its shading points, and a render replaces only the reservoirs its sensor sees;
            :attr:`steps` then counts the store's steps under key -1) or ``"auto"``
            (``carry_over`` for scenes with several sensors: 1.9-2.2x lower error x time than
            per-sensor chains in ``torchir bench restir_views``).
        spp_chains: at ``spp > 1``, sample ``s`` of a pixel reuses only samples ``s`` of the
            pixels around it (``spp`` interleaved chains: a pixel's samples stay independent, and
            the screen search scans ``spp`` times fewer samples). Measured at 128², 4 spp
            against one search over every sample: gradient error 0.028 vs 0.038 (``oxalis_lite``)
            and 0.029 vs 0.031 (``ajar_painting``) at 0.66x and 0.59x the step time.
        offset_lifetime: steps a camera sample keeps its position in the pixel, on average
            (``None`` or 0: a new one every step; ``float("inf")``: until the sensor or the
            geometry changes). Each step's positions stay uniform, so every step is unbiased;
            but the points a step samples persist, so texels narrower than the pixel spacing
            may get no gradient for that long. With temporal reuse alone, a kept sample
            resamples with its own previous reservoir, at the same shading point.
        light_guide: with kept offsets and temporal reuse alone (``preset="persistent"``), the
            share of each lane's light candidates drawn from what it learned of where its light
            comes from (0: off); unbiased (RIS weighs by the mixture's density).

    Example:
        >>> scene = torchir.Scene.builtin("oxalis_lite", resolution=32)
        >>> r = ReSTIRSampler(scene, candidates=8, burn_in=8)
        >>> img = render(scene, {}, spp=1, seed=0, sampler=r)   # (3, 32, 32)
        >>> r.diagnostics()["mean_M"] > 8
        True
    """

    def __init__(
        self,
        scene: Scene,
        candidates: int = 16,
        neighbors: int = 8,
        radius: float | None = None,
        m_cap: int | None = None,
        temporal: bool = True,
        spatial: bool = True,
        burn_in: int = 32,
        grad_paths: str = "decorrelated",
        nn_backend: str = "auto",
        seed: int = 0,
        normal_threshold: float = 0.9,
        preset: str = "restir",
        target: str = "shadowed",
        freeze: bool | None = None,
        multiview: str = "auto",
        spp_chains: bool = True,
        offset_lifetime: float | None = None,
        light_guide: float = 0.0,
    ) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a torchir.Scene, got {type(scene).__name__}")
        if preset not in _PRESETS:
            raise ValueError(f"preset must be one of {_PRESETS}, got {preset!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
            raise ValueError(f"seed must be an int in [0, 2^32), got {seed!r}")
        forward_only = preset == "forward_only"
        if preset == "b1":
            candidates, temporal, spatial, burn_in = 1, False, False, 0
        elif preset == "persistent":  # each sensor its own chains: a carried-over store has no lanes to keep
            spatial, multiview = False, "per_sensor" if multiview == "auto" else multiview
            offset_lifetime = PERSISTENT_LIFETIME if offset_lifetime is None else offset_lifetime
        elif preset == "b2":
            temporal, spatial, burn_in = False, False, 0
        from .. import backend
        from ..integrators.restir_di import ReSTIRDirectIntegrator, check_scene

        backend.variant()
        check_scene(scene.mi_scene)
        self.scene = scene
        self.preset = preset
        self.seed = seed
        self.integrator = ReSTIRDirectIntegrator(
            candidates=candidates,
            neighbors=neighbors,
            radius=0.0 if radius is None else float(radius),
            m_cap=0 if m_cap is None else m_cap,
            temporal=temporal,
            spatial=spatial,
            burn_in=burn_in,
            grad_paths=grad_paths,
            forward_only=forward_only,
            nn_backend=nn_backend,
            normal_threshold=normal_threshold,
            target=target,
            freeze=backend.frozen_renders() if freeze is None else bool(freeze),
            multiview=multiview,
            spp_chains=spp_chains,
            offset_lifetime=offset_lifetime,
            light_guide=light_guide,
        )

    # ------------------------------------------------------------------ used by render()
    def render_seed(self, seed: int) -> int:
        """The sampler seed of a render with ``seed`` (``self.seed`` mixed in when non-zero)."""
        if self.seed == 0:
            return seed
        import mitsuba as mi

        return int(mi.sample_tea_32(seed, self.seed)[0])

    def check_gradients(self, grad_names) -> None:
        """Refuse light-placement parameters; warn once about shape parameters (stage v2)."""
        # ReSTIR differentiates the path contribution of the reservoirs' light samples, which are
        # not rebuilt when a light moves: light placement gets no gradient (it failed inside Dr.Jit).
        emitters = {e.id() for e in self.scene.mi_scene.emitters()}
        for name in grad_names:
            owner, _, field = name.partition(".")
            if owner in emitters and not field.startswith(("intensity", "radiance", "irradiance", "scale")):
                raise ValueError(
                    f"ReSTIR gives no gradient for the light parameter {name!r} (light samples are reused, not "
                    f"re-sampled, when a light moves): optimise it without sampler=, e.g. with the scene's own integrator"
                )
        if any(is_geometry_key(name) for name in grad_names):
            integrator = self.integrator
            if not (integrator.edge_temporal and integrator.can_chain_edges()):
                edges = "afresh each step, "
            elif integrator.edge_temporal == "auto":
                edges = "afresh each step, or kept across steps (edge chains) on meshes with many edges, "
            else:
                edges = "and kept across steps (edge chains), "
            self.scene.warn_once(
                "restir-geometry",
                "ReSTIR with shape parameters: interior term with reuse (ray-following shading points); "
                "boundary terms: shadow edges sampled on the moving meshes under area lights "
                + edges
                + "silhouettes and the shading-horizon bands of smooth meshes without reuse, the rest from "
                "direct_projective; the temporal support test "
                "uses the current geometry (small bias, spec D7)",
            )

    # ------------------------------------------------------------------ public state API
    def reset(self) -> None:
        """Drop all reservoirs (also automatic when the emitter count or a mesh's topology
        changes); the next render of each sensor burns in again."""
        self.integrator.reset()

    def diagnostics(self) -> dict[str, float]:
        """Statistics of the last step: mean/max M, valid-neighbour fraction, fraction of
        W = 0, max W (over shading points that hit a surface) and seconds per stage
        (``time_ris``, ``time_nn``, ``time_combine``, ``time_backward``, ``time_burn_in``)."""
        out = dict(self.integrator.stats)
        timings = self.integrator.timings
        out.update({f"time_{k}": float(v) for k, v in timings.items()})
        step = sum(v for k, v in timings.items() if k != "burn_in")
        if step > 0:  # share of the step spent on reuse (NN search + combination)
            out["reuse_fraction"] = float((timings.get("nn", 0.0) + timings.get("combine", 0.0)) / step)
        return out

    def state_dict(self) -> dict[str, Any]:
        """Reservoirs (numpy arrays) and resolved radius per sensor, plus the options."""
        return {"preset": self.preset, "seed": self.seed, "sensors": self.integrator.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not isinstance(state, dict) or "sensors" not in state:
            raise ValueError("expected a dict from ReSTIRSampler.state_dict()")
        self.integrator.load_state_dict(copy.deepcopy(state["sensors"]))

    @property
    def steps(self) -> dict[int, int]:
        """Steps taken per sensor since the last reset."""
        return {s: st.steps for s, st in self.integrator.states.items()}

    def __repr__(self) -> str:
        i = self.integrator
        return (
            f"ReSTIRSampler(preset={self.preset!r}, candidates={i.candidates}, neighbors={i.neighbors}, "
            f"temporal={i.temporal}, spatial={i.spatial}, burn_in={i.burn_in}, grad_paths={i.grad_paths!r}, "
            f"m_cap={i.m_cap:g}, nn_backend={i.nn_backend!r}, target={i.target!r})"
        )
