"""Fast, exact tests of :mod:`torchir.training.cli`, written for the mutation audit: the
argument helpers are called directly; TorchirCLI's hooks are called on an instance made
without running LightningCLI (``object.__new__``) with jsonargparse Namespaces as configs and
stand-ins for the trainer and model; ``main`` runs with a recording stand-in for TorchirCLI.
No Lightning ``Trainer`` runs here.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from types import SimpleNamespace

import torchir  # (before torch: sets the OpenMP policy)

import pytest
from jsonargparse import Namespace
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

import torchir.training.cli as cli
from torchir.training.callbacks import CurvePlotter, ImageWriter
from torchir.training.cli import (
    TorchirCLI,
    _absolute,
    _map_sets,
    _newest_last_checkpoint,
    _one_set,
    _parse_value,
    main,
    split_parameter_sets,
)
from torchir.training.data import ViewDataModule
from torchir.training.module import InverseRenderingModule, NonFiniteLossError

FIELDS = ["init", "bounds", "lr", "transform", "seed", "truth", "parametrization", "resolution"]
SET_HELP = (
    f"--set takes KEY.FIELD=VALUE with FIELD one of {FIELDS}, e.g. --set 'red.reflectance.value.init=0.3'; got "
)


def test_fields():
    assert list(cli._FIELDS) == FIELDS


def test_parse_value():
    assert _parse_value("[0.3, 0.3]") == [0.3, 0.3]
    assert _parse_value("0.5") == 0.5
    assert _parse_value("sigmoid") == "sigmoid"
    assert _parse_value("null") is None


# ---------------------------------------------------------------- split_parameter_sets


def test_split_no_sets():
    argv = ["fit", "--config", "run.yaml", "--trainer.max_steps", "5"]
    assert split_parameter_sets(argv) == (argv, [])


def test_split_forms():
    argv = [
        "fit", "--set", "a.b.init=0.3", "--trainer.max_steps=5", "--set=c.lr=0.01",
        "--model.parameters", "{k: {seed: 3, transform: log}}", "--model.parameters={m: null}", "--x",
    ]
    rest, sets = split_parameter_sets(argv)
    assert rest == ["fit", "--trainer.max_steps=5", "--x"]
    assert sets == [("a.b", "init", 0.3), ("c", "lr", 0.01), ("k", "seed", 3), ("k", "transform", "log"), ("m", None, None)]


def test_command_line_paths_are_relative_to_the_working_directory(tmp_path, monkeypatch):
    """Paths typed on the command line resolve against the shell's folder (a config's own paths
    against the config's folder, test_resolve_paths): ``--model.scene``, ``--data.targets`` (one
    path or a list) and image files in ``--set KEY.init/truth``; names and numbers are kept."""
    import json

    monkeypatch.chdir(tmp_path)
    here = tmp_path.resolve()
    argv = ["fit", "--config", "cfg/run.yaml", "--model.scene", "scenes/a.xml", "--data.targets=[t/a.png, t/b.exr]",
            "--set", "k.init=tex.png", "--set", "k.truth=0.5", "--data.targets", "one.jpg"]
    rest, sets = split_parameter_sets(argv)
    assert rest[:4] == ["fit", "--config", "cfg/run.yaml", "--model.scene"]  # the config itself: Lightning's own rule
    assert rest[4] == str(here / "scenes" / "a.xml")
    assert rest[5] == "--data.targets" and json.loads(rest[6]) == [str(here / "t" / "a.png"), str(here / "t" / "b.exr")]
    assert rest[7:] == ["--data.targets", str(here / "one.jpg")]
    assert sets == [("k", "init", str(here / "tex.png")), ("k", "truth", 0.5)]
    assert split_parameter_sets(["--model.scene", "cbox"])[0] == ["--model.scene", "cbox"]  # a built-in name


def test_split_value_with_equals_sign():
    rest, sets = split_parameter_sets(["--set=k.init=[1, 2]"])
    assert rest == [] and sets == [("k", "init", [1, 2])]


@pytest.mark.parametrize("flag", ["--set", "--model.parameters"])
def test_split_missing_value(flag):
    with pytest.raises(ValueError, match=f"^{flag} needs a value$"):
        split_parameter_sets(["fit", flag])


def test_split_last_argument_with_value():
    assert split_parameter_sets(["--set", "k.seed=1"]) == ([], [("k", "seed", 1)])


def test_one_set():
    assert _one_set(" red.reflectance.value.init =[0.3, 0.3, 0.3]") == ("red.reflectance.value", "init", [0.3, 0.3, 0.3])
    assert _one_set("k.bounds=[0, 1]") == ("k", "bounds", [0, 1])
    assert _one_set("k.truth=") == ("k", "truth", None)
    assert _one_set("k.transform=a=b") == ("k", "transform", "a=b")  # the value may hold "="


@pytest.mark.parametrize("text", ["k.init", "init=0.3", ".init=0.3", "k.colour=1", "k.Init=1"])
def test_one_set_rejects(text):
    import re

    with pytest.raises(ValueError, match="^" + re.escape(SET_HELP + repr(text)) + "$"):
        _one_set(text)


def test_map_sets():
    assert _map_sets("{a: {init: 1, lr: 2}, b: {}, c: null}") == [("a", "init", 1), ("a", "lr", 2), ("b", None, None), ("c", None, None)]
    assert _map_sets("{}") == []


def test_map_sets_rejects():
    import re

    with pytest.raises(ValueError, match="^" + re.escape("--model.parameters takes a mapping {key: {field: value}}, got '[1]'") + "$"):
        _map_sets("[1]")
    msg = f"--model.parameters['a'] must be a mapping of {FIELDS}, got 0.5"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        _map_sets("{a: 0.5}")
    msg = f"--model.parameters['a'] has unknown field 'colour'; allowed: {FIELDS}"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        _map_sets("{a: {init: 1, colour: 2}}")


# ---------------------------------------------------------------- paths


def test_absolute(tmp_path):
    assert _absolute("/abs/x.xml", tmp_path) == "/abs/x.xml"
    assert _absolute("/abs/./d/../x.xml", tmp_path) == "/abs/./d/../x.xml"  # kept as given
    assert _absolute("sub/../x.xml", tmp_path) == str(tmp_path.resolve() / "x.xml")


def test_newest_last_checkpoint(tmp_path):
    import re

    msg = (
        f"--ckpt_path last: no run of {str(tmp_path / 'exp')!r} has checkpoints/last.ckpt yet; "
        "start without --ckpt_path, or give a checkpoint file"
    )
    with pytest.raises(FileNotFoundError, match="^" + re.escape(msg) + "$"):
        _newest_last_checkpoint(str(tmp_path), "exp")
    now = time.time()
    paths = {}
    for version, age in (("version_0", 30), ("version_2", 10), ("version_1", 20)):
        p = tmp_path / "exp" / version / "checkpoints" / "last.ckpt"
        p.parent.mkdir(parents=True)
        p.write_text("x")
        os.utime(p, (now - age, now - age))
        paths[version] = p
    (tmp_path / "exp" / "version_3" / "checkpoints").mkdir(parents=True)
    (tmp_path / "exp" / "version_3" / "checkpoints" / "other.ckpt").write_text("x")
    assert _newest_last_checkpoint(str(tmp_path), "exp") == paths["version_2"]
    os.utime(paths["version_0"], (now, now))  # newest by time, not by name
    assert _newest_last_checkpoint(str(tmp_path), "exp") == paths["version_0"]


def test_resolve_paths(tmp_path):
    base = tmp_path / "cfg"
    config = Namespace(
        model=Namespace(
            scene="scenes/room.xml",
            parameters={
                "a": {"init": "tex/a.png", "truth": "0.5"},
                "b": Namespace(init="b.EXR", truth="/abs/t.exr", lr=None),
                "c": {"init": 0.3},
                "d": Namespace(init=None, truth=[1, 2]),
            },
            derived={"x": {"function": "fn.py:make"}, "y": {"function": "pkg.mod:make"}, "z": "not a dict",
                     "w": {"function": None}},
        ),
        data=Namespace(targets=["t0.exr", "/abs/t1.png"]),
    )
    TorchirCLI._resolve_paths(config, base)
    r = str(base.resolve())
    assert config.model.scene == f"{r}/scenes/room.xml"
    assert config.data.targets == [f"{r}/t0.exr", "/abs/t1.png"]
    params = config.model.parameters
    assert params["a"] == {"init": f"{r}/tex/a.png", "truth": "0.5"}
    assert params["b"].init == f"{r}/b.EXR" and params["b"].truth == "/abs/t.exr"
    assert params["c"] == {"init": 0.3}
    assert params["d"].init is None and params["d"].truth == [1, 2]
    derived = config.model.derived
    assert derived["x"] == {"function": f"{r}/fn.py:make"}
    assert derived["y"] == {"function": "pkg.mod:make"}
    assert derived["z"] == "not a dict" and derived["w"] == {"function": None}


def test_resolve_paths_builtin_and_empty(tmp_path):
    config = Namespace(model=Namespace(scene="cbox", parameters=None, derived=None), data=Namespace(targets=None))
    TorchirCLI._resolve_paths(config, tmp_path)
    assert config.model.scene == "cbox" and config.data.targets is None
    config = Namespace(model=Namespace(scene={"type": "scene"}, parameters={}, derived={}), data=Namespace(targets=[]))
    TorchirCLI._resolve_paths(config, tmp_path)
    assert config.model.scene == {"type": "scene"} and config.data.targets == []
    config = Namespace(model=Namespace(scene="room.xml.bak", parameters={}, derived={}), data=Namespace(targets=None))
    TorchirCLI._resolve_paths(config, tmp_path)
    assert config.model.scene == "room.xml.bak"


def test_resolve_paths_truth_and_objects(tmp_path):
    config = Namespace(
        model=Namespace(scene="cbox", derived={},
                        parameters={"a": {"init": 0.5, "truth": "t.exr"}, "b": SimpleNamespace(init="i.png"),
                                    "c": SimpleNamespace(init=0.1, truth="u.hdr")}),
        data=Namespace(targets=None),
    )
    TorchirCLI._resolve_paths(config, tmp_path)
    r = str(tmp_path.resolve())
    params = config.model.parameters
    assert params["a"] == {"init": 0.5, "truth": f"{r}/t.exr"}
    assert params["b"].init == f"{r}/i.png" and not hasattr(params["b"], "truth")
    assert params["c"].init == 0.1 and params["c"].truth == f"{r}/u.hdr"


def test_resolve_paths_derived_last_colon(tmp_path):
    config = Namespace(model=Namespace(scene="cbox", parameters={}, derived={"x": {"function": "sub/..:x.py:fn"}}),
                       data=Namespace(targets=None))
    TorchirCLI._resolve_paths(config, tmp_path)
    # the file is everything before the last ":" (a name "..:x.py" in sub/, not sub's parent)
    assert config.model.derived["x"]["function"] == f"{tmp_path.resolve()}/sub/..:x.py:fn"


def test_resolve_paths_derived_rsplit(tmp_path):
    config = Namespace(model=Namespace(scene="cbox", parameters={}, derived={"x": {"function": "a:b.py:fn"}}),
                       data=Namespace(targets=None))
    TorchirCLI._resolve_paths(config, tmp_path)
    assert config.model.derived["x"]["function"] == f"{tmp_path.resolve()}/a:b.py:fn"


# ---------------------------------------------------------------- merging --set


def bare_cli(**attrs) -> TorchirCLI:
    obj = object.__new__(TorchirCLI)
    for k, v in attrs.items():
        setattr(obj, k, v)
    return obj


DEFAULTS = {"init": 0.5, "bounds": None, "lr": None, "transform": "none", "seed": 0, "truth": None, "parametrization": None,
            "resolution": None}


def test_merge_parameter_sets():
    existing_ns = Namespace(**{**DEFAULTS, "init": 0.1})
    config = Namespace(model=Namespace(parameters={"a": {"init": 0.2, "lr": 0.5}, "b": existing_ns, "keep": {"init": 1}}))
    c = bare_cli(parameter_sets=[("a", "seed", 4), ("b", "bounds", [0, 2]), ("new", "init", [1, 2]), ("empty", None, None),
                                 ("b", "bounds", None)])
    c._merge_parameter_sets(config)
    params = config.model.parameters
    assert isinstance(params["a"], Namespace)
    assert dict(vars(params["a"])) == {**DEFAULTS, "init": 0.2, "lr": 0.5, "seed": 4}
    assert params["b"] is existing_ns and params["b"].bounds is None and params["b"].init == 0.1
    assert dict(vars(params["new"])) == {**DEFAULTS, "init": [1, 2]}
    assert dict(vars(params["empty"])) == DEFAULTS
    assert params["keep"] == {"init": 1}
    assert list(params) == ["a", "b", "keep", "new", "empty"]


def test_merge_bounds_tuple():
    config = Namespace(model=Namespace(parameters=None))
    bare_cli(parameter_sets=[("k", "bounds", [0, 1]), ("j", "init", [0, 1])])._merge_parameter_sets(config)
    assert config.model.parameters["k"].bounds == (0, 1)
    assert config.model.parameters["j"].init == [0, 1]


def test_merge_nothing():
    params = {"a": {"init": 1}}
    config = Namespace(model=Namespace(parameters=params))
    bare_cli(parameter_sets=[])._merge_parameter_sets(config)
    assert config.model.parameters is params


# ---------------------------------------------------------------- before_instantiate_classes


def fit_config(tmp_path, ckpt_path=None, logger=None, config_file=True):
    files = [SimpleNamespace(absolute=str(tmp_path / "first" / "a.yaml")),
             SimpleNamespace(absolute=str(tmp_path / "cfg" / "run.yaml"))] if config_file else None
    return Namespace(
        config=files, ckpt_path=ckpt_path,
        model=Namespace(scene="room.xml", parameters={}, derived={}),
        data=Namespace(targets=None), trainer=Namespace(logger=logger),
    )


def test_before_instantiate_relative_to_last_config(tmp_path):
    config = fit_config(tmp_path)
    c = bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[("k", "seed", 1)])
    c.before_instantiate_classes()
    assert config.model.scene == str(tmp_path / "cfg" / "room.xml")
    assert config.model.parameters["k"].seed == 1
    assert config.ckpt_path is None


def test_before_instantiate_three_configs_and_no_attributes(tmp_path):
    config = fit_config(tmp_path)
    config.config = [SimpleNamespace(absolute=str(tmp_path / d / "c.yaml")) for d in ("one", "two", "three")]
    bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
    assert config.model.scene == str(tmp_path / "three" / "room.xml")
    # a config without "config" and "ckpt_path" entries
    bare = Namespace(model=Namespace(scene="cbox", parameters={}, derived={}), data=Namespace(targets=None))
    bare_cli(config=Namespace(fit=bare), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
    assert not hasattr(bare, "ckpt_path")


def test_before_instantiate_no_subcommand_no_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = fit_config(tmp_path, config_file=False)
    c = bare_cli(config=config, subcommand=None, parameter_sets=[])
    c.before_instantiate_classes()
    assert config.model.scene == str(tmp_path.resolve() / "room.xml")


def make_last(tmp_path, save_dir, name, version="version_0"):
    p = Path(save_dir) / name / version / "checkpoints" / "last.ckpt"
    p.parent.mkdir(parents=True)
    p.write_text("x")
    return p


@pytest.mark.parametrize("as_list", [True, False])
def test_before_instantiate_ckpt_last(tmp_path, capsys, as_list):
    last = make_last(tmp_path, str(tmp_path / "out"), "exp")
    logger = Namespace(class_path="CSVLogger", init_args=Namespace(save_dir=str(tmp_path / "out"), name="exp"))
    config = fit_config(tmp_path, ckpt_path="last", logger=[logger] if as_list else logger)
    bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
    assert config.ckpt_path == str(last)
    assert capsys.readouterr().out == f"[torchir] resuming from {last}\n"


def test_before_instantiate_ckpt_last_defaults(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    last = make_last(tmp_path, "results", "torchir")
    for logger in (None, [], Namespace(class_path="X", init_args=Namespace()),
                   Namespace(class_path="X", init_args=Namespace(version=1))):
        config = fit_config(tmp_path, ckpt_path="last", logger=logger)
        bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
        assert config.ckpt_path == "results/torchir/version_0/checkpoints/last.ckpt"
    assert last.is_file()
    capsys.readouterr()


def test_before_instantiate_ckpt_last_partial_logger_args(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    a = make_last(tmp_path, "results", "exp")
    b = make_last(tmp_path, str(tmp_path / "out"), "torchir")
    for init_args, last in ((Namespace(name="exp"), "results/exp/version_0/checkpoints/last.ckpt"),
                            (Namespace(save_dir=str(tmp_path / "out")), str(b))):
        config = fit_config(tmp_path, ckpt_path="last", logger=Namespace(class_path="X", init_args=init_args))
        bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
        assert config.ckpt_path == last
    assert a.is_file()
    capsys.readouterr()


def test_before_instantiate_ckpt_other(tmp_path):
    config = fit_config(tmp_path, ckpt_path="some.ckpt")
    bare_cli(config=Namespace(fit=config), subcommand="fit", parameter_sets=[]).before_instantiate_classes()
    assert config.ckpt_path == "some.ckpt"
    config = fit_config(tmp_path, ckpt_path="last")
    bare_cli(config=Namespace(validate=config), subcommand="validate", parameter_sets=[]).before_instantiate_classes()
    assert config.ckpt_path == "last"


# ---------------------------------------------------------------- parser, trainer, after_fit


class RecordingParser:
    def __init__(self) -> None:
        self.calls = []

    def add_lightning_class_args(self, cls, name):
        self.calls.append(("class", cls, name))

    def set_defaults(self, defaults):
        self.calls.append(("defaults", defaults))


def test_add_arguments_to_parser():
    parser = RecordingParser()
    bare_cli().add_arguments_to_parser(parser)
    assert parser.calls == [
        ("class", ModelCheckpoint, "checkpoint"),
        ("defaults", {"checkpoint.save_last": True, "checkpoint.every_n_train_steps": 50, "checkpoint.save_top_k": -1}),
        ("class", ImageWriter, "images"),
        ("class", CurvePlotter, "curves"),
    ]


@pytest.fixture()
def super_trainer(monkeypatch):
    made = {}

    def instantiate(self, **kwargs):
        made["kwargs"] = kwargs
        return made["trainer"]

    monkeypatch.setattr(LightningCLI, "instantiate_trainer", instantiate)
    return made


def test_instantiate_trainer_adds_tensorboard(tmp_path, super_trainer, monkeypatch):
    monkeypatch.setattr(cli, "_tensorboard_installed", lambda: True)
    csv = CSVLogger(save_dir=str(tmp_path), name="exp", version=3)
    super_trainer["trainer"] = SimpleNamespace(loggers=[csv])
    trainer = bare_cli().instantiate_trainer(a=1)
    assert super_trainer["kwargs"] == {"a": 1}
    assert trainer is super_trainer["trainer"]
    assert len(trainer.loggers) == 2 and trainer.loggers[0] is csv
    tb = trainer.loggers[1]
    assert isinstance(tb, TensorBoardLogger)
    assert (tb.save_dir, tb.name, tb.version) == (str(tmp_path), "exp", 3)


def test_instantiate_trainer_leaves_loggers(tmp_path, super_trainer, monkeypatch):
    csv = CSVLogger(save_dir=str(tmp_path), name="exp", version=0)
    tb = TensorBoardLogger(save_dir=str(tmp_path), name="exp", version=0)
    monkeypatch.setattr(cli, "_tensorboard_installed", lambda: False)
    super_trainer["trainer"] = SimpleNamespace(loggers=[csv])
    assert bare_cli().instantiate_trainer().loggers == [csv]
    monkeypatch.setattr(cli, "_tensorboard_installed", lambda: True)
    for loggers in ([], [tb], [tb, csv], [csv, tb]):
        super_trainer["trainer"] = SimpleNamespace(loggers=list(loggers))
        assert bare_cli().instantiate_trainer().loggers == list(loggers)


def test_tensorboard_installed(monkeypatch):
    import importlib.util

    asked = []
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: asked.append(name) or None)
    assert cli._tensorboard_installed() is False
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: asked.append(name) or object())
    assert cli._tensorboard_installed() is True
    assert asked == ["tensorboard", "tensorboard"]


def test_after_fit(capsys):
    model = SimpleNamespace(nonfinite=None, results_dir="/runs/v0",
                            step_metrics={"loss": 0.000123456, "seconds_per_step": 2.0, "param_error": 12345.6, "image_error": 1})
    c = bare_cli(model=model, trainer=SimpleNamespace(is_global_zero=True, global_step=7))
    c.after_fit()
    assert capsys.readouterr().out == (
        "[torchir] finished 7 steps (loss 0.0001235, param_error 1.235e+04, image_error 1); outputs in /runs/v0\n"
    )
    c.trainer.is_global_zero = False
    c.after_fit()
    assert capsys.readouterr().out == ""
    model.nonfinite = "loss is nan at step 3"
    with pytest.raises(NonFiniteLossError, match="^loss is nan at step 3$"):
        c.after_fit()


# ---------------------------------------------------------------- main


class FakeCLI:
    calls: list = []
    error: BaseException | None = None
    parameter_sets: list = []

    def __init__(self, *args, **kwargs) -> None:
        FakeCLI.calls.append((args, kwargs, list(FakeCLI.parameter_sets)))
        if FakeCLI.error is not None:
            raise FakeCLI.error


@pytest.fixture()
def fake_cli(monkeypatch):
    FakeCLI.calls, FakeCLI.error, FakeCLI.parameter_sets = [], None, []
    monkeypatch.setattr(cli, "TorchirCLI", FakeCLI)
    return FakeCLI


def test_main_runs(fake_cli):
    assert main(["fit", "--set", "k.seed=2", "--trainer.max_steps", "3"]) == 0
    ((args, kwargs, sets),) = fake_cli.calls
    assert args == (InverseRenderingModule, ViewDataModule)
    assert sets == [("k", "seed", 2)]
    assert fake_cli.parameter_sets == []  # reset afterwards
    assert kwargs["args"] == ["fit", "--trainer.max_steps", "3"]
    defaults = kwargs["trainer_defaults"]
    assert set(defaults) == {"logger", "accelerator", "log_every_n_steps", "max_steps", "enable_model_summary"}
    assert defaults["log_every_n_steps"] == 1 and defaults["max_steps"] == 100
    assert defaults["accelerator"] == torchir.backend.device()  # where the variant's images are
    assert defaults["enable_model_summary"] is False  # its table ("Total FLOPs: 0") is not a run's console
    (logger,) = defaults["logger"]  # a class_path default: a lazy instance failed in configs without a logger
    assert logger == {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "results", "name": "torchir"}}
    assert kwargs["save_config_kwargs"] == {"overwrite": False}
    assert kwargs["seed_everything_default"] == 0
    assert kwargs["auto_configure_optimizers"] is False
    assert set(kwargs) == {"args", "trainer_defaults", "save_config_kwargs", "seed_everything_default", "auto_configure_optimizers"}


def test_main_sys_argv(fake_cli, monkeypatch):
    monkeypatch.setattr(cli.sys, "argv", ["torchir", "fit", "--x", "1"])
    assert main() == 0
    assert fake_cli.calls[0][1]["args"] == ["fit", "--x", "1"]


def test_main_bad_set(fake_cli, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--set"])
    assert exit_info.value.code == 2 and exit_info.value.__cause__ is None and exit_info.value.__suppress_context__
    assert capsys.readouterr().err == "torchir: error: --set needs a value\n"
    assert fake_cli.calls == []


@pytest.mark.parametrize(
    "error, message",
    [
        (KeyError("no parameter 'x'"), "no parameter 'x'"),
        (KeyError(), ""),
        (ValueError("bad value"), "bad value"),
        (FileNotFoundError("no file"), "no file"),
        (TypeError("bad type"), "bad type"),
        (AttributeError("no attr"), "no attr"),
        (NonFiniteLossError("nan"), "nan"),
    ],
)
def test_main_reported_errors(fake_cli, capsys, error, message):
    fake_cli.error = error
    assert main(["fit", "--set", "k.seed=1"]) == 1
    assert capsys.readouterr().err == f"torchir: error: {message}\n"
    assert fake_cli.parameter_sets == []


def test_main_other_errors_propagate(fake_cli):
    fake_cli.error = RuntimeError("boom")
    with pytest.raises(RuntimeError, match="^boom$"):
        main(["fit", "--set", "k.seed=1"])
    assert fake_cli.parameter_sets == []


def test_fit_help_starts_with_torchir_s_own_flags(capsys):
    """``--set`` and the path rules were nowhere in ``torchir fit --help`` (1,682 lines of
    LightningCLI's): they come first, then Lightning's help."""
    from torchir.training.cli import main

    with pytest.raises(SystemExit) as done:
        main(["fit", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("torchir's additions") and "--set KEY.FIELD=VALUE" in out and "--ckpt_path last" in out
    assert out.index("--set KEY.FIELD=VALUE") < out.index("--trainer CONFIG")  # before Lightning's own
