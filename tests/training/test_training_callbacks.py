"""Fast, exact tests of :mod:`torchir.training.callbacks`, written for the mutation audit: each
callback hook is called directly with a stand-in trainer and module (namespaces with the
attributes the callbacks read), a fake clock and recording stand-ins for ``write_image``,
``save_checkpoint`` and ``write_results``. No Lightning ``Trainer`` runs here.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import torchir  # noqa: F401  (before torch: sets the OpenMP policy)

import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

import torchir.training.callbacks as callbacks
import torchir.training.results as results
from torchir.training.callbacks import (
    CurvePlotter,
    ImageWriter,
    NonFiniteLossGuard,
    ParameterProjection,
    ResultWriter,
    StepProgressBar,
    StepTimer,
    _interrupted,
)


class Clock:
    def __init__(self, *times: float) -> None:
        self.times = list(times)

    def perf_counter(self) -> float:
        return self.times.pop(0)


@pytest.fixture()
def clock(monkeypatch):
    fake = Clock()
    monkeypatch.setattr(callbacks, "time", fake)
    return fake


def trainer(**attrs) -> SimpleNamespace:
    base = {"world_size": 1, "global_step": 0, "is_global_zero": True, "should_stop": False, "loggers": [],
            "checkpoint_callback": None, "max_steps": 10}
    base.update(attrs)
    t = SimpleNamespace(**base)
    t.saved = []
    t.save_checkpoint = lambda path, **kw: t.saved.append((path, kw))
    return t


def module(tmp_path, **attrs) -> SimpleNamespace:
    m = SimpleNamespace(results_dir=str(tmp_path), nonfinite=None, step_metrics={}, **attrs)
    m.logged = []
    m.log = lambda name, value, **kw: m.logged.append((name, value, kw))
    return m


# ---------------------------------------------------------------- small callbacks


def test_parameter_projection():
    calls = []
    pl_module = SimpleNamespace(project_parameters=lambda: calls.append(1))
    ParameterProjection().on_train_batch_end(None, pl_module, None, None, 0)
    assert calls == [1]


@pytest.mark.parametrize("world", [1, 2])
def test_step_timer(tmp_path, clock, world):
    clock.times = [10.0, 10.75]
    t, m = trainer(world_size=world), module(tmp_path)
    timer = StepTimer()
    timer.on_train_batch_start(t, m, None, 0)
    timer.on_train_batch_end(t, m, None, None, 0)
    assert m.step_metrics == {"seconds_per_step": 0.75}
    if world == 1:
        assert m.logged == []
    else:
        assert m.logged == [("seconds_per_step", 0.75, {"on_step": True, "on_epoch": False, "batch_size": 1})]


def test_step_timer_leaves_out_the_rows_mesh_distances(tmp_path, clock):
    """A step whose logged row computed the mesh distances (0.5 s of its 0.75 s): seconds_per_step
    is the step's 0.25 s; the distances made a distance row's step look 3x its neighbours'."""
    clock.times = [10.0, 10.75]
    t, m = trainer(), module(tmp_path)
    timer = StepTimer()
    timer.on_train_batch_start(t, m, None, 0)
    assert m.diagnostic_seconds == 0.0
    m.diagnostic_seconds = 0.5  # what _record_step adds while the step runs
    timer.on_train_batch_end(t, m, None, None, 0)
    assert m.step_metrics == {"seconds_per_step": 0.25}


def test_nonfinite_guard_quiet(tmp_path):
    t, m = trainer(), module(tmp_path)
    NonFiniteLossGuard().on_train_batch_end(t, m, None, None, 0)
    assert t.saved == [] and t.should_stop is False and m.nonfinite is None


def test_nonfinite_guard_stops(tmp_path):
    t, m = trainer(), module(tmp_path, )
    m.nonfinite = "loss is nan at step 3"
    NonFiniteLossGuard().on_train_batch_end(t, m, None, None, 0)
    path = tmp_path / "checkpoints" / "last-good.ckpt"
    assert t.saved == [(path, {})]
    assert m.nonfinite == f"loss is nan at step 3; the last good state is in {path}"
    assert t.should_stop is True


