"""Measuring one setting through the real trainer: its gradient error at the starting point and
its seconds per step, or its error decrease per second in a short training run.

Every trial is a ``lightning.pytorch.Trainer`` fit of an :class:`~torchir.training.InverseRenderingModule`
built from the config with the setting's ``model`` keys (no logger, no checkpoints), so what is
timed is what ``torchir fit`` runs. A gradient trial zeroes the gradients before every optimiser
step (Adam and SGD then leave the parameters where they are): each step is an independent
gradient estimate at the starting point, with the step seeds ``torchir fit`` uses.
"""
from __future__ import annotations

import contextlib
import gc
import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterator
from typing import Any, Callable, Optional

import torch

from .. import backend
from .config import UserConfig
from .space import Setting

__all__ = ["Reference", "Bench", "relative_errors", "split_error"]

REFERENCE_SEED_OFFSET = 7_654_321  # the reference's module seed: step seeds unlike any trial's


@dataclass
class Reference:
    """The config's own gradient at high spp: ``grad`` ``(P,)`` (all latents, flattened), the
    relative standard error of that mean (from its batches' spread), its spp and seconds."""

    grad: torch.Tensor
    relative_se: float
    spp: int
    batches: int
    seconds: float


def relative_errors(grads: list[torch.Tensor], reference: torch.Tensor) -> list[float]:
    """``||g_i - g_ref|| / ||g_ref||`` per gradient ``g_i`` (each ``(P,)``)."""
    norm = float(reference.norm())
    return [float((g - reference).norm()) / norm for g in grads]


def split_error(grads: list[torch.Tensor], reference: torch.Tensor, ref_se: float) -> tuple[float, float]:
    """A trial's relative gradient error split into ``(persistent, spread)``: ``spread`` is one
    step's error about the trial's mean gradient (what averages out over steps), ``persistent``
    the mean gradient's error beyond what ``n`` independent steps of that spread leave
    (``spread² / n``) and beyond the reference's own error ``ref_se`` (a bias, or error kept from
    step to step), removed in quadrature and floored at 0. Both relative to ``||reference||``;
    ``(nan, nan)`` for fewer than 2 steps."""
    n = len(grads)
    if n < 2:
        return math.nan, math.nan
    norm_sq = float(reference.norm()) ** 2
    stacked = torch.stack(grads).double() - reference.double()  # (n, P): each step's error
    mean = stacked.mean(0)
    spread_sq = float((stacked - mean).square().sum()) / (n - 1) / norm_sq
    persistent_sq = float(mean.square().sum()) / norm_sq - spread_sq / n - ref_se * ref_se
    return math.sqrt(max(persistent_sq, 0.0)), math.sqrt(spread_sq)


def _relative_se(grads: torch.Tensor) -> float:
    """Relative standard error of the mean of ``grads`` ``(n, P)``: ``||sd|| / sqrt(n) / ||mean||``."""
    norm = float(grads.mean(0).norm()) if len(grads) else 0.0
    if len(grads) < 2 or not norm > 0:  # a zero mean has no relative error: never "enough" (the caller says why)
        return math.inf
    return float(grads.std(0).norm()) / math.sqrt(len(grads)) / norm


@contextlib.contextmanager
def _captured() -> Iterator[list[str]]:
    """Lines a trial prints (e.g. ReSTIR's ``preset: auto`` decision), kept for its row
    instead of interleaving with the progress lines."""
    import io

    buffer = io.StringIO()
    lines: list[str] = []
    try:
        with contextlib.redirect_stdout(buffer):
            yield lines
    finally:
        lines.extend(line.strip() for line in buffer.getvalue().splitlines() if line.strip())


