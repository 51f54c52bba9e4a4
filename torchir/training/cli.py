"""``torchir fit --config run.yaml``: LightningCLI over InverseRenderingModule and ViewDataModule.

Beyond Lightning's own options (``trainer.*``, ``model.*``, ``data.*``, ``--ckpt_path``,
dotted overrides such as ``--trainer.max_steps 50``), the parser has three callback sections
that are always on: ``checkpoint`` (ModelCheckpoint), ``images`` (ImageWriter) and ``curves``
(CurvePlotter). Every run writes into a new folder ``<save_dir>/<name>/version_<n>/``:
``config.yaml`` (the resolved config), ``metrics.csv``, ``images/``, ``curves.png``,
``result.yaml`` (recovered values) and ``checkpoints/`` (``last.ckpt``: the last step, also on
Ctrl-C); earlier runs are never overwritten.

torchir's additions to the command line:

- Relative paths in a config (``model.scene``, ``data.targets``, a parameter's image ``init`` or
  ``truth``, a truth mesh, a derived parameter's ``function`` file) are relative to that config file; paths
  typed on the command line (``--model.scene``, ``--data.targets``, ``--set KEY.init=FILE``) are
  relative to the working directory, as a shell user expects (``results/`` is written there too).
- ``--set KEY.FIELD=VALUE`` sets one field of one ``model.parameters`` entry (Mitsuba keys
  contain dots, so ``--model.parameters.<key>.init`` cannot work):
  ``--set 'red.reflectance.value.init=[0.3, 0.3, 0.3]'``. ``--model.parameters '{...}'``
  merges into the config's map, field by field, instead of replacing it.
- ``--ckpt_path last`` resumes from the newest run's ``last.ckpt`` of the same logger
  ``save_dir``/``name``.
"""
from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

from .. import backend
from .callbacks import CurvePlotter, ImageWriter
from .data import ViewDataModule
from .module import InverseRenderingModule, NonFiniteLossError
from .parameters import ParameterConfig, is_image_file, is_mesh_file

__all__ = ["TorchirCLI", "main", "quiet_lightning", "split_parameter_sets"]

_FIELDS = tuple(ParameterConfig.__dataclass_fields__)


def _parse_value(text: str) -> Any:
    import yaml

    return yaml.safe_load(text)


def split_parameter_sets(argv: list[str]) -> tuple[list[str], list[tuple[str, str, Any]]]:
    """Take ``--set KEY.FIELD=VALUE`` and ``--model.parameters MAP`` out of ``argv``.

    Returns the remaining arguments and ``(key, field, value)`` triples to merge into
    ``model.parameters`` (a ``MAP`` entry ``{key: {field: value}}`` gives one triple per field).
    """
    rest, sets = [], []
    i = 0
    cwd = Path.cwd()
    while i < len(argv):
        arg = argv[i]
        name, eq, inline = arg.partition("=")
        if name in ("--set", "--model.parameters") + COMMAND_LINE_PATHS:
            if eq:
                value = inline
            elif i + 1 < len(argv):
                value, i = argv[i + 1], i + 1
            else:
                raise ValueError(f"{name} needs a value")
            if name == "--set":
                sets.append(_one_set(value))
            elif name == "--model.parameters":
                sets.extend(_map_sets(value))
            else:  # a path typed here: relative to the working directory, not to the config
                rest += [name, _paths_from(value, cwd, name == "--model.scene")]
        else:
            rest.append(arg)
        i += 1
    return rest, [(k, f, _absolute(v, cwd) if f in ("init", "truth") and _is_file(v) else v) for k, f, v in sets]


def _is_file(value: Any) -> bool:
    """Whether an ``init``/``truth`` value names a file (an image, or a truth mesh)."""
    return is_image_file(value) or is_mesh_file(value)


COMMAND_LINE_PATHS = ("--model.scene", "--data.targets")


def _paths_from(text: str, base: Path, scene: bool) -> str:
    """A ``--model.scene`` / ``--data.targets`` value with its relative file paths made absolute
    against ``base`` (a built-in scene's name is kept; a list stays a list)."""
    import json

    value = _parse_value(text)
    if scene:
        if isinstance(value, str) and ".py:" in text:
            return _absolute_callable(text, base)
        return _absolute(text, base) if isinstance(value, str) and text.endswith(".xml") else text
    if isinstance(value, str):
        return _absolute(value, base)
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return json.dumps([_absolute(v, base) for v in value])
    return text