def test_interrupted():
    assert _interrupted(KeyboardInterrupt()) is True
    assert _interrupted(RuntimeError("x")) is False
    assert _interrupted(SystemExit()) is False


# ---------------------------------------------------------------- ImageWriter


@pytest.fixture()
def written(monkeypatch):
    files = []
    monkeypatch.setattr(callbacks, "write_image", lambda path, image: files.append((Path(path), float(image.flatten()[0]))))
    return files


def writer_setup(tmp_path, views=(0, 1, 2), **attrs):
    data = SimpleNamespace(views=list(views), targets=[torch.full((3, 1, 1), 10.0 + v) for v in views])
    t = trainer(datamodule=data, **attrs)
    m = module(tmp_path)
    m.previewed = []

    def preview(v):
        m.previewed.append(v)
        return torch.full((3, 1, 1), float(v))

    m.preview = preview
    return t, m


def names(files, tmp_path):
    return [(str(p.relative_to(tmp_path)), value) for p, value in files]


def test_image_writer_defaults():
    w = ImageWriter()
    assert (w.every_n_steps, w.exr, w.max_views) == (50, True, 4)


def test_image_writer_start(tmp_path, written):
    t, m = writer_setup(tmp_path, views=(3, 1, 2), global_step=0)
    ImageWriter(max_views=2).on_train_start(t, m)
    assert (tmp_path / "images").is_dir()
    assert names(written, tmp_path) == [
        ("images/target_v3.png", 13.0), ("images/target_v3.exr", 13.0),
        ("images/target_v1.png", 11.0), ("images/target_v1.exr", 11.0),
        ("images/initial_v3.png", 3.0), ("images/initial_v3.exr", 3.0),
        ("images/initial_v1.png", 1.0), ("images/initial_v1.exr", 1.0),
    ]
    assert m.previewed == [3, 1]


def test_image_writer_start_resumed_no_exr(tmp_path, written):
    t, m = writer_setup(tmp_path, views=(0, 1), global_step=1)
    ImageWriter(exr=False).on_train_start(t, m)
    assert names(written, tmp_path) == [("images/target_v0.png", 10.0), ("images/target_v1.png", 11.0)]
    assert m.previewed == []


def test_image_writer_new_run_folder(tmp_path, written):
    t, m = writer_setup(tmp_path, views=(0,))
    m.results_dir = str(tmp_path / "results" / "version_0")  # not made yet
    ImageWriter().on_train_end(t, m)
    assert (tmp_path / "results" / "version_0" / "images").is_dir()
    assert [p.name for p, _ in written] == ["final_v0.png", "final_v0.exr"]


def test_image_writer_not_global_zero(tmp_path, written):
    t, m = writer_setup(tmp_path, is_global_zero=False, global_step=0)
    w = ImageWriter(every_n_steps=1)
    w.on_train_start(t, m)
    w.on_train_batch_end(t, m, None, None, 0)
    w.on_train_end(t, m)
    assert written == [] and not (tmp_path / "images").exists()


@pytest.mark.parametrize("every, step, writes", [(5, 10, True), (5, 7, False), (0, 10, False), (1, 3, True)])
def test_image_writer_current(tmp_path, written, every, step, writes):
    t, m = writer_setup(tmp_path, views=(0,), global_step=step)
    ImageWriter(every_n_steps=every).on_train_batch_end(t, m, None, None, 0)
    expected = [("images/current_v0.png", 0.0), ("images/current_v0.exr", 0.0)] if writes else []
    assert names(written, tmp_path) == expected


def test_image_writer_current_not_global_zero_skips_preview(tmp_path, written):
    t, m = writer_setup(tmp_path, views=(0,), global_step=10, is_global_zero=False)
    ImageWriter(every_n_steps=5).on_train_batch_end(t, m, None, None, 0)
    assert m.previewed == [] and written == []


def test_image_writer_end_and_exception(tmp_path, written):
    t, m = writer_setup(tmp_path, views=(0, 1))
    w = ImageWriter(exr=False)
    w.on_train_end(t, m)
    assert names(written, tmp_path) == [("images/final_v0.png", 0.0), ("images/final_v1.png", 1.0)]
    written.clear()
    w.on_exception(t, m, RuntimeError("boom"))
    assert written == []
    w.on_exception(t, m, KeyboardInterrupt())
    assert names(written, tmp_path) == [("images/final_v0.png", 0.0), ("images/final_v1.png", 1.0)]
    m.previewed.clear()
    t.is_global_zero = False
    w.on_train_end(t, m)
    assert m.previewed == []