def _error_text(error: BaseException, limit: int = 300) -> str:
    text = f"{type(error).__name__}: {error}".replace("\n", " ")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _callbacks() -> tuple[type, type]:
    """The two recorders (built lazily: Lightning is imported by the first trial)."""
    import lightning.pytorch as pl

    from ..bench._common import sync_time as now

    class GradientRecorder(pl.Callback):
        """Per step after ``warmup``: the parameters' gradient ``(P,)`` and the step's seconds;
        every gradient is zeroed before the optimiser step, so the parameters never move."""

        def __init__(self, warmup: int, deadline: Optional[float],
                     enough: Optional[Callable[[list[torch.Tensor], float], bool]] = None) -> None:
            self.warmup, self.deadline, self.enough = warmup, deadline, enough
            self.start = time.perf_counter()
            self.grads: list[torch.Tensor] = []
            self.seconds: list[float] = []
            self.count = 0
            self.diagnostics: dict[str, float] = {}
            self.stage1_seconds: Optional[float] = None

        def on_train_batch_start(self, trainer, module, batch, batch_idx) -> None:
            sampler = module.sampler
            if self.count == 1 and getattr(sampler, "uses_stage1", False):
                sampler.last_update = None  # a Stage-1 refresh with compiled kernels, timed below
            self.t0 = now()

        def on_before_optimizer_step(self, trainer, module, optimizer) -> None:
            if self.count >= self.warmup:
                self.grads.append(torch.cat([p.latent.grad.detach().flatten().clone() if p.latent.grad is not None
                                             else torch.zeros(p.latent.numel()) for p in module.scene_parameters]))
            for p in module.scene_parameters:
                if p.latent.grad is not None:
                    p.latent.grad.zero_()

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
            seconds = now() - self.t0
            sampler = module.sampler
            if self.count == 0 and sampler is not None and hasattr(sampler, "diagnostics"):
                self.diagnostics = {k: float(v) for k, v in sampler.diagnostics().items()}
            if self.count == 1 and getattr(sampler, "uses_stage1", False):
                self.stage1_seconds = float(sampler.diagnostics().get("stage1_seconds", 0.0))
            if self.count >= self.warmup:
                self.seconds.append(seconds)
            self.count += 1
            if self.deadline is not None and time.perf_counter() > self.deadline and self.seconds:
                trainer.should_stop = True
            if self.enough is not None and self.enough(self.grads, time.perf_counter() - self.start):
                trainer.should_stop = True

    class WindowRecorder(pl.Callback):
        """Per step after the first (which holds kernel compilation): the seconds since the end
        of the first step when the step started, the error of the values it rendered and its
        loss; stops the run after ``seconds`` (or at ``deadline``)."""

        def __init__(self, seconds: float, deadline: Optional[float]) -> None:
            self.window, self.deadline = seconds, deadline
            self.times: list[float] = []
            self.errors: list[float] = []
            self.losses: list[float] = []
            self.count = 0
            self.metric = "image_error"

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
            t = now()
            if self.count == 0:
                self.start = t
            else:
                metrics = module.step_metrics
                if "param_error" in metrics:
                    self.metric = "param_error"
                self.times.append(self.last - self.start)
                self.errors.append(float(metrics.get(self.metric, metrics.get("image_error", metrics.get("loss", math.nan)))))
                self.losses.append(float(metrics.get("loss", math.nan)))
            self.last = t
            self.count += 1
            if self.count > 1 and (t - self.start >= self.window or (self.deadline is not None and time.perf_counter() > self.deadline)):
                trainer.should_stop = True

    return GradientRecorder, WindowRecorder


