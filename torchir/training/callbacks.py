"""Lightning callbacks of an inverse-rendering run: projection, timing, the NaN guard, images
and curves. Outputs go to the run's folder (the logger's version directory)."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch

from lightning.pytorch.callbacks import TQDMProgressBar

from ..imageio import write_image

__all__ = ["ParameterProjection", "StepTimer", "NonFiniteLossGuard", "ImageWriter", "CurvePlotter", "ResultWriter", "StepProgressBar"]


class ParameterProjection(pl.Callback):
    """Clamp every optimised parameter to its bounds after each optimiser step."""

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        pl_module.project_parameters()


class StepTimer(pl.Callback):
    """Log ``seconds_per_step``: wall time of a training step (render, loss, backward, update),
    less the module's ``diagnostic_seconds`` (the mesh distances of a logged row: a measurement
    of the run, not part of its step)."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        pl_module.diagnostic_seconds = 0.0
        self._start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        seconds = time.perf_counter() - self._start - pl_module.diagnostic_seconds
        pl_module.step_metrics["seconds_per_step"] = seconds  # written with the step's row
        if trainer.world_size > 1:
            pl_module.log("seconds_per_step", seconds, on_step=True, on_epoch=False, batch_size=1)


class NonFiniteLossGuard(pl.Callback):
    """When the loss turns NaN/Inf, save the (still good) state as ``last-good.ckpt`` and stop."""

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if pl_module.nonfinite is None:
            return
        path = Path(pl_module.results_dir) / "checkpoints" / "last-good.ckpt"
        trainer.save_checkpoint(path)
        pl_module.nonfinite += f"; the last good state is in {path}"
        trainer.should_stop = True


def _interrupted(exception: BaseException) -> bool:
    """Ctrl-C: the run stops between steps, with a state worth keeping."""
    return isinstance(exception, KeyboardInterrupt)


class ImageWriter(pl.Callback):
    """Write target, initial, current and final images of every view (PNG, tone-mapped; EXR, linear).

    Files: ``images/{target,initial,current,final}_v{view}.{png,exr}`` in the run folder;
    ``current`` is rewritten every ``every_n_steps`` steps.

    Args:
        every_n_steps: how often ``current`` is rewritten (0: never).
        exr: also write linear EXR files.
        max_views: write at most this many views.
    """

    def __init__(self, every_n_steps: int = 50, exr: bool = True, max_views: int = 4) -> None:
        self.every_n_steps, self.exr, self.max_views = every_n_steps, exr, max_views

    def _write(self, trainer, pl_module, kind: str, images: dict[int, torch.Tensor]) -> None:
        if not trainer.is_global_zero:
            return
        folder = Path(pl_module.results_dir) / "images"
        folder.mkdir(parents=True, exist_ok=True)
        for view, image in images.items():
            write_image(folder / f"{kind}_v{view}.png", image)
            if self.exr:
                write_image(folder / f"{kind}_v{view}.exr", image)

    def _views(self, trainer) -> list[int]:
        return list(trainer.datamodule.views)[: self.max_views]

    def _previews(self, trainer, pl_module) -> dict[int, torch.Tensor]:
        return {v: pl_module.preview(v) for v in self._views(trainer)}

    def on_train_start(self, trainer, pl_module) -> None:
        data = trainer.datamodule
        self._write(trainer, pl_module, "target", {v: t for v, t in zip(data.views, data.targets) if v in self._views(trainer)})
        if trainer.global_step == 0:
            self._write(trainer, pl_module, "initial", self._previews(trainer, pl_module))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.every_n_steps and trainer.global_step % self.every_n_steps == 0 and trainer.is_global_zero:
            self._write(trainer, pl_module, "current", self._previews(trainer, pl_module))

    def on_train_end(self, trainer, pl_module) -> None:
        if trainer.is_global_zero:
            self._write(trainer, pl_module, "final", self._previews(trainer, pl_module))

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        if _interrupted(exception):
            self.on_train_end(trainer, pl_module)