# ---------------------------------------------------------------- CurvePlotter


def test_curve_plotter_history(tmp_path, clock):
    clock.times = [100.0, 101.5, 103.0]
    t, m = trainer(global_step=1), module(tmp_path)
    c = CurvePlotter()
    assert c.history == [] and c.state_dict() == {"history": [], "elapsed": 0.0}
    c.on_train_start(t, m)
    m.step_metrics = {"loss": torch.tensor(0.5), "param_error": 2, "seconds_per_step": 9.0}
    c.on_train_batch_end(t, m, None, None, 0)
    t.global_step = 2
    m.step_metrics = {"loss": 0.25, "image_error": 0.125}
    c.on_train_batch_end(t, m, None, None, 0)
    assert c.history == [
        {"step": 0.0, "seconds": 1.5, "loss": 0.5, "param_error": 2.0},
        {"step": 1.0, "seconds": 3.0, "loss": 0.25, "image_error": 0.125},
    ]
    assert all(type(v) is float for row in c.history for v in row.values())
    assert c.state_dict() == {"history": c.history, "elapsed": 3.0}


def test_curve_plotter_resume(tmp_path, clock):
    c = CurvePlotter()
    history = [{"step": 0.0, "seconds": 4.0, "loss": 1.0}]
    c.load_state_dict({"history": history, "elapsed": 4})
    assert c.history == history and c.history is not history
    assert c.state_dict()["elapsed"] == 4.0 and type(c.state_dict()["elapsed"]) is float
    clock.times = [50.0, 52.0]
    t, m = trainer(global_step=2), module(tmp_path)
    c.on_train_start(t, m)  # the clock continues from 4 s
    m.step_metrics = {"loss": 0.5}
    c.on_train_batch_end(t, m, None, None, 0)
    assert c.history[-1] == {"step": 1.0, "seconds": 6.0, "loss": 0.5}


@pytest.fixture()
def plotted(monkeypatch):
    calls = []
    monkeypatch.setattr(CurvePlotter, "plot", lambda self, path: calls.append(path))
    return calls


def test_curve_plotter_end(tmp_path, plotted):
    c = CurvePlotter()
    t, m = trainer(), module(tmp_path)
    c.on_train_end(t, m)
    assert plotted == []  # no history
    c.history = [{"step": 0.0, "seconds": 1.0, "loss": 1.0}]
    t.is_global_zero = False
    c.on_train_end(t, m)
    assert plotted == []
    t.is_global_zero = True
    c.on_exception(t, m, ValueError("x"))
    assert plotted == []
    c.on_exception(t, m, KeyboardInterrupt())
    c.on_train_end(t, m)
    assert plotted == [tmp_path / "curves.png", tmp_path / "curves.png"]


