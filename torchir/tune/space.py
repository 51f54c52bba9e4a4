"""The settings ``torchir tune`` tries: which techniques apply to a config's scene and loss.

A :class:`Setting` is the tuned part of ``model``: ``spp`` (and ``spp_grad`` in proportion when
the config sets it), ``sampler`` (a pixel sampler or ReSTIR), ``denoiser`` and, for settings
scored only by training, ``loss``. :func:`enumerate_space` keeps what the scene and loss admit:

* pixel samplers only for a path-replay integrator (``prb``, ``prb_basic``, ``prbvolpath``: not
  a projective one's shape gradients), a per-pixel loss (``pixelwise``, as the module requires) and targets
  that do not clip (pixel sampling compares unclipped pixels);
* ReSTIR only when :func:`torchir.integrators.restir_di.check_scene` accepts the scene (direct
  illumination only: no indirect bounces, media or environment light);
* denoisers always (full images), never together with a pixel sampler;
* the LOI loss only in place of a built-in image loss (``l1``, ``l2``, ``relative_l2``, ``gp``,
  ``multiscale_l1``, ``multiscale_l2``), never with a pixel sampler: it compares whole images.
  It changes the loss, so its gradient cannot be compared with the config's reference.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any, Optional

__all__ = ["Setting", "Space", "enumerate_space", "spp_ladder", "replaceable_loss"]

IMAGE_LOSSES = ("l1", "l2", "relative_l2", "gp", "multiscale_l1", "multiscale_l2")  # LOI may replace these
LOI = {"type": "loi", "transform": "reinhard"}  # the paper's scales (the module's defaults), HDR tone-mapped
PIXEL = {"refresh_every": 20, "levels": 4, "alpha": 0.1}  # as configs/sampling_*.yaml
TARGET_AWARE = {"type": "target_aware", "radius": 7, "bandwidth": 0.1}  # as configs/denoise_target_aware.yaml
CROSS_BILATERAL = {"type": "cross_bilateral", "radius": 7}  # as configs/denoise_cross_bilateral.yaml


@dataclass(frozen=True)
class Setting:
    """One point of the search: what it sets in ``model`` (``None``: no sampler / denoiser;
    ``loss`` ``None``: the config's own loss)."""

    spp: int
    sampler: Optional[dict[str, Any]] = None
    denoiser: Optional[dict[str, Any]] = None
    loss: Optional[dict[str, Any]] = None
    spp_grad: Optional[int] = None

    @property
    def key(self) -> str:
        """A stable text identity (dicts are not hashable)."""
        return json.dumps([self.spp, self.spp_grad, self.sampler, self.denoiser, self.loss], sort_keys=True, default=str)

    @property
    def pixel(self) -> bool:
        """Whether the sampler is a pixel sampler (full images are not rendered)."""
        from ..samplers import PIXEL_SAMPLERS

        return self.sampler is not None and self.sampler.get("type") in PIXEL_SAMPLERS

    @property
    def gradient_scored(self) -> bool:
        """Whether the setting keeps the config's loss (its gradient error is defined)."""
        return self.loss is None

    def model_changes(self) -> dict[str, Any]:
        """The ``model`` keys this setting sets (``None``: remove the key)."""
        out: dict[str, Any] = {"spp": self.spp, "sampler": self.sampler, "denoiser": self.denoiser}
        if self.spp_grad is not None:
            out["spp_grad"] = self.spp_grad
        if self.loss is not None:
            out["loss"] = self.loss
        return out

    def label(self) -> str:
        """A short name: ``spp 4 + restir(persistent) + target_aware``."""
        parts = [f"spp {self.spp}" + (f"/{self.spp_grad}" if self.spp_grad not in (None, self.spp) else "")]
        if self.sampler is not None:
            s = self.sampler
            if s.get("type") == "restir":
                parts.append(f"restir({s['preset'] if 'preset' in s else 'options' if len(s) > 1 else 'default'})")
            elif "budget" in s:
                parts.append(f"{s['type']} {_fraction(s['budget'])}")
            else:
                parts.append(str(s.get("type")))
        if self.denoiser is not None:
            parts.append(str(self.denoiser.get("type")))
        if self.loss is not None:
            parts.append(f"loss {self.loss.get('type') if isinstance(self.loss, dict) else self.loss}")
        return " + ".join(parts)


def _fraction(budget: Any) -> str:
    return f"{budget:.0%}" if isinstance(budget, float) and budget <= 1 else f"{budget} px"


@dataclass
class Space:
    """The options of each tuned key for one config (``None`` first: off), and why techniques
    were left out (``notes``)."""

    base: Setting
    spps: list[int]
    samplers: list[Optional[dict[str, Any]]]
    denoisers: list[Optional[dict[str, Any]]]
    losses: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    spp_grad_ratio: Optional[float] = None

    def setting(self, spp: int, sampler: Optional[dict] = None, denoiser: Optional[dict] = None,
                loss: Optional[dict] = None) -> Setting:
        """A setting at ``spp`` (``spp_grad`` kept in the config's proportion)."""
        grad = None if self.spp_grad_ratio is None else max(1, round(spp * self.spp_grad_ratio))
        return Setting(spp, sampler, denoiser, loss, grad)

    def at_spp(self, setting: Setting, spp: int) -> Setting:
        """``setting`` at another ``spp``."""
        return self.setting(spp, setting.sampler, setting.denoiser, setting.loss)

    def grid(self) -> list[Setting]:
        """Every valid combination that keeps the loss (no pixel sampler with a denoiser)."""
        out = []
        for spp in self.spps:
            for sampler in self.samplers:
                for denoiser in self.denoisers:
                    s = self.setting(spp, sampler, denoiser)
                    if not (s.pixel and denoiser is not None):
                        out.append(s)
        return _unique(out)

    def loss_variants(self, settings: list[Setting]) -> list[Setting]:
        """``settings`` (those without a pixel sampler) with each alternative loss."""
        return _unique([replace(s, loss=loss) for s in settings if not s.pixel for loss in self.losses])

    def describe(self) -> dict[str, Any]:
        return {"spp": self.spps, "sampler": self.samplers, "denoiser": self.denoisers, "loss": self.losses,
                "base": self.base.label(), "notes": self.notes}


def _unique(settings: list[Setting]) -> list[Setting]:
    seen: dict[str, Setting] = {}
    for s in settings:
        seen.setdefault(s.key, s)
    return list(seen.values())


def spp_ladder(user_spp: int, quick: bool) -> list[int]:
    """Samples per pixel to try: powers of two from 1 to ``max(16, 2 x user_spp)`` (at most 64;
    quick: 1, 4, 16), with the config's own."""
    if quick:
        ladder = {1, 4, 16}
    else:
        top = min(64, max(16, 2 * user_spp))
        ladder = {2**k for k in range(7) if 2**k <= top}
    return sorted(ladder | {user_spp})


def replaceable_loss(loss: Any) -> bool:
    """Whether LOI may replace the config's loss: a built-in image loss by name (``"l2"`` or
    ``{type: l2, ...}``); a loss of the user's own class is left alone."""
    name = loss.get("type") if isinstance(loss, dict) else loss
    return isinstance(name, str) and name in IMAGE_LOSSES


def _normalised(spec: Any) -> Optional[dict[str, Any]]:
    """A sampler/denoiser value as a dict, ``None`` when off (absent or ``{type: none}``)."""
    if spec is None or (isinstance(spec, dict) and spec.get("type") in (None, "none")):
        return None
    return dict(spec) if isinstance(spec, dict) else spec


def _include(options: list[Optional[dict[str, Any]]], own: Optional[dict[str, Any]]) -> None:
    """Put the config's own ``own`` among ``options``: in place of the option it equals but for
    its ``seed`` (one setting, one row), else at the end."""
    if own is None:
        return
    same = [i for i, o in enumerate(options) if o is not None and {k: v for k, v in o.items() if k != "seed"} ==
            {k: v for k, v in own.items() if k != "seed"}]
    if same:
        options[same[0]] = own
    else:
        options.append(own)


def config_spp(model: dict[str, Any]) -> int:
    """The config's ``model.spp`` (default 8); a schedule ``{spp: first step}`` is refused: a
    setting is one spp for the whole run."""
    spp = model.get("spp", 8)
    if isinstance(spp, dict):
        raise ValueError(f"torchir tune tries one spp for a whole run, and model.spp is a schedule {spp}: "
                         f"tune the config with one count (e.g. spp: {next(iter(spp))}), then put the schedule back")
    return int(spp)


def enumerate_space(model: dict[str, Any], scene: Any, loss_fn: Any, pixel_targets_ok: bool, quick: bool) -> Space:
    """The options for a config's ``model`` arguments.

    Args:
        model: the config's ``InverseRenderingModule`` arguments.
        scene: its loaded :class:`torchir.Scene` (ReSTIR's scene check).
        loss_fn: its loss module (per-pixel or not).
        pixel_targets_ok: whether the targets allow pixel sampling (no clipping).
        quick: fewer spp rungs and one pixel budget (every family of sampler and denoiser stays).
    """
    from ..functions.render_pixels import integrator_problem
    from ..integrators.restir_di import check_scene

    spp = config_spp(model)
    grad = model.get("spp_grad")
    sampler, denoiser = _normalised(model.get("sampler")), _normalised(model.get("denoiser"))
    notes: list[str] = []
    samplers: list[Optional[dict[str, Any]]] = [None]
    pixel_problem = integrator_problem(scene)
    if pixel_problem is not None:
        notes.append(f"pixel sampling: left out, {pixel_problem}")
    elif getattr(loss_fn, "pixelwise", False) and hasattr(loss_fn, "pixel_terms"):
        if pixel_targets_ok:
            fractions = (0.25,) if quick else (0.25, 0.05)
            kinds = ("uniform", "loss", "adaptive")  # every family, quick too (quick: one budget)
            samplers += [{"type": k, "budget": f, **PIXEL} for f in fractions for k in kinds
                         if not (k == "loss" and f != fractions[-1])]
        else:
            notes.append("pixel sampling: left out, the targets clip (pixel sampling compares unclipped pixels)")
    else:
        notes.append(f"pixel sampling: left out, the loss {type(loss_fn).__name__} couples pixels")
    try:
        check_scene(scene.mi_scene)
    except ValueError as error:
        notes.append(f"ReSTIR: left out, {error}")
    else:
        presets = ("auto", "persistent", "restir", "b2")  # every family, quick too: reuse across steps, in space, none
        samplers += [{"type": "restir", "preset": p} for p in presets]
    denoisers: list[Optional[dict[str, Any]]] = [None, TARGET_AWARE, CROSS_BILATERAL]  # every family, quick too
    _include(samplers, sampler)
    _include(denoisers, denoiser)
    losses: list[dict[str, Any]] = []
    user_loss = model.get("loss", "l2")
    if replaceable_loss(user_loss):
        losses.append(dict(LOI))
    else:
        name = user_loss.get("type") if isinstance(user_loss, dict) else user_loss
        notes.append(f"LOI: left out, the loss {name if isinstance(name, str) else type(user_loss).__name__} "
                     f"is {'LOI already' if name == 'loi' else 'not a built-in image loss'}")
    ratio = None if grad is None else float(grad) / spp
    space = Space(Setting(spp, sampler, denoiser, None, grad), spp_ladder(spp, quick), samplers, denoisers, losses, notes, ratio)
    return space