class CurvePlotter(pl.Callback):
    """Keep the per-step metrics and write ``curves.png`` (loss, image and parameter error, and
    a mesh's Chamfer/Hausdorff distances to its truth mesh on the steps that log them, against
    steps and against wall time) at the end. Its history is saved in checkpoints, so a
    resumed run plots the whole trajectory."""

    METRICS = ("loss", "image_error", "param_error")
    PREFIXES = ("chamfer/", "hausdorff/")  # per-parameter metrics, plotted where a step has them

    def __init__(self) -> None:
        self.history: list[dict[str, float]] = []
        self._elapsed = 0.0

    def on_train_start(self, trainer, pl_module) -> None:
        self._start = time.perf_counter() - self._elapsed

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        metrics = pl_module.step_metrics
        # the step whose metrics were just logged (metrics.csv's numbering): global_step has moved on
        row = {"step": float(trainer.global_step - 1), "seconds": time.perf_counter() - self._start}
        row.update({m: float(v) for m, v in metrics.items() if m in self.METRICS or m.startswith(self.PREFIXES)})
        self.history.append(row)
        self._elapsed = row["seconds"]

    def on_train_end(self, trainer, pl_module) -> None:
        if trainer.is_global_zero and self.history:
            self.plot(Path(pl_module.results_dir) / "curves.png")

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        if _interrupted(exception):
            self.on_train_end(trainer, pl_module)

    def plot(self, path: Path) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        metrics = [m for m in self.METRICS if any(m in r for r in self.history)]
        metrics += sorted({m for r in self.history for m in r if m.startswith(self.PREFIXES)})
        fig, axes = plt.subplots(2, len(metrics), figsize=(4 * len(metrics), 6.5), squeeze=False)
        for col, metric in enumerate(metrics):
            rows = [r for r in self.history if metric in r]
            for row, x in enumerate(("step", "seconds")):
                ax = axes[row][col]
                ax.semilogy([r[x] for r in rows], [max(r[metric], 1e-12) for r in rows])
                # a mesh distance ("chamfer/<key>"): its key on a line of its own, so that titles do not overlap
                ax.set(xlabel="optimiser step" if x == "step" else "wall time (s)", ylabel=metric.split("/")[0],
                       title=f"{metric} vs {x}".replace("/", "\n"))
                ax.grid(alpha=0.3)
        # fixed margins: tight_layout draws the figure once more to measure it (most of a plot's time)
        fig.subplots_adjust(left=0.07 if len(metrics) < 3 else 0.05, right=0.98, bottom=0.08, top=0.92, wspace=0.4, hspace=0.45)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=100)
        plt.close(fig)

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history, "elapsed": self._elapsed}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.history, self._elapsed = list(state["history"]), float(state["elapsed"])


class ResultWriter(pl.Callback):
    """At the end of a run and on Ctrl-C: ``checkpoints/last.ckpt`` of the last step and
    ``result.yaml`` (recovered values in their own units, see :mod:`torchir.training.results`)."""

    def _finish(self, trainer, pl_module, interrupted: bool = False) -> None:
        from lightning.pytorch.callbacks import ModelCheckpoint

        from .results import write_results

        checkpoint = trainer.checkpoint_callback
        if not trainer.loggers and checkpoint is None:
            return  # a run without outputs (logger=False, no checkpointing): write nothing, as Lightning does
        if interrupted:
            print(f"\n[torchir] interrupted after step {trainer.global_step}: saving the state")
        if isinstance(checkpoint, ModelCheckpoint) and checkpoint.dirpath and trainer.global_step > 0:
            # ModelCheckpoint's own "last" file (it may carry a version suffix), registered with it so
            # that it never writes a second one (last-v1.ckpt) beside ours
            name = f"{ModelCheckpoint.CHECKPOINT_NAME_LAST}{ModelCheckpoint.FILE_EXTENSION}"
            path = checkpoint.last_model_path or str(Path(checkpoint.dirpath) / name)
            checkpoint.last_model_path = path
            trainer.save_checkpoint(path, weights_only=False)  # the full state, resumable
        if trainer.is_global_zero:
            path = write_results(pl_module, pl_module.results_dir, trainer.global_step, images=False)
            print(f"[torchir] recovered values: {path}")

    def on_train_end(self, trainer, pl_module) -> None:
        if pl_module.nonfinite is None:
            self._finish(trainer, pl_module)

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        if _interrupted(exception):
            self._finish(trainer, pl_module, interrupted=True)


class StepProgressBar(TQDMProgressBar):
    """One bar over optimiser steps (``step 120/150``, seconds per step, loss, parameter error),
    instead of Lightning's per-epoch bar: a run's epoch is one pass over the views, often one step."""

    SHOWN = ("loss", "param_error")

    def on_train_start(self, trainer, pl_module) -> None:
        import sys

        from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm

        self.train_progress_bar = Tqdm(
            desc="step", total=trainer.max_steps if trainer.max_steps > 0 else None, initial=trainer.global_step,
            position=2 * self.process_position, disable=self.is_disabled, leave=True, dynamic_ncols=True,
            file=sys.stdout, smoothing=0, bar_format="{desc} {n_fmt}/{total_fmt} |{bar}| [{elapsed}<{remaining}{postfix}]",
        )

    def on_train_epoch_start(self, trainer, *_: Any) -> None:
        pass  # no per-epoch reset

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        bar = self.train_progress_bar
        bar.n = trainer.global_step
        self._show(pl_module.step_metrics)

    def _show(self, metrics: dict) -> None:
        postfix = {}
        if "seconds_per_step" in metrics:
            postfix["s/step"] = f"{float(metrics['seconds_per_step']):.3g}"
        postfix.update({k: f"{float(metrics[k]):.4g}" for k in self.SHOWN if k in metrics})
        self.train_progress_bar.set_postfix(postfix, refresh=False)
        self.train_progress_bar.refresh()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        pass

    def on_train_end(self, trainer, pl_module) -> None:
        if self.train_progress_bar is not None:
            if hasattr(pl_module, "final_metrics") and pl_module.step_metrics:
                self._show(pl_module.final_metrics())  # the errors of the values the run ends with
            self.train_progress_bar.close()