def test_curve_plotter_plot(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt
    from PIL import Image

    figures = []
    monkeypatch.setattr(plt, "close", lambda fig: figures.append(fig))
    c = CurvePlotter()
    c.history = [
        {"step": 0.0, "seconds": 1.0, "loss": 4.0},
        {"step": 1.0, "seconds": 2.0, "loss": 0.0, "param_error": 0.5},
        {"step": 2.0, "seconds": 3.5, "loss": 1.0, "param_error": 0.25},
    ]
    path = tmp_path / "new" / "sub" / "curves.png"  # folders made, parents too
    c.plot(path)
    with Image.open(path) as png:
        assert png.size == (800, 650)  # figsize (4 * 2, 6.5) at dpi 100
    (fig,) = figures
    axes = fig.axes
    assert len(axes) == 4
    grid = [[axes[0], axes[1]], [axes[2], axes[3]]]  # 2 rows x 2 metrics
    for col, metric in enumerate(("loss", "param_error")):
        for row, (x, label) in enumerate((("step", "optimiser step"), ("seconds", "wall time (s)"))):
            ax = grid[row][col]
            assert ax.get_xlabel() == label and ax.get_ylabel() == metric
            assert ax.get_title() == f"{metric} vs {x}"
            assert ax.get_yscale() == "log"
            (line,) = ax.get_lines()
            rows = [r for r in c.history if metric in r]
            assert list(line.get_xdata()) == [r[x] for r in rows]
            assert list(line.get_ydata()) == [max(r[metric], 1e-12) for r in rows]
            gridlines = ax.xaxis.get_gridlines()
            assert gridlines[0].get_visible() and gridlines[0].get_alpha() == 0.3
    assert list(grid[0][0].get_lines()[0].get_ydata()) == [4.0, 1e-12, 1.0]


def test_curve_plotter_plot_one_metric(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(plt, "close", lambda fig: figures.append(fig))
    c = CurvePlotter()
    c.history = [{"step": 0.0, "seconds": 1.0, "image_error": 0.5}]
    c.plot(tmp_path / "c.png")
    (fig,) = figures
    assert len(fig.axes) == 2 and tuple(fig.get_size_inches()) == (4.0, 6.5)
    assert [ax.get_ylabel() for ax in fig.axes] == ["image_error", "image_error"]


# ---------------------------------------------------------------- ResultWriter


@pytest.fixture()
def results_written(monkeypatch, tmp_path):
    calls = []

    def fake(module, folder, step, images=True):
        calls.append((module, folder, step, images))
        return Path(folder) / "result.yaml"

    monkeypatch.setattr(results, "write_results", fake)
    return calls


def test_result_writer_no_outputs(tmp_path, results_written, capsys):
    t, m = trainer(global_step=5), module(tmp_path)
    ResultWriter().on_exception(t, m, KeyboardInterrupt())
    assert results_written == [] and t.saved == [] and capsys.readouterr().out == ""


def test_result_writer_end(tmp_path, results_written, capsys):
    ckpt_dir = tmp_path / "checkpoints"
    checkpoint = ModelCheckpoint(dirpath=str(ckpt_dir))
    t, m = trainer(global_step=7, checkpoint_callback=checkpoint), module(tmp_path)
    ResultWriter().on_train_end(t, m)
    expected = str(ckpt_dir / "last.ckpt")
    assert t.saved == [(expected, {"weights_only": False})]
    assert checkpoint.last_model_path == expected
    assert results_written == [(m, str(tmp_path), 7, False)]
    assert capsys.readouterr().out == f"[torchir] recovered values: {tmp_path / 'result.yaml'}\n"


def test_result_writer_after_one_step(tmp_path, results_written, capsys):
    checkpoint = ModelCheckpoint(dirpath=str(tmp_path / "c"))
    t, m = trainer(global_step=1, checkpoint_callback=checkpoint), module(tmp_path)
    ResultWriter().on_train_end(t, m)
    assert t.saved == [(str(tmp_path / "c" / "last.ckpt"), {"weights_only": False})]
    capsys.readouterr()


def test_result_writer_keeps_registered_last(tmp_path, results_written, capsys):
    checkpoint = ModelCheckpoint(dirpath=str(tmp_path / "c"))
    checkpoint.last_model_path = str(tmp_path / "c" / "last-v1.ckpt")
    t, m = trainer(global_step=3, checkpoint_callback=checkpoint, is_global_zero=False), module(tmp_path)
    ResultWriter().on_train_end(t, m)
    assert t.saved == [(str(tmp_path / "c" / "last-v1.ckpt"), {"weights_only": False})]
    assert checkpoint.last_model_path == str(tmp_path / "c" / "last-v1.ckpt")
    assert results_written == [] and capsys.readouterr().out == ""


def test_result_writer_no_checkpoint_at_step_zero_or_without_dir(tmp_path, results_written, capsys):
    t, m = trainer(global_step=0, checkpoint_callback=ModelCheckpoint(dirpath=str(tmp_path))), module(tmp_path)
    ResultWriter().on_train_end(t, m)
    assert t.saved == [] and results_written == [(m, str(tmp_path), 0, False)]
    t2 = trainer(global_step=4, checkpoint_callback=ModelCheckpoint(), loggers=["csv"])
    ResultWriter().on_train_end(t2, m)
    assert t2.saved == [] and results_written[-1] == (m, str(tmp_path), 4, False)
    # a logger alone (no checkpointing) still writes result.yaml
    t3 = trainer(global_step=2, loggers=["csv"])
    ResultWriter().on_train_end(t3, m)
    assert t3.saved == [] and results_written[-1] == (m, str(tmp_path), 2, False)
    capsys.readouterr()


def test_result_writer_nonfinite_and_exceptions(tmp_path, results_written, capsys):
    checkpoint = ModelCheckpoint(dirpath=str(tmp_path / "c"))
    t, m = trainer(global_step=9, checkpoint_callback=checkpoint), module(tmp_path)
    m.nonfinite = "loss is nan"
    w = ResultWriter()
    w.on_train_end(t, m)
    assert t.saved == [] and results_written == []
    w.on_exception(t, m, RuntimeError("x"))
    assert t.saved == [] and results_written == [] and capsys.readouterr().out == ""
    w.on_exception(t, m, KeyboardInterrupt())
    out = capsys.readouterr().out
    assert out == (
        "\n[torchir] interrupted after step 9: saving the state\n"
        f"[torchir] recovered values: {tmp_path / 'result.yaml'}\n"
    )
    assert t.saved == [(str(tmp_path / "c" / "last.ckpt"), {"weights_only": False})]
    assert results_written == [(m, str(tmp_path), 9, False)]


# ---------------------------------------------------------------- StepProgressBar


@pytest.fixture(autouse=True)
def no_tqdm_monitor(monkeypatch):
    """No tqdm monitor thread: a thread alive in the process mutmut forks from can leave tqdm's
    lock held in the child (seen as runs of "timeout")."""
    import tqdm

    monkeypatch.setattr(tqdm.tqdm, "monitor_interval", 0)
    yield
    for bar in list(getattr(tqdm.tqdm, "_instances", ())):  # a failed test leaves its bar open
        bar.close()


def test_step_progress_bar(tmp_path, capsys):
    bar = StepProgressBar()
    t, m = trainer(global_step=3, max_steps=20), module(tmp_path)
    bar.on_train_start(t, m)
    tq = bar.train_progress_bar
    assert tq.total == 20 and tq.n == 3 and tq.initial == 3 and tq.desc == "step"
    assert tq.leave is True and tq.smoothing == 0 and callable(tq.dynamic_ncols) and tq.pos == 0
    assert tq.bar_format == "{desc} {n_fmt}/{total_fmt} |{bar}| [{elapsed}<{remaining}{postfix}]"
    assert tq.disable is False
    bar.on_train_epoch_start(t)
    assert tq.n == 3
    t.global_step = 5
    m.step_metrics = {"seconds_per_step": 0.123456, "loss": torch.tensor(0.000123456), "param_error": 12345.6, "image_error": 1.0}
    bar.on_train_batch_end(t, m, None, None, 0)
    assert tq.n == 5
    assert tq.postfix == "s/step=0.123, loss=0.0001235, param_error=1.235e+04"
    m.step_metrics = {"loss": 2.0}
    t.global_step = 6
    bar.on_train_batch_end(t, m, None, None, 0)
    assert tq.postfix == "loss=2" and tq.n == 6
    bar.on_train_epoch_end(t, m)
    assert tq.n == 6
    out = capsys.readouterr().out
    assert "step 6/20" in out
    bar.on_train_end(t, m)
    assert tq.disable is True  # tqdm marks a closed bar disabled


def test_step_progress_bar_no_max_steps(tmp_path, capsys):
    bar = StepProgressBar()
    bar.on_train_start(trainer(global_step=0, max_steps=-1), module(tmp_path))
    assert bar.train_progress_bar.total is None
    bar.train_progress_bar.close()
    bar2 = StepProgressBar(process_position=1)
    bar2.on_train_start(trainer(global_step=0, max_steps=0), module(tmp_path))
    assert bar2.train_progress_bar.total is None and bar2.train_progress_bar.pos == -2  # tqdm keeps -position
    bar2.train_progress_bar.close()
    bar3 = StepProgressBar()
    bar3.disable()
    bar3.on_train_start(trainer(global_step=0, max_steps=1), module(tmp_path))
    assert bar3.train_progress_bar.disable is True and bar3.train_progress_bar.total == 1
    capsys.readouterr()
