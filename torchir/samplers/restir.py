"""``ReSTIRSampler``: reservoirs reused across gradient steps (Wang et al. 2023) for ``render``.

Wang et al. 2023 is "Amortizing Samples in Physics-Based Inverse Rendering using ReSTIR"
(SIGGRAPH Asia 2023), "the paper" below.

The sampler owns the per-sensor reservoir state and the Dr.Jit integrator that reads and
updates it; ``render(scene, params, spp, seed, sampler=r)`` then renders direct illumination
by ReSTIR and back-propagates its interior-term gradient (W constant, only ``Le * fs * g``
differentiated). Reservoirs are keyed by world-space shading points (shape, primitive,
barycentrics), so they survive parameter changes and every sensor keeps its own chain.

Presets (one flag for the paper's equal-time comparisons):

=================  ====================================================================
``preset``         meaning
=================  ====================================================================
``"auto"``         the default when nothing is given: settings chosen at the first render
                   from a probe of the scene (:mod:`._restir_auto`): persistent chains,
                   spatiotemporal reuse, or RIS without reuse where reuse does not pay;
                   options given beside it are kept as given
``"restir"``       the options as given (the default when options are given:
                   spatiotemporal reuse, decorrelated gradient paths: see ``grad_paths``)
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
import dataclasses
import sys
import warnings
from typing import Any

from ..integrators.restir_options import PERSISTENT_LIFETIME, PRESETS, ReSTIROptions
from ..scene import Scene, is_geometry_key
from ._restir_auto import DEFAULT_PLANNED_STEPS, PROBE_CANDIDATES, AutoChoice, choose, probe_scene

__all__ = ["ReSTIRSampler", "ReSTIROptions", "PERSISTENT_LIFETIME"]

AUTO = "auto"
_PRESETS = (AUTO, *PRESETS)


class ReSTIRSampler:
    """ReSTIR reservoir state for one scene (all its sensors).

    Args:
        scene: a :class:`torchir.Scene` with direct illumination only (point, spot and area
            emitters, no media, box filter).
        options: a :class:`ReSTIROptions` (every setting, validated); default: the ``preset``'s.
        preset: the short name of a named configuration (table above; the YAML ``preset:``
            key): ``"auto"`` (the default when neither options nor changes are given),
            ``"restir"`` (the default otherwise), ``"persistent"``, ``"b2"``, ``"b1"`` or
            ``"forward_only"``. Options given beside it win over what it sets.
        seed: mixed into every render seed (0: the render seed is used as is).
        planned_steps: steps the run will take, over which ``"auto"`` charges its burn-in
            (default 300; the trainer sets its ``max_steps``).
        **changes: any :class:`ReSTIROptions` field (``candidates=8``, ``light_guide=0.5``, ...),
            applied to ``options`` or to the preset (with ``"auto"``: kept, the rest chosen).

    Example:
        >>> scene = torchir.Scene.builtin("oxalis_lite", resolution=32)
        >>> r = ReSTIRSampler(scene, candidates=8, burn_in=8)
        >>> img = render(scene, {}, spp=1, seed=0, sampler=r)   # (3, 32, 32)
        >>> r.diagnostics()["mean_M"] > 8
        True
    """

    def __init__(self, scene: Scene, options: ReSTIROptions | None = None, *, preset: str | None = None,
                 seed: int = 0, planned_steps: int | None = None, **changes: Any) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a torchir.Scene, got {type(scene).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
            raise ValueError(f"seed must be an int in [0, 2^32), got {seed!r}")
        if preset is not None and preset not in _PRESETS:
            raise ValueError(f"preset must be one of {_PRESETS}, got {preset!r}")
        given = options is not None
        auto = preset == AUTO or (preset is None and options is None and not changes)
        self.choice: AutoChoice | None = None  # what "auto" chose, once it has
        self._choosing = auto  # until the first render (or a loaded state) settles the options
        self._pinned = dict(changes) if auto else {}
        self.planned_steps = planned_steps
        self._planned_given = planned_steps is not None
        if auto and given:
            raise TypeError("preset='auto' chooses the options itself: give it options as keyword arguments to pin, not options=")
        if auto:
            options = ReSTIROptions().replace(**changes)  # validated now; the chosen options replace it at the first render
        elif options is None:
            options = ReSTIROptions.preset("restir" if preset is None else preset, **changes)
        elif not isinstance(options, ReSTIROptions):
            raise TypeError(f"options must be a ReSTIROptions, got {type(options).__name__} "
                            f"(other settings are keyword arguments: ReSTIRSampler(scene, candidates=8))")
        elif preset is not None:
            raise TypeError("give options= or preset=, not both (ReSTIROptions.preset(name, ...) builds the options of a preset)")
        else:
            options = options.replace(**changes)
        from .. import backend
        from ..integrators.restir_di import ReSTIRDirectIntegrator, check_scene

        backend.variant()
        check_scene(scene.mi_scene)
        self.scene = scene
        self.preset = AUTO if auto else preset if preset is not None else (None if given else "restir")  # None: options given
        self.seed = seed
        self.integrator = ReSTIRDirectIntegrator(options=options)

    @property
    def options(self) -> ReSTIROptions:
        """The sampler's settings (immutable: build a new sampler to change them); with
        ``preset="auto"``, those it chose (before its first render: the defaults and pins)."""
        return self.integrator.options

    @property
    def planned_steps(self) -> int:
        """Steps the run will take (``"auto"`` charges its burn-in over them)."""
        return self._planned_steps

    @planned_steps.setter
    def planned_steps(self, steps: int | None) -> None:
        if steps is None:
            steps = DEFAULT_PLANNED_STEPS
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"planned_steps must be an int >= 1, got {steps!r}")
        self._planned_steps = steps

    def plan_run(self, steps: int) -> None:
        """The trainer's ``max_steps``: the run length ``"auto"`` charges its burn-in over (unless
        ``planned_steps`` was given)."""
        if not self._planned_given:
            self.planned_steps = steps

    def prepare(self, values: dict[str, Any], grad_names: frozenset[str], sensor: int, spp: int, seed: int) -> None:
        """Before a render (called by :func:`torchir.functions.render`): with ``preset="auto"``,
        at the first one that differentiates something, probe the scene at ``values`` and build
        the integrator it chooses (renders before it: RIS without reuse)."""
        if not self._choosing:
            return
        from ..integrators.restir_di import ReSTIRDirectIntegrator

        if not grad_names:  # nothing differentiated to measure yet: plain RIS until a render that is
            if self.integrator.options.reuse:
                self.integrator = ReSTIRDirectIntegrator(options=ReSTIROptions.no_reuse())
            return
        plain = tuple(ReSTIRSampler(self.scene, preset="b2", candidates=m, burn_in=0) for m in PROBE_CANDIDATES)
        probe = probe_scene(self.scene, values, grad_names, sensor, spp, self.render_seed(seed), plain)
        self.choice = _agreed(choose(probe, self.planned_steps, self._pinned))
        self.integrator = ReSTIRDirectIntegrator(options=self.choice.options)
        self._choosing = False
        sys.stdout.write(f"[torchir] {self.choice.describe()}\n")  # one write: processes sharing a pipe keep whole lines
        sys.stdout.flush()

    # ------------------------------------------------------------------ used by render()
    def render_seed(self, seed: int) -> int:
        """The sampler seed of a render with ``seed`` (``self.seed`` mixed in when non-zero)."""
        if self.seed == 0:
            return seed
        import mitsuba as mi

        return int(mi.sample_tea_32(seed, self.seed)[0])

    def check_gradients(self, grad_names) -> None:
        """Refuse light-placement parameters; warn once about shape parameters (what their boundary
        terms reuse, and a small bias)."""
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
                "uses the current geometry, not the previous step's (a small bias)",
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
        """Reservoirs (numpy arrays) and resolved radius per sensor, plus the preset, seed and
        options (every :class:`ReSTIROptions` field) the chains were built with."""
        state = {"preset": self.preset, "seed": self.seed, "options": dataclasses.asdict(self.options),
                 "sensors": self.integrator.state_dict()}
        if self.choice is not None:
            state["auto"] = self.choice.to_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """The chains of ``state``, continued under this sampler's own options; where those differ
        from the options the chains were built with (a checkpoint resumed with another config), a
        warning names each field, saved and now."""
        if not isinstance(state, dict) or "sensors" not in state:
            raise ValueError("expected a dict from ReSTIRSampler.state_dict()")
        if self._choosing and isinstance(state.get("auto") or state.get("options"), dict):
            from ..integrators.restir_di import ReSTIRDirectIntegrator  # a resumed run keeps its chains' options

            if isinstance(state.get("auto"), dict):
                self.choice = AutoChoice.from_dict(state["auto"])
            options = self.choice.options if self.choice is not None else ReSTIROptions(**state["options"]).replace(**self._pinned)
            self.integrator = ReSTIRDirectIntegrator(options=options)
            self._choosing = False
        saved, now = state.get("options"), dataclasses.asdict(self.options)
        if isinstance(saved, dict):  # older checkpoints have none
            changed = [f"{k}: {saved[k]!r} -> {now[k]!r}" for k in now if k in saved and saved[k] != now[k]]
            if changed:
                warnings.warn("ReSTIR reservoirs loaded from a state built with other options; they continue under "
                              "this sampler's (" + "; ".join(changed) + ")", stacklevel=2)
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


def _agreed(choice: AutoChoice) -> AutoChoice:
    """Under torch.distributed (DDP), process 0's choice for every process: the probes of the
    processes' own views would measure (and time) slightly differently."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() < 2:
        return choice
    box = [choice.to_dict() if dist.get_rank() == 0 else None]
    dist.broadcast_object_list(box, src=0)
    return AutoChoice.from_dict(box[0])
