"""``ReSTIROptions``: every setting of ReSTIR direct illumination, in one validated, frozen object.

:class:`~torchir.samplers.ReSTIRSampler` and :class:`~torchir.integrators.restir_di.ReSTIRDirectIntegrator`
take one; the named constructors are the usual configurations, and arguments given to them win
over what the configuration sets::

    ReSTIROptions()                                  # spatiotemporal reuse (the default)
    ReSTIROptions.no_reuse()                         # streaming RIS over `candidates`, no reuse
    ReSTIROptions.one_light_sample()                 # one light sample per camera ray, no reuse
    ReSTIROptions.persistent(light_guide=0.5)        # each camera sample its own chain
    ReSTIROptions.reuse_for_image_only()             # reuse for the image, plain RIS for the gradient
    opts.replace(candidates=4)                       # a validated copy with changes

What each option does is in the class's docstring below.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any, ClassVar

__all__ = ["ReSTIROptions", "PRESETS", "PERSISTENT_LIFETIME", "NN_BACKENDS"]

PERSISTENT_LIFETIME = 2048.0  # persistent(): mean steps a camera sample keeps its position in the pixel
AUTO = "auto"
NN_BACKENDS = (AUTO, "kdtree", "grid", "screen")  # neighbour searches (integrators._knn.NeighbourSearch)


def _int(name: str, value: Any, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    value = int(value)
    if value < lo:
        raise ValueError(f"{name} must be >= {lo}, got {value}")
    return value


def _choice(name: str, value: Any, choices: tuple) -> Any:
    if not any(value is c or (type(value) is type(c) and value == c) for c in choices):
        names = [repr(c) for c in choices]
        raise ValueError(f"{name} must be {', '.join(names[:-1])} or {names[-1]}, got {value!r}")
    return value


def _flag(name: str, value: Any) -> bool:
    """True/False (or 0/1, as Mitsuba properties and older configs give them)."""
    if not isinstance(value, numbers.Integral) or value not in (0, 1):
        raise TypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


@dataclass(frozen=True)
class ReSTIROptions:
    """Settings of ReSTIR direct illumination (validated when constructed; immutable): light
    resampling first, from ``candidates`` to ``light_guide``, then the boundary terms of shape
    gradients, from ``shadow_edge_sampling`` on.

    Attributes:
        candidates: M, light candidates per camera sample (streaming RIS).
        neighbors: k, reservoirs of the previous step combined per camera sample (8 and 16
            candidates: the lowest error x time of those tried; measurements: docs/restir.md, "Speed").
        radius: neighbour search radius in world units (``None``: 2 pixel footprints).
        m_cap: cap on M (``None``: 2 * candidates for searched neighbours, 64 * candidates
            for a lane's own chain). Any move of a shading point lets a long memory count in
            ``Z`` where its sample is hidden from the new point, so searched neighbours keep a
            short one; a chain at a fixed shading point has no such events (measurements:
            docs/restir-measurements.md, "M caps").
        temporal: reuse of the previous step's reservoirs (with ``spatial``: the paper's
            spatiotemporal reuse; neither: plain RIS).
        spatial: reuse of the same step's reservoirs nearby.
        burn_in: forward-only reuse passes before a sensor's first step (kept offsets without
            spatial reuse, e.g. ``persistent()``: one pass over ``burn_in x candidates``).
        grad_paths: ``"decorrelated"`` (the default: a second resampling pass with
            ``seed_grad``/``spp_grad``, with temporal reuse a step of the gradient's own chain,
            which never reuses what the image reused) or ``"shared"``
            (the paper: the gradient re-evaluates the image's paths, so ``render``'s
            ``seed_grad``/``spp_grad`` are unused and the second pass is saved). Shared paths
            are unbiased only for a loss linear in the image: for L2,
            ``E[2 (I - T) dI] = 2 (E[I] - T) E[dI] + 2 Cov(I, dI)``, and the covariance term
            pulls the fit off the truth in proportion to the image's variance, which is largest
            where light sampling is hard (docs/restir.md, "Gradient paths"). Decorrelated paths remove
            that term for every preset (``tests/integrators/test_restir_grad_paths.py``); with reuse the
            gradient's chain burns in too, once, at the first backward.
        forward_only: reuse for the image, plain RIS (``seed_grad``) for the gradient (an ablation).
        nn_backend: ``"auto"`` (timed) | ``"kdtree"`` (scipy) | ``"grid"`` (Dr.Jit) | ``"screen"``
            (the previous step's samples in the surrounding pixels; a sensor that has not moved).
        normal_threshold: neighbours with ``n . n' <`` this are dropped.
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
            (``carry_over`` for scenes with several sensors: lower error x time than per-sensor
            chains, with no burn-in per view and reservoirs from every view; measurements:
            docs/restir.md, the opening section, ``torchir bench restir_views``).
        spp_chains: at ``spp > 1``, sample ``s`` of a pixel reuses only samples ``s`` of the
            pixels around it (``spp`` interleaved chains: a pixel's samples stay independent, and
            the screen search scans ``spp`` times fewer samples): lower gradient error in less
            time than one search over every sample (measurements: docs/restir.md, "Speed").
        offset_lifetime: steps a camera sample keeps its position in the pixel, on average
            (``None`` or 0: a new one every step; ``float("inf")``: until the sensor or the
            geometry changes). Each step's positions stay uniform, so every step is unbiased;
            but the points a step samples persist, so texels narrower than the pixel spacing
            may get no gradient for that long. With temporal reuse alone, a kept sample
            resamples with its own previous reservoir, at the same shading point.
        light_guide: with kept offsets and temporal reuse alone (``persistent()``), the
            share of each lane's light candidates drawn from what it learned of where its light
            comes from (0: off); unbiased (RIS weighs by the mixture's density).
        shadow_edge_sampling: sample shadow edges on the moving meshes (False: Mitsuba's
            ``direct_projective`` term).
        edge_guiding: draw (edge, light) pairs by what earlier steps found (True / False / "auto").
        edge_temporal: keep shadow-edge samples across steps (edge chains; True / False / "auto").
        edge_light_candidates: light points per shadow-edge sample, one kept by RIS.
        edge_candidates: whole shadow-edge samples per sample kept, one kept by RIS.
        edge_chain_cap: confidence cap of an edge chain, in candidates.
        silhouette_sampling: sample primary silhouettes on the moving meshes' edges (True / False / "auto").
        silhouette_candidates: light candidates on either side of a silhouette sample.
        shading_bands: the shading-horizon term of smooth meshes (True / False / "auto").
        moving_geometry_m_cap: the M cap of temporal reuse after the geometry moved (0: ``m_cap``).

    Example:
        >>> ReSTIROptions.no_reuse(candidates=8).spatial
        False
        >>> ReSTIROptions.one_light_sample(candidates=4).candidates   # explicit arguments win
        4
        >>> ReSTIROptions(candidates=0)
        Traceback (most recent call last):
        ...
        ValueError: candidates must be >= 1, got 0
    """

    candidates: int = 16
    neighbors: int = 8
    radius: float = 0.0
    normal_threshold: float = 0.9
    m_cap: int = 0
    temporal: bool = True
    spatial: bool = True
    burn_in: int = 32
    grad_paths: str = "decorrelated"
    forward_only: bool = False
    nn_backend: str = AUTO
    target: str = "shadowed"
    freeze: bool | None = None
    multiview: str = AUTO
    spp_chains: bool = True
    offset_lifetime: float = 0.0
    light_guide: float = 0.0
    shadow_edge_sampling: bool = True
    edge_guiding: bool | str = AUTO
    edge_temporal: bool | str = AUTO
    edge_light_candidates: int = 1
    edge_candidates: int = 1
    edge_chain_cap: float = 32.0
    silhouette_sampling: bool | str = AUTO
    silhouette_candidates: int = 16
    shading_bands: bool | str = AUTO
    moving_geometry_m_cap: int = 4

    MULTIVIEW: ClassVar[tuple[str, ...]] = (AUTO, "per_sensor", "carry_over")

    def __post_init__(self) -> None:
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen)
        for name, lo in (("candidates", 1), ("neighbors", 1), ("burn_in", 0), ("edge_light_candidates", 1),
                         ("edge_candidates", 1), ("silhouette_candidates", 1), ("moving_geometry_m_cap", 0)):
            set_(name, _int(name, getattr(self, name), lo))
        set_("m_cap", _int("m_cap", 0 if self.m_cap is None else self.m_cap, 0))
        set_("radius", self._real("radius", 0.0 if self.radius is None else self.radius))
        if not math.isfinite(self.radius) or self.radius < 0:
            raise ValueError(f"radius must be >= 0 (0 = automatic), got {self.radius}")
        set_("normal_threshold", self._real("normal_threshold", self.normal_threshold))
        if math.isnan(self.normal_threshold):  # beyond [-1, 1]: every neighbour kept (< -1) or none (> 1)
            raise ValueError("normal_threshold is a cosine, got nan")
        for name in ("temporal", "spatial", "forward_only", "spp_chains", "shadow_edge_sampling"):
            set_(name, _flag(name, getattr(self, name)))
        if self.freeze is not None:
            set_("freeze", _flag("freeze", self.freeze))
        _choice("grad_paths", self.grad_paths, ("shared", "decorrelated"))
        _choice("nn_backend", self.nn_backend, NN_BACKENDS)
        _choice("target", self.target, ("shadowed", "unshadowed"))
        _choice("multiview", self.multiview, self.MULTIVIEW)
        for name in ("edge_guiding", "edge_temporal", "silhouette_sampling", "shading_bands"):
            _choice(name, getattr(self, name), (True, False, AUTO))
        lifetime = self._real("offset_lifetime", 0.0 if self.offset_lifetime is None else self.offset_lifetime)
        if not (lifetime == 0.0 or lifetime >= 1.0):  # NaN fails both
            raise ValueError(f"offset_lifetime must be None or 0 (a fresh camera offset every step) or >= 1 "
                             f"steps (inf: kept until the sensor moves), got {self.offset_lifetime!r}")
        set_("offset_lifetime", lifetime)
        set_("light_guide", self._real("light_guide", self.light_guide))
        if not 0.0 <= self.light_guide < 1.0:  # NaN fails too
            raise ValueError(f"light_guide must be a share of candidates in [0, 1) (0: off), got {self.light_guide!r}")
        if self.light_guide > 0 and not self.lane_chains:  # a guide is learned at a kept shading point
            raise ValueError("light_guide needs lane chains: kept camera offsets and temporal reuse alone "
                             "(ReSTIROptions.persistent(light_guide=...), or ReSTIRSampler(scene, preset='persistent', light_guide=...))")
        set_("edge_chain_cap", self._real("edge_chain_cap", self.edge_chain_cap))
        if not self.edge_chain_cap > 0:
            raise ValueError(f"edge_chain_cap must be > 0, got {self.edge_chain_cap}")

    @staticmethod
    def _real(name: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise TypeError(f"{name} must be a number, got {type(value).__name__}")
        return float(value)

    # ------------------------------------------------------------------ derived
    @property
    def lane_chains(self) -> bool:
        """Each camera sample resamples with its own previous reservoir at a kept shading point
        (temporal reuse with kept offsets, no spatial reuse)."""
        return self.temporal and not self.spatial and self.offset_lifetime > 0

    @property
    def reuse(self) -> bool:
        return self.temporal or self.spatial

    def replace(self, **changes: Any) -> ReSTIROptions:
        """A validated copy with ``changes`` (``self`` when there are none)."""
        _check_names(changes)
        return dataclasses.replace(self, **changes) if changes else self

    # ------------------------------------------------------------------ named configurations
    @classmethod
    def spatiotemporal(cls, **options: Any) -> ReSTIROptions:
        """Temporal and spatial reuse (the defaults; the paper's ReSTIR)."""
        return cls._configured({}, options)

    @classmethod
    def persistent(cls, **options: Any) -> ReSTIROptions:
        """Temporal reuse of each camera sample's own reservoir at a kept shading point: no
        spatial reuse, ``offset_lifetime=2048``, one chain per sensor. For light-bound scenes
        whose texels span several pixels."""
        base = {"spatial": False, "multiview": "per_sensor", "offset_lifetime": PERSISTENT_LIFETIME}
        if options.get("multiview") == AUTO:  # a store carried over between views has no lanes to keep
            options = {**options, "multiview": "per_sensor"}
        if options.get("offset_lifetime", 1) is None:
            options = {k: v for k, v in options.items() if k != "offset_lifetime"}
        return cls._configured(base, options)

    @classmethod
    def no_reuse(cls, **options: Any) -> ReSTIROptions:
        """Streaming RIS over ``candidates`` light samples per camera ray, no reuse (the paper's B.2)."""
        return cls._configured({"temporal": False, "spatial": False, "burn_in": 0}, options)

    @classmethod
    def one_light_sample(cls, **options: Any) -> ReSTIROptions:
        """One light sample per camera ray, no reuse (the paper's B.1)."""
        return cls._configured({"candidates": 1, "temporal": False, "spatial": False, "burn_in": 0}, options)

    @classmethod
    def reuse_for_image_only(cls, **options: Any) -> ReSTIROptions:
        """Reuse for the image, plain RIS for the gradient (an ablation)."""
        return cls._configured({"forward_only": True}, options)

    @classmethod
    def preset(cls, name: str, **options: Any) -> ReSTIROptions:
        """The configuration by its short name (the YAML ``preset:`` key): see :data:`PRESETS`."""
        if name not in PRESETS:
            raise ValueError(f"preset must be one of {tuple(PRESETS)}, got {name!r}")
        return getattr(cls, PRESETS[name])(**options)

    @classmethod
    def _configured(cls, base: dict, options: dict) -> ReSTIROptions:
        _check_names(options)
        return cls(**{**base, **options})


PRESETS = {  # short name (YAML, ReSTIRSampler(preset=...)) -> named constructor
    "restir": "spatiotemporal",
    "persistent": "persistent",
    "b1": "one_light_sample",
    "b2": "no_reuse",
    "forward_only": "reuse_for_image_only",
}


def _check_names(options: dict) -> None:
    known = {f.name for f in dataclasses.fields(ReSTIROptions)}
    unknown = sorted(set(options) - known)
    if unknown:
        import difflib

        hints = [m for name in unknown for m in difflib.get_close_matches(name, known, n=1)]
        hint = f" (did you mean {', '.join(repr(h) for h in hints)}?)" if hints else ""
        raise TypeError(f"unknown ReSTIR option(s) {unknown}{hint}; known: {sorted(known)}")