def decrease_per_second(times: list[float], values: list[float]) -> float:
    """How fast ``values`` fall: the mean of the first fifth minus the mean of the last fifth (at
    least one point each) over the time between their centres; NaN with fewer than 3 points."""
    n = len(values)
    if n < 3 or len(times) != n:
        return math.nan
    k = max(1, n // 5)
    span = statistics.fmean(times[-k:]) - statistics.fmean(times[:k])
    if span <= 0:
        return math.nan
    return (statistics.fmean(values[:k]) - statistics.fmean(values[-k:])) / span


class Bench:
    """Trials of one config: the plain reference, gradient trials and training trials. The
    targets are rendered (or read) once and shared by every trial.

    Args:
        user: the config (its ``model.seed`` seeds the trials; the reference gets another).
        workdir: Lightning's ``default_root_dir`` (nothing is written there: no logger).
    """

    def __init__(self, user: UserConfig, workdir: Path) -> None:
        self.user, self.workdir = user, workdir
        self.seed = int(user.model.get("seed", 0))
        self._data: Optional[dict[str, Any]] = None  # the loaded targets, shared by the trials
        self.reference: Optional[Reference] = None

    # ---------------------------------------------------------------------------- building
    def model_args(self, setting: Setting, seed: Optional[int] = None) -> dict[str, Any]:
        """The config's ``model`` arguments with ``setting``'s keys (``None``: removed)."""
        model = dict(self.user.model)
        for key, value in setting.model_changes().items():
            if value is None:
                model.pop(key, None)
            else:
                model[key] = value
        sampler = model.get("sampler")
        if isinstance(sampler, dict) and sampler.get("type") == "restir":
            # a trial's trainer runs a few steps: ReSTIR plans its burn-in for the config's run instead
            model["sampler"] = {"planned_steps": self.user.max_steps, **sampler}
        model["preview_spp"] = 1  # no preview is rendered: no logger
        model["seed"] = self.seed if seed is None else seed
        return model

    def module(self, setting: Setting, seed: Optional[int] = None) -> Any:
        """The ``InverseRenderingModule`` of ``setting`` (:meth:`model_args`)."""
        from ..training import InverseRenderingModule

        return InverseRenderingModule(**self.model_args(setting, seed))

    def datamodule(self, all_views: bool) -> Any:
        """A ``ViewDataModule`` of the config, holding the shared targets once they exist
        (``all_views``: every view each step, for gradient trials)."""
        from ..training import ViewDataModule

        args = dict(self.user.data)
        if all_views:
            args["views_per_step"] = None
        data = ViewDataModule(**args)
        if self._data is not None:
            for name, value in self._data.items():
                setattr(data, name, value)
        return data

    def _keep_data(self, data: Any) -> None:
        if self._data is None and data.targets:
            self._data = {name: getattr(data, name) for name in ("targets", "views", "lossy", "chroma", "quantisation")}

    def _fit(self, module: Any, data: Any, callbacks: list[Any], max_steps: int) -> None:
        """``Trainer.fit`` without logger, checkpoints or progress bar; keeps the targets it loaded."""
        import lightning.pytorch as pl

        from ..training import NonFiniteLossError

        pl.seed_everything(self.seed, verbose=False)
        trainer = pl.Trainer(accelerator=backend.device(), max_steps=max_steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False, log_every_n_steps=1, default_root_dir=str(self.workdir),
                             callbacks=callbacks, num_sanity_val_steps=0)
        trainer.fit(module, data)
        self._keep_data(data)
        if module.nonfinite is not None:
            raise NonFiniteLossError(module.nonfinite)

    # --------------------------------------------------------------------------- reference
    def make_reference(self, plain: Setting, batch_spp: int, target_se: float, max_seconds: float,
                       min_batches: int = 4, max_batches: int = 64) -> Reference:
        """The plain setting's gradient as the mean of batches of ``batch_spp`` samples per pixel
        (independent seeds), added until the mean's relative standard error (from the batches'
        spread) is at most ``target_se``, or ``max_seconds`` have passed (at least
        ``min_batches``, at most ``max_batches``)."""
        from dataclasses import replace

        GradientRecorder, _ = _callbacks()
        started = time.perf_counter()
        setting = replace(plain, spp=batch_spp, spp_grad=None)

        def enough(grads: list[torch.Tensor], seconds: float) -> bool:
            return len(grads) >= min_batches and (seconds >= max_seconds or _relative_se(torch.stack(grads)) <= target_se)

        gc.collect()
        module = self.config_module(setting, seed=self.seed + REFERENCE_SEED_OFFSET)
        recorder = GradientRecorder(0, None, enough)
        with _captured() as messages:
            self._fit(module, self.datamodule(all_views=True), [recorder], max_batches)
        del module
        grads = torch.stack(recorder.grads)
        norm = float(grads.mean(0).norm())
        if not norm > 0 or not math.isfinite(norm):
            raise ValueError("the gradient at the starting point is zero (or not finite): nothing to compare settings "
                             "by; does the init already equal the truth?")
        self.reference = Reference(grads.mean(0), _relative_se(grads), batch_spp * len(grads), len(grads),
                                   time.perf_counter() - started)
        self.reference_messages = messages
        return self.reference

    def config_module(self, setting: Setting, seed: Optional[int] = None) -> Any:
        """The module of ``setting``; a ``ValueError`` naming the config when it does not build
        (the config's own setting must)."""
        try:
            return self.module(setting, seed)
        except (ValueError, TypeError, KeyError) as error:
            raise ValueError(f"{self.user.path}: the config's own model does not build: {error}") from error

    # ---------------------------------------------------------------------------- trials
    def gradient_trial(self, setting: Setting, steps: int, warmup: int = 2, deadline: Optional[float] = None) -> dict[str, Any]:
        """``steps`` gradient steps of ``setting`` at the starting point after ``warmup`` untimed
        ones: per-step relative errors against the reference, RMS error with the reference's
        own error removed in quadrature, that error split into the part that averaged out over
        the steps and the part that persisted (:func:`split_error`), and seconds per step charged with one-off costs
        (ReSTIR's burn-in over ``trainer.max_steps``, a pixel sampler's Stage 1 over its
        ``refresh_every``). ``status`` is ``ran``, ``rejected`` (the module refused the
        setting) or ``failed``."""
        from ..bench.restir_report import error_beyond_reference

        if self.reference is None:
            raise RuntimeError("make_reference first")
        GradientRecorder, _ = _callbacks()
        row: dict[str, Any] = {"kind": "gradient", "setting": setting.label(), "key": setting.key, "steps": steps}
        recorder = GradientRecorder(warmup, deadline)
        ended, started = self._attempt(setting, row, recorder, True, warmup + steps)
        if ended is not None:
            return ended
        if not recorder.grads:
            return {**row, "status": "failed", "error": "no step was measured", "seconds": time.perf_counter() - started}
        errors = relative_errors(recorder.grads, self.reference.grad)
        error, error_se = error_beyond_reference(errors, self.reference.relative_se)
        persistent, spread = split_error(recorder.grads, self.reference.grad, self.reference.relative_se)
        step = statistics.median(recorder.seconds)
        charged = step + self._one_off(setting, recorder)
        return {**row, "status": "ran", "steps": len(errors), "relative_errors": errors, "gradient_error": error,
                "gradient_error_sq_se": error_se, "persistent_error": persistent, "step_spread": spread,
                "step_seconds": recorder.seconds, "seconds_per_step": charged,
                "median_step_seconds": step, "seconds": time.perf_counter() - started}

    def _attempt(self, setting: Setting, row: dict[str, Any], recorder: Any, all_views: bool,
                 max_steps: int) -> tuple[Optional[dict[str, Any]], float]:
        """Build ``setting``'s module and fit it with ``recorder``: ``(ended, started)``, where
        ``ended`` is the finished row when the module refused the setting or the run failed
        (``None`` when it ran) and ``started`` the clock after the build."""
        module = self._build(setting, row)
        if module is None:
            return row, time.perf_counter()
        started = time.perf_counter()
        failure = self._run(module, self.datamodule(all_views=all_views), recorder, max_steps, row)
        del module
        if failure is not None:
            return {**row, "status": "failed", "error": failure, "seconds": time.perf_counter() - started}, started
        return None, started

    def _run(self, module: Any, data: Any, recorder: Any, max_steps: int, row: dict[str, Any]) -> Optional[str]:
        """Fit ``module``; the error's text when it fails (reported in the table: the search goes
        on). What the run prints joins ``row["messages"]``."""
        lines: list[str] = []
        try:
            with _captured() as lines:
                self._fit(module, data, [recorder], max_steps)
        except Exception as error:  # noqa: BLE001 - any failure of one setting is that setting's result
            return _error_text(error)
        finally:
            row["messages"] = row.get("messages", []) + lines
        return None

    def _one_off(self, setting: Setting, recorder: Any) -> float:
        """Seconds per step of one-off costs: ReSTIR's burn-in over the run, Stage 1 over its refresh period."""
        burn_in = recorder.diagnostics.get("time_burn_in", 0.0)
        extra = burn_in / self.user.max_steps if burn_in > 0 else 0.0
        if recorder.stage1_seconds is not None:
            extra += recorder.stage1_seconds / int((setting.sampler or {}).get("refresh_every", 20))
        return extra

    def _build(self, setting: Setting, row: dict[str, Any]) -> Any:
        """The module of ``setting``, or ``None`` with ``row`` marked rejected."""
        gc.collect()  # free the last trial's scene: the next gets its Dr.Jit ids, and its compiled kernels
        lines: list[str] = []
        try:
            with _captured() as lines:
                return self.module(setting)
        except (ValueError, TypeError, KeyError) as error:
            status = "unavailable" if _unknown_preset(error, setting) else "rejected"
            row.update(status=status, error=_error_text(error))
            return None
        finally:
            row["messages"] = lines

    def training_trial(self, setting: Setting, seconds: float, max_steps: int = 100_000,
                       deadline: Optional[float] = None) -> dict[str, Any]:
        """A real training run of ``setting`` for ``seconds`` of wall time after its first step
        (the config's views per step): its error (parameter RMSE where the truth is known, else
        the render's image MSE) and its loss against time, and how fast each falls
        (:func:`decrease_per_second`)."""
        _, WindowRecorder = _callbacks()
        row: dict[str, Any] = {"kind": "training", "setting": setting.label(), "key": setting.key, "window_seconds": seconds}
        recorder = WindowRecorder(seconds, deadline)
        ended, started = self._attempt(setting, row, recorder, False, max_steps)
        if ended is not None:
            return ended
        return {**row, "status": "ran", "metric": recorder.metric, "steps": recorder.count, "times": recorder.times,
                "errors": recorder.errors, "losses": recorder.losses,
                "decrease_per_second": decrease_per_second(recorder.times, recorder.errors),
                "loss_decrease_per_second": decrease_per_second(recorder.times, recorder.losses),
                "seconds": time.perf_counter() - started}


def _unknown_preset(error: BaseException, setting: Setting) -> bool:
    """Whether ``error`` says the setting's ReSTIR preset does not exist in this version."""
    sampler = setting.sampler or {}
    return sampler.get("type") == "restir" and "preset" in str(error) and repr(sampler.get("preset")) in str(error)