def _one_set(text: str) -> tuple[str, str, Any]:
    path, eq, value = text.partition("=")
    key, _, field = path.strip().rpartition(".")
    if not eq or not key or field not in _FIELDS:
        raise ValueError(
            f"--set takes KEY.FIELD=VALUE with FIELD one of {list(_FIELDS)}, e.g. "
            f"--set 'red.reflectance.value.init=0.3'; got {text!r}"
        )
    return key, field, _parse_value(value)


def _map_sets(text: str) -> list[tuple[str, str, Any]]:
    mapping = _parse_value(text)
    if not isinstance(mapping, dict):
        raise ValueError(f"--model.parameters takes a mapping {{key: {{field: value}}}}, got {text!r}")
    out = []
    for key, fields in mapping.items():
        if fields is None or fields == {}:
            out.append((key, None, None))  # the entry with default fields
            continue
        if not isinstance(fields, dict):
            raise ValueError(f"--model.parameters[{key!r}] must be a mapping of {list(_FIELDS)}, got {fields!r}")
        for field, value in fields.items():
            if field not in _FIELDS:
                raise ValueError(f"--model.parameters[{key!r}] has unknown field {field!r}; allowed: {list(_FIELDS)}")
            out.append((key, field, value))
    return out


def _absolute(path: str, base: Path) -> str:
    return path if Path(path).is_absolute() else str((base / path).resolve())


def _absolute_callable(spec: str, base: Path) -> str:
    """``"file.py:attr"`` with the file made absolute against ``base``."""
    file, attr = spec.rsplit(":", 1)
    return f"{_absolute(file, base)}:{attr}"


