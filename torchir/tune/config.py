"""The user's YAML for ``torchir tune``: read it as ``torchir fit --config`` would, and write the
tuned copy beside it (``<stem>.tuned.yaml``) with the chosen settings filled in."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Optional

__all__ = ["UserConfig", "read_config", "tuned_path", "write_tuned", "TUNED_KEYS"]

TUNED_KEYS = ("spp", "spp_grad", "sampler", "denoiser", "loss")  # the model keys a tuned config may change


@dataclass
class UserConfig:
    """A run's config as ``InverseRenderingModule`` / ``ViewDataModule`` arguments.

    Attributes:
        path: the YAML file.
        raw: its parsed text, untouched (the tuned copy starts from it).
        model: ``InverseRenderingModule`` keyword arguments, relative paths made absolute
            against the config's folder (as ``torchir fit`` does).
        data: ``ViewDataModule`` keyword arguments, paths likewise (``{}`` when the config has
            no ``data`` section: synthetic targets).
        max_steps: ``trainer.max_steps`` (what a one-off cost such as ReSTIR's burn-in is
            spread over; 100, ``torchir fit``'s default, when absent).
    """

    path: Path
    raw: dict[str, Any]
    model: dict[str, Any]
    data: dict[str, Any] = field(default_factory=dict)
    max_steps: int = 100


def _section(raw: dict[str, Any], name: str, path: Path) -> dict[str, Any]:
    """``raw[name]`` as keyword arguments (a LightningCLI ``{class_path, init_args}`` form too)."""
    value = raw.get(name)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ValueError(f"{path}: '{name}' must be a mapping, got {type(value).__name__}")
    if "class_path" in value:
        return dict(value.get("init_args") or {})
    return dict(value)


def _instantiate(value: Any) -> Any:
    """A ``{class_path: ..., init_args: ...}`` mapping (a loss or denoiser by class path) built, as
    jsonargparse builds it for ``torchir fit``; anything else as is."""
    if not (isinstance(value, dict) and "class_path" in value):
        return value
    import importlib

    module, _, name = value["class_path"].rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as error:
        raise ValueError(f"cannot import {value['class_path']!r}: {error}") from None
    return cls(**(value.get("init_args") or {}))


def read_config(path: str | Path) -> UserConfig:
    """Read a ``torchir fit`` YAML file; ``FileNotFoundError``/``ValueError`` with the reason when
    it is missing, not YAML, or has no ``model`` section."""
    import yaml

    from ..training.cli import TorchirCLI

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config not found: {str(path)!r}")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ValueError(f"{path} is not valid YAML: {error}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("model"), dict):
        raise ValueError(f"{path} has no 'model' section: a torchir fit config has model: {{scene: ..., parameters: ...}}")
    model = copy.deepcopy(_section(raw, "model", path))
    data = copy.deepcopy(_section(raw, "data", path))
    unknown = sorted(set(model) - _arguments())
    if unknown:
        raise ValueError(f"{path}: unknown model key(s) {unknown}; InverseRenderingModule takes {sorted(_arguments())}")
    for key in ("loss", "denoiser"):
        if key in model:
            model[key] = _instantiate(model[key])
    # relative paths against the config's folder, by the same code torchir fit uses
    view = SimpleNamespace(model=SimpleNamespace(**{"scene": "cbox", "parameters": None, "derived": None, **model}),
                           data=SimpleNamespace(targets=data.get("targets")))
    TorchirCLI._resolve_paths(view, path.resolve().parent)
    for key in ("scene", "parameters", "derived"):
        if key in model:
            model[key] = getattr(view.model, key)
    if data.get("targets"):
        data["targets"] = view.data.targets
    trainer = _section(raw, "trainer", path)
    max_steps = trainer.get("max_steps")
    return UserConfig(path, raw, model, data, int(max_steps) if isinstance(max_steps, int) and max_steps > 0 else 100)


def _arguments() -> set[str]:
    import inspect

    from ..training import InverseRenderingModule

    return set(inspect.signature(InverseRenderingModule.__init__).parameters) - {"self"}


def tuned_path(config: str | Path) -> Path:
    """``<dir>/<stem>.tuned.yaml`` beside ``config``."""
    config = Path(config)
    return config.with_name(f"{config.stem}.tuned.yaml")


def write_tuned(user: UserConfig, changes: dict[str, Any], header: str, path: Optional[Path] = None) -> Path:
    """Write the user's YAML with the model keys of ``changes`` set (a value of ``None`` removes
    the key: no sampler, no denoiser) to ``path`` (default :func:`tuned_path`), ``header`` as
    its leading comment. Relative paths stay valid: the file sits beside the original."""
    import yaml

    unknown = sorted(set(changes) - set(TUNED_KEYS))
    if unknown:
        raise ValueError(f"tune changes only {TUNED_KEYS}, got {unknown}")
    raw = copy.deepcopy(user.raw)
    model = raw["model"]
    target = model["init_args"] if "class_path" in model and isinstance(model.get("init_args"), dict) else model
    for key, value in changes.items():
        if value is None:
            target.pop(key, None)
        else:
            target[key] = value
    path = tuned_path(user.path) if path is None else Path(path)
    comment = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    leading = []  # the original's opening comment (what the run is), kept under ours
    for line in user.path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            break
        leading.append(line + "\n")
    path.write_text(comment + "".join(leading) + yaml.safe_dump(raw, sort_keys=False, default_flow_style=None))
    return path
