"""``preset="auto"``: ReSTIR settings chosen from what a probe of the scene measures.

A probe (:func:`probe_scene`) renders gradients of the first step's parameters with RIS and
no reuse (the paper's B.2): with 4 and 256 light candidates on camera rays ``a``, and again on
other camera rays ``b``. Squared differences of the gradients split their variance into

* ``v_C``, the camera-sampling floor: what no light sampler removes (the variance left with
  infinitely many candidates), and
* ``v_L``, the light part with one candidate: RIS over ``M`` candidates leaves ``v_L / M``,

and the timings of the two candidate counts give a step's fixed cost ``t0`` and the cost of a
candidate ``t_c``. :func:`choose` then compares, per unit of error² x time (the inverse of the
effective sample count per second), the best plain RIS (``M`` from 1 to 256), spatiotemporal
reuse and persistent lane chains with light guides, each with its burn-in charged over the
planned steps, and keeps the plain estimator unless reuse is predicted to win by a margin.
Persistent chains keep each camera sample's position in its pixel, so they are chosen only
where a step's samples reach every differentiated value another step's would (coarse
textures, no shape parameters).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

from ..integrators.restir_options import ReSTIROptions

__all__ = ["SceneProbe", "AutoChoice", "probe_scene", "choose", "DEFAULT_PLANNED_STEPS"]

PROBE_CANDIDATES = (4, 256)  # the two RIS candidate counts of the probe (same camera rays)
PLAIN_CANDIDATES = (1, 2, 4, 8, 16, 32, 64, 128, 256)  # the fallback's candidate counts
DEFAULT_PLANNED_STEPS = 300  # the run length that the burn-in is charged over when none is given
REUSE_MARGIN = 1.25  # reuse must be predicted this much cheaper (error² x time) than plain RIS
# Step-cost and variance models of the reuse strategies against B.2 at equal candidates,
# measured on the built-in light-bound scenes (docs/restir-measurements.md, "Decorrelated paths").
PERSISTENT_STEP = 2.0  # a persistent step with light guides / a B.2 step (1.5-1.9 measured on held-out scenes)
# Kept camera offsets keep their camera-sampling error from step to step, where fresh offsets
# give the optimiser new errors to average: Adam's momentum (beta1 = 0.9) averages about 10 steps,
# so the persistent chains' floor counts this many times (on a held-out scene lit by two visible
# area lights, light/camera variance 10, persistent chains fitted 2.6x worse than B.2: texture RMSE 0.0057 against 0.0040)
PERSISTENCE_WINDOW = 10.0
PERSISTENT_CANDIDATES = 4
BURN_IN_SHARE = 1.0  # the lane chains' burn-in may take at most this share of the planned steps' time (but always 64 x PERSISTENT_CANDIDATES candidates)
CHAINS_BURNED_IN = 2  # the image's chains and, with decorrelated gradient paths, the gradient's own
SPATIOTEMPORAL_CANDIDATES = 16
SPATIOTEMPORAL_STEP = 2.3  # a spatiotemporal step / a B.2 step (1.6-2.3 measured)
SPATIOTEMPORAL_GAIN = 12.0  # its light variance / B.2's at equal candidates (12-17 measured)
SPATIOTEMPORAL_BURN_IN = 32
MISSED_SHARE = 0.02  # persistent chains only if one step misses at most this share of what another reaches


@dataclass(frozen=True)
class SceneProbe:
    """What the probe measured (variances are of the gradient vector: sums over its entries).

    Attributes:
        light_variance: ``v_L``, the light-sampling variance with one candidate (RIS over ``M``: ``v_L / M``).
        camera_variance: ``v_C``, the camera-sampling floor (an upper bound when not ``camera_resolved``).
        camera_resolved: whether ``v_C`` stood out of the 256-candidate RIS's own light variance.
        step_seconds: ``t0``, a B.2 step's cost that does not grow with candidates.
        candidate_seconds: ``t_c``, the cost of one more candidate per camera sample.
        missed_share: share of the gradient's non-zero entries that one step reaches and
            another misses (texels finer than the pixel spacing, which kept camera samples starve).
        geometry: whether a shape parameter is differentiated.
        spp: samples per pixel the probe rendered at (the run's).
        seconds: the probe's own wall time.
    """

    light_variance: float
    camera_variance: float
    camera_resolved: bool
    step_seconds: float
    candidate_seconds: float
    missed_share: float
    geometry: bool
    spp: int
    seconds: float

    @property
    def light_to_camera(self) -> float:
        """``v_L / v_C``: how light-bound the scene is (one candidate against the floor)."""
        return self.light_variance / self.camera_variance if self.camera_variance > 0 else math.inf


@dataclass(frozen=True)
class AutoChoice:
    """The strategy chosen and why.

    Attributes:
        strategy: ``"persistent"``, ``"spatiotemporal"`` or ``"plain"`` (RIS without reuse).
        options: the :class:`ReSTIROptions` the sampler runs with (pinned options applied).
        probe: the measurements behind it.
        costs: predicted error² x seconds per step (burn-in charged) of each strategy considered,
            relative to the best plain estimator's.
        planned_steps: the steps the burn-in was charged over.
    """

    strategy: str
    options: ReSTIROptions
    probe: SceneProbe
    costs: dict[str, float]
    planned_steps: int

    def describe(self) -> str:
        """One line for the run's log."""
        o, p = self.options, self.probe
        if self.strategy == "plain":
            what = f"RIS over {o.candidates} candidate(s), no reuse (reuse is not predicted to pay here)"
        elif self.strategy == "persistent":
            what = (f"persistent lane chains: {o.candidates} candidates a step, light guide {o.light_guide:g}, "
                    f"burn-in {o.burn_in} x {o.candidates} candidates, M cap {o.m_cap}")
        else:
            what = f"spatiotemporal reuse: {o.candidates} candidates, {o.neighbors} neighbours, burn-in {o.burn_in}"
        ratio = "%.3g" % p.light_to_camera + ("" if p.camera_resolved else "+")
        costs = ", ".join(f"{k} {v:.2g}" for k, v in self.costs.items())
        return (f"ReSTIR auto: {what}; light/camera variance {ratio}, missed share {p.missed_share:.3f}, "
                f"predicted error² x time vs plain RIS: {costs} (probe {p.seconds:.1f} s)")

    def to_dict(self) -> dict[str, Any]:
        return {"strategy": self.strategy, "options": dataclasses.asdict(self.options), "probe": dataclasses.asdict(self.probe),
                "costs": dict(self.costs), "planned_steps": self.planned_steps}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AutoChoice:
        return cls(data["strategy"], ReSTIROptions(**data["options"]), SceneProbe(**data["probe"]), dict(data["costs"]),
                   int(data["planned_steps"]))


# ----------------------------------------------------------------------------- the probe
def probe_scene(scene: Any, values: dict[str, Any], grad_names: frozenset[str], sensor: int, spp: int, seed: int,
                samplers: tuple[Any, Any]) -> SceneProbe:
    """Measure ``scene`` (a :class:`torchir.Scene`) at ``values`` (``{key: tensor}``, as bound by
    the render that asks) with B.2 gradients of ``grad_names`` (the image, when nothing is
    differentiated) at ``spp``, rendered by ``samplers``: RIS without reuse over
    :data:`PROBE_CANDIDATES` (4 and 256) candidates. 4 and 256 candidates on camera rays ``a`` and
    on rays ``b`` (the light part from each pair, the floor from the two 256s), and 4 again on
    rays ``c`` for its timing (the first of each count compiles)."""
    import torch

    from ..functions import render
    from ..scene import is_geometry_key

    started = time.perf_counter()
    names = sorted(grad_names)
    low, high = samplers

    def sample(sampler: Any, rays: int) -> tuple[Any, float]:
        leaves = {k: v.detach().clone().requires_grad_(k in grad_names) for k, v in values.items()}
        probe_seed = (seed * 4 + rays) % 2**31
        t0 = time.perf_counter()
        image = render(scene, leaves, spp=spp, seed=probe_seed, seed_grad=probe_seed + 2**31, sensor=sensor, sampler=sampler)
        if names:
            grads = torch.autograd.grad(image.sum(), [leaves[k] for k in names], allow_unused=True)
            vector = torch.cat([(torch.zeros_like(leaves[k]) if g is None else g).reshape(-1).double() for k, g in zip(names, grads)])
        else:
            vector = image.detach().reshape(-1).double()
        return vector, time.perf_counter() - t0

    low_a, _ = sample(low, 1)
    high_a, _ = sample(high, 1)
    high_b, seconds_high = sample(high, 2)
    low_b, seconds_low = sample(low, 2)
    seconds_low = min(seconds_low, sample(low, 3)[1])
    m_low, m_high = PROBE_CANDIDATES
    light = float((low_a - high_a).square().sum() + (low_b - high_b).square().sum()) / 2 / (1 / m_low + 1 / m_high)
    camera_upper = float((high_a - high_b).square().sum()) / 2
    camera = camera_upper - light / m_high
    resolved = camera > 0.1 * camera_upper
    camera = camera if resolved else 0.1 * camera_upper
    per_candidate = max((seconds_high - seconds_low) / (m_high - m_low), 1e-9)
    fixed = max(seconds_low - m_low * per_candidate, 0.1 * seconds_low)
    reached_a, reached_b = high_a != 0, high_b != 0
    either = int((reached_a | reached_b).sum())
    missed = float((reached_a ^ reached_b).sum()) / either if either and names else 0.0
    return SceneProbe(light_variance=max(light, 0.0), camera_variance=max(camera, 1e-30), camera_resolved=bool(resolved),
                      step_seconds=fixed, candidate_seconds=per_candidate, missed_share=missed,
                      geometry=any(is_geometry_key(k) for k in names), spp=int(spp), seconds=time.perf_counter() - started)


# ----------------------------------------------------------------------------- the choice
def choose(probe: SceneProbe, planned_steps: int = DEFAULT_PLANNED_STEPS, pinned: dict[str, Any] | None = None) -> AutoChoice:
    """The strategy of lowest predicted error² x time (burn-in charged over ``planned_steps``),
    reuse only when it beats the best plain RIS by :data:`REUSE_MARGIN`; ``pinned`` options
    (given by the user) replace what the choice sets."""
    if planned_steps < 1:
        raise ValueError(f"planned_steps must be >= 1, got {planned_steps}")
    pinned = dict(pinned or {})
    v_c, v_l = probe.camera_variance, probe.light_variance
    t0, t_c = probe.step_seconds, probe.candidate_seconds
    n = float(planned_steps)

    def plain(m: int) -> float:
        return (v_c + v_l / m) * (t0 + m * t_c)

    m_plain = min(PLAIN_CANDIDATES, key=plain)
    base = plain(m_plain)
    options = {"plain": ReSTIROptions.no_reuse(candidates=m_plain)}
    costs = {"plain": 1.0}

    m = SPATIOTEMPORAL_CANDIDATES
    step = SPATIOTEMPORAL_STEP * (t0 + m * t_c)
    costs["spatiotemporal"] = (v_c + v_l / (m * SPATIOTEMPORAL_GAIN)) * step * (1 + SPATIOTEMPORAL_BURN_IN / n) / base
    options["spatiotemporal"] = ReSTIROptions.spatiotemporal(candidates=m, burn_in=SPATIOTEMPORAL_BURN_IN)

    if not probe.geometry and probe.missed_share <= MISSED_SHARE:
        c = PERSISTENT_CANDIDATES
        step = PERSISTENT_STEP * (t0 + c * t_c)
        chains = CHAINS_BURNED_IN if pinned.get("grad_paths", "decorrelated") == "decorrelated" else 1
        # burn-in candidates x minimising (W v_C + v_L / x) (n step + chains x t_c):
        # x = sqrt(v_L n step / (chains W v_C t_c))
        most = max(BURN_IN_SHARE * n * step / (chains * t_c), 64.0 * c)
        x = min(max(math.sqrt(v_l * n * step / (chains * PERSISTENCE_WINDOW * v_c * t_c)), 64.0 * c), most)
        burn_in = max(1, math.ceil(x / c))
        ran = burn_in * c  # the burn-in's candidates per lane as run (x rounded up to whole passes)
        costs["persistent"] = (PERSISTENCE_WINDOW * v_c + v_l / ran) * step * (1 + chains * burn_in * c * t_c / (n * step)) / base
        options["persistent"] = ReSTIROptions.persistent(candidates=c, burn_in=burn_in, m_cap=4 * burn_in * c, light_guide=0.5)

    reuse = min((k for k in costs if k != "plain"), key=costs.get)
    strategy = reuse if costs[reuse] * REUSE_MARGIN < 1.0 else "plain"
    chosen = options[strategy]
    if pinned:
        try:
            chosen = chosen.replace(**pinned)
        except (TypeError, ValueError) as error:
            raise ValueError(f"ReSTIR auto chose {strategy!r}, which the pinned options {pinned} do not fit: {error} "
                             f"(give a preset instead of 'auto')") from error
    return AutoChoice(strategy, chosen, probe, costs, int(planned_steps))