def _newest_last_checkpoint(save_dir: str, name: str) -> Path:
    runs = sorted(Path(save_dir, name).glob("version_*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
    if not runs:
        raise FileNotFoundError(
            f"--ckpt_path last: no run of {str(Path(save_dir, name))!r} has checkpoints/last.ckpt yet; "
            f"start without --ckpt_path, or give a checkpoint file"
        )
    return runs[-1]

# Lightning 2.6 itself calls APIs that jsonargparse and torch deprecate; users cannot act on it.
os.environ.setdefault("JSONARGPARSE_DEPRECATION_WARNINGS", "off")
warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\).*")
# main() hands LightningCLI the command line without torchir's own flags (--set ...), as ``args``
warnings.filterwarnings("ignore", message=r".*LightningCLI's args parameter is intended to run from within Python.*")
# Lightning's and Fabric's info lines ("Seed set to 0", "GPU available: False", an advertisement for
# its cloud logger): a run's console is torchir's progress bar, warnings and result
QUIET_LOGGERS = ("lightning.pytorch", "lightning.fabric", "pytorch_lightning", "lightning_fabric")


@contextlib.contextmanager
def quiet_lightning():
    """Lightning's loggers at WARNING for the run (their levels restored after it)."""
    loggers = [logging.getLogger(name) for name in QUIET_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(max(logger.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _tensorboard_installed() -> bool:
    return importlib.util.find_spec("tensorboard") is not None


class TorchirCLI(LightningCLI):
    """LightningCLI with torchir's defaults: CSV (+TensorBoard) logs, checkpoints, images, curves,
    result.yaml; config-relative paths, ``--set`` and ``--ckpt_path last`` (module docstring)."""

    parameter_sets: list[tuple[str, str, Any]] = []  # from main(): merged into model.parameters

    def before_instantiate_classes(self) -> None:
        config = self.config[self.subcommand] if self.subcommand else self.config
        files = getattr(config, "config", None) or []
        base = Path(files[-1].absolute).parent if files else Path.cwd()
        self._resolve_paths(config, base)
        self._merge_parameter_sets(config)
        if self.subcommand == "fit" and getattr(config, "ckpt_path", None) == "last":
            logger = config.trainer.logger
            logger = logger[0] if isinstance(logger, list) and logger else logger
            args = getattr(logger, "init_args", None)
            save_dir, name = (getattr(args, "save_dir", "results"), getattr(args, "name", "torchir")) if args else ("results", "torchir")
            config.ckpt_path = str(_newest_last_checkpoint(save_dir, name))
            print(f"[torchir] resuming from {config.ckpt_path}")

    @staticmethod
    def _resolve_paths(config, base: Path) -> None:
        model, data = config.model, config.data
        if isinstance(model.scene, str) and model.scene.endswith(".xml"):
            model.scene = _absolute(model.scene, base)
        elif isinstance(model.scene, str) and ".py:" in model.scene:  # a factory file beside the config
            model.scene = _absolute_callable(model.scene, base)
        if data.targets:
            data.targets = [_absolute(str(t), base) for t in data.targets]
        for entry in (model.parameters or {}).values():
            for field in ("init", "truth"):
                value = entry.get(field) if isinstance(entry, dict) else getattr(entry, field, None)
                if _is_file(value):
                    if isinstance(entry, dict):
                        entry[field] = _absolute(value, base)
                    else:
                        setattr(entry, field, _absolute(value, base))
        for spec in (model.derived or {}).values():
            function = spec.get("function") if isinstance(spec, dict) else None
            if isinstance(function, str) and ".py:" in function:
                spec["function"] = _absolute_callable(function, base)

    def _merge_parameter_sets(self, config) -> None:
        from jsonargparse import Namespace

        if not self.parameter_sets:
            return
        parameters = dict(config.model.parameters or {})
        for key, field, value in self.parameter_sets:
            entry = parameters.get(key)
            if entry is None:
                entry = Namespace(**{f: getattr(ParameterConfig(), f) for f in _FIELDS})
            elif isinstance(entry, dict):
                entry = Namespace(**{**{f: getattr(ParameterConfig(), f) for f in _FIELDS}, **entry})
            if field is not None:
                setattr(entry, field, tuple(value) if field == "bounds" and value is not None else value)
            parameters[key] = entry
        config.model.parameters = parameters

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
            metrics = {k: float(v) for k, v in model.step_metrics.items()
                       if k in ("loss", "param_error", "image_error") or k.startswith("chamfer/")}
            summary = ", ".join(f"{k} {v:.4g}" for k, v in metrics.items())
            print(f"[torchir] finished {trainer.global_step} steps ({summary}); outputs in {model.results_dir}")


TORCHIR_HELP = """torchir's additions (the rest is LightningCLI's help, below):
  --set KEY.FIELD=VALUE   one field of one model.parameters entry, e.g.
                          --set 'red.reflectance.value.init=[0.3, 0.3, 0.3]' or --set red.reflectance.value.lr=0.05
                          (FIELD: init, bounds, lr, transform, seed, truth, parametrization, resolution; repeat for more)
  --model.parameters MAP  merged into the config's map field by field, e.g. --model.parameters '{KEY: {lr: 0.1}}'
  --ckpt_path last        resume from the newest run's checkpoints/last.ckpt (same logger save_dir/name)
  paths                   a config's relative paths are relative to the config file; paths typed here
                          (--model.scene, --data.targets, --set KEY.init=FILE) to the working directory
"""


def main(args: list[str] | None = None) -> int:
    """Run ``fit``/``validate`` through :class:`TorchirCLI`; returns a process exit code."""
    try:
        args, TorchirCLI.parameter_sets = split_parameter_sets(sys.argv[1:] if args is None else list(args))
    except ValueError as error:  # a command-line error, reported like the parser's own
        print(f"torchir: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    if args[:1] in (["fit"], ["validate"]) and any(a in ("-h", "--help") for a in args[1:]):
        print(TORCHIR_HELP)
    try:
        with quiet_lightning():
            _run_cli(args)
    except (NonFiniteLossError, FileNotFoundError, KeyError, ValueError, TypeError, AttributeError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"torchir: error: {message}", file=sys.stderr)
        return 1
    finally:
        TorchirCLI.parameter_sets = []
    return 0


def _run_cli(args: list[str]) -> None:
    TorchirCLI(
        InverseRenderingModule,
        ViewDataModule,
        args=args,
        trainer_defaults={
            # a class_path default, not jsonargparse's lazy_instance: a config without its own
            # logger got the lazy instance itself ("no attribute '_version'")
            "logger": [{"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "results", "name": "torchir"}}],
            "accelerator": backend.device(),  # "cpu" or "cuda": where the variant's tensors live
            "log_every_n_steps": 1,
            "max_steps": 100,
            "enable_model_summary": False,  # a table of nn.Modules with 0 FLOPs: our parameters are in result.yaml
        },
        save_config_kwargs={"overwrite": False},
        seed_everything_default=0,
        auto_configure_optimizers=False,
    )
