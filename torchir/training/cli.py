"""``torchir fit --config run.yaml``: LightningCLI over InverseRenderingModule and ViewDataModule.

Beyond Lightning's own options (``trainer.*``, ``model.*``, ``data.*``, ``--ckpt_path``,
dotted overrides such as ``--trainer.max_steps 50``), the parser has three callback sections
that are always on: ``checkpoint`` (ModelCheckpoint), ``images`` (ImageWriter) and ``curves``
(CurvePlotter). Every run writes into a new folder ``<save_dir>/<name>/version_<n>/``:
``config.yaml`` (the resolved config), ``metrics.csv``, ``images/``, ``curves.png`` and
``checkpoints/``; earlier runs are never overwritten.
"""
from __future__ import annotations

import importlib.util
import os
import sys
import warnings

from lightning.pytorch.callbacks import ModelCheckpoint
from jsonargparse import lazy_instance
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from .callbacks import CurvePlotter, ImageWriter
from .data import ViewDataModule
from .module import InverseRenderingModule, NonFiniteLossError

__all__ = ["TorchirCLI", "main"]

# Lightning 2.6 itself calls APIs that jsonargparse and torch deprecate; users cannot act on it.
os.environ.setdefault("JSONARGPARSE_DEPRECATION_WARNINGS", "off")
warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\).*")


def _tensorboard_installed() -> bool:
    return importlib.util.find_spec("tensorboard") is not None


class TorchirCLI(LightningCLI):
    """LightningCLI with torchir's defaults: CSV (+TensorBoard) logs, checkpoints, images, curves."""

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.save_last": True, "checkpoint.every_n_train_steps": 50, "checkpoint.save_top_k": -1})
        parser.add_lightning_class_args(ImageWriter, "images")
        parser.add_lightning_class_args(CurvePlotter, "curves")

    def instantiate_trainer(self, **kwargs):
        """Add a TensorBoard logger beside the CSV one, into the same run folder, when
        ``tensorboard`` is installed and the config has none."""
        trainer = super().instantiate_trainer(**kwargs)
        loggers = trainer.loggers
        if _tensorboard_installed() and loggers and isinstance(loggers[0], CSVLogger) and not any(
            isinstance(logger, TensorBoardLogger) for logger in loggers
        ):
            csv = loggers[0]
            trainer.loggers = [*loggers, TensorBoardLogger(save_dir=csv.save_dir, name=csv.name, version=csv.version)]
        return trainer

    def after_fit(self) -> None:
        model, trainer = self.model, self.trainer
        if model.nonfinite is not None:
            raise NonFiniteLossError(model.nonfinite)
        if trainer.is_global_zero:
            metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k in ("loss", "param_error", "image_error")}
            summary = ", ".join(f"{k} {v:.4g}" for k, v in metrics.items())
            print(f"[torchir] finished {trainer.global_step} steps ({summary}); outputs in {model.results_dir}")


def main(args: list[str] | None = None) -> int:
    """Run ``fit``/``validate`` through :class:`TorchirCLI`; returns a process exit code."""
    try:
        TorchirCLI(
            InverseRenderingModule,
            ViewDataModule,
            args=args,
            trainer_defaults={
                "logger": [lazy_instance(CSVLogger, save_dir="results", name="torchir")],
                "log_every_n_steps": 1,
                "max_steps": 100,
            },
            save_config_kwargs={"overwrite": False},
            seed_everything_default=0,
            auto_configure_optimizers=False,
        )
    except (NonFiniteLossError, FileNotFoundError, KeyError, ValueError, TypeError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"torchir: error: {message}", file=sys.stderr)
        return 1
    return 0
