"""Guards of the training loop that a mutation audit found untested: an Inf loss must stop a
run as a NaN loss does, before the step is applied; unknown ``model.parameters`` fields are
rejected from the Python API as from YAML; the per-step render seed changes with the step.

Tiny scenes (8x8, a few steps) keep these fast; none of them depends on Monte Carlo luck.
"""
from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from torch import nn

from torchir import cli
from torchir.training import InverseRenderingModule, ParameterConfig, ViewDataModule

from tests.helpers import _latents

KEY = "red.reflectance.value"


class InfAfterLoss(nn.Module):
    """L2 loss that returns +Inf from its ``steps``-th call on (``steps=0``: at once)."""

    def __init__(self, steps: int = 0) -> None:
        super().__init__()
        self.steps, self.calls = steps, 0

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        loss = (rendered - target).square().mean()
        return loss + float("inf") if self.calls > self.steps else loss


def _trainer(tmp_path, steps: int) -> pl.Trainer:
    return pl.Trainer(
        max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
        enable_model_summary=False, default_root_dir=tmp_path,
    )


# ------------------------------------------------------------------------- unknown fields
@pytest.mark.parametrize("fields", [{"bonds": [0, 1]}, {"init": 0.3, "transfrom": "sigmoid"}])
def test_unknown_parameter_fields_are_rejected_from_python(fields):
    misspelt = next(k for k in fields if k not in ParameterConfig.__dataclass_fields__)
    with pytest.raises(ValueError, match=rf"parameters\['{KEY}'\] has unknown field\(s\) \['{misspelt}'\]"):
        InverseRenderingModule(scene="cbox", resolution=8, parameters={KEY: fields})


def test_known_parameter_fields_are_kept():
    """The control: the same entry spelt right reaches the ParameterConfig unchanged."""
    model = InverseRenderingModule(scene="cbox", resolution=8, parameters={KEY: {"init": 0.25, "bounds": [0.1, 0.9]}})
    config = model.configs[KEY]
    assert config.init == 0.25 and tuple(config.bounds) == (0.1, 0.9)
    torch.testing.assert_close(model.scene_values()[KEY].detach(), torch.full((3,), 0.25))


# ------------------------------------------------------------------------------ Inf loss
def test_inf_loss_stops_the_run_before_the_step_is_applied(tmp_path):
    """With an Inf loss the Adam step would turn the latent into NaN (its gradient is Inf or
    NaN); the guard must return before backward, so the parameter keeps its initial value
    exactly (Lightning still counts the skipped step in ``global_step``)."""
    model = InverseRenderingModule(
        scene="cbox", resolution=8, spp=1, parameters={KEY: ParameterConfig(init=0.3, bounds=(0.0, 1.0))}, loss=InfAfterLoss(0),
    )
    before = model.scene_values()[KEY].detach().clone()
    trainer = _trainer(tmp_path, 5)
    trainer.fit(model, ViewDataModule(target_spp=4))
    assert model.nonfinite is not None and "the loss became inf at step 0" in model.nonfinite
    assert torch.equal(model.scene_values()[KEY].detach(), before)


def _fit(save_dir, *overrides: str) -> int:
    return cli.main([
        "fit", "--config", "configs/quickstart.yaml", "--model.resolution", "8", "--model.spp", "1",
        "--data.target_spp", "4", "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
        "--trainer.logger.init_args.save_dir", str(save_dir), "--images.exr", "false", *overrides,
    ])


def _fit_yaml(tmp_path, monkeypatch, name: str, text: str):
    """Write ``text`` as ``tmp_path/name``, run ``torchir fit`` on it from ``tmp_path`` (as a user
    would: no logger options) and return the run's folder."""
    config = tmp_path / name
    config.write_text(text)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["fit", "--config", str(config), "--images.exr", "false"]) == 0
    return tmp_path / "results" / "torchir" / "version_0"


def test_inf_loss_after_good_steps_stops_fit_with_a_clear_error(tmp_path, capsys):
    """Through ``torchir fit``: two good steps, then Inf: exit code 1, the message names the
    value and the step, and the saved state is the one after the two good steps (equal to a
    clean two-step run's, up to Dr.Jit's float32 atomics), not one updated with the Inf."""
    code = _fit(tmp_path, "--trainer.max_steps", "6", "--model.loss", f"{__name__}.InfAfterLoss", "--model.loss.steps", "2")
    err = capsys.readouterr().err
    assert code == 1, err
    assert "the loss became inf at step 2" in err and "last-good.ckpt" in err
    good = _latents(tmp_path / "quickstart" / "version_0" / "checkpoints" / "last-good.ckpt")
    assert _fit(tmp_path / "clean", "--trainer.max_steps", "2") == 0
    clean = _latents(tmp_path / "clean" / "quickstart" / "version_0" / "checkpoints" / "last.ckpt")
    assert good.keys() == clean.keys() and good
    for key in clean:
        torch.testing.assert_close(good[key], clean[key], rtol=1e-5, atol=1e-6)


# -------------------------------------------------------------------------- step seeds
def test_every_step_and_view_renders_with_a_fresh_seed(tmp_path, monkeypatch):
    """Reusing a seed across steps correlates the gradient noise of successive steps: the run
    then converges to a biased answer (the estimator is unbiased per step, not across steps
    that share their paths). Record the seed of every render a short pixel-mode run makes."""
    import torchir.functions as functions

    seen: list[tuple[int, int]] = []
    real = functions.render_pixels

    def spy(scene, params, pixels, spp=1, seed=0, sensor=0, **kw):
        seen.append((sensor, seed))
        return real(scene, params, pixels, spp=spp, seed=seed, sensor=sensor, **kw)

    monkeypatch.setattr(functions, "render_pixels", spy)
    model = InverseRenderingModule(
        scene="cbox", resolution=8, spp=1, parameters={KEY: {"init": 0.3}}, sampler={"type": "uniform", "budget": 16},
    )
    _trainer(tmp_path, 4).fit(model, ViewDataModule(target_spp=4))
    assert len(seen) == 4
    assert len({seed for _, seed in seen}) == 4, seen
    # and the seeds are the documented function of (seed, step, view) only
    assert [seed for _, seed in seen] == [model.step_seed(step, 0) for step in range(4)]
    other = InverseRenderingModule(scene="cbox", resolution=8, seed=1, parameters={KEY: {"init": 0.3}})
    assert other.step_seed(0, 0) != model.step_seed(0, 0)


def test_a_minimal_config_without_a_logger_runs(tmp_path, monkeypatch):
    """Scene, one parameter, spp, max_steps: the first YAML a user writes. It names no
    ``trainer.logger``; the default CSV logger must still work (it once failed with
    "'LazyInstance_CSVLogger' object has no attribute '_version'")."""
    run = _fit_yaml(tmp_path, monkeypatch, "minimal.yaml",
                    "model:\n  scene: cbox\n  resolution: 8\n  spp: 1\n  parameters:\n    red.reflectance.value: {init: 0.5}\n"
                    "data:\n  target_spp: 4\ntrainer:\n  max_steps: 2\n  enable_progress_bar: false\n")
    assert (run / "metrics.csv").is_file() and (run / "result.yaml").is_file()


def test_per_entry_bounds_from_yaml_pin_one_entry(tmp_path, monkeypatch):
    """``bounds: [[lo per entry], [hi per entry]]`` from YAML: the red wall's blue channel pinned
    at 0.1 (lo == hi) while red and green are fitted (as one axis of a rigid transform's
    translation is pinned)."""
    import yaml

    run = _fit_yaml(tmp_path, monkeypatch, "pinned.yaml",
                    "model:\n  scene: cbox\n  resolution: 8\n  spp: 1\n  lr: 0.2\n  parameters:\n"
                    "    red.reflectance.value: {init: [0.5, 0.5, 0.1], bounds: [[0, 0, 0.1], [1, 1, 0.1]]}\n"
                    "data:\n  target_spp: 4\ntrainer:\n  max_steps: 3\n  enable_progress_bar: false\n")
    result = yaml.safe_load((run / "result.yaml").read_text())
    red, green, blue = result["parameters"]["red.reflectance.value"]
    assert blue == pytest.approx(0.1) and red != 0.5 and green != 0.5


def test_the_console_of_a_run_holds_only_torchir_s_lines(tmp_path):
    """``torchir fit`` as a user starts it (a fresh process, a minimal YAML): every console line is
    torchir's progress bar or one of its ``[torchir]`` lines; none of Lightning's info lines ("Seed
    set", "GPU available", its cloud-logger advertisement), its model table ("Total FLOPs: 0"),
    LightningCLI's warning about ``args``, or jsonargparse's "Unable to serialize"."""
    import subprocess
    import sys

    config = tmp_path / "minimal.yaml"
    config.write_text("model:\n  scene: cbox\n  resolution: 8\n  spp: 1\n  parameters:\n    red.reflectance.value: {init: 0.5}\n"
                      "data:\n  target_spp: 4\ntrainer:\n  max_steps: 2\n")
    out = subprocess.run([sys.executable, "-m", "torchir", "fit", "--config", str(config)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = [line.strip() for line in (out.stdout + out.stderr).replace("\r", "\n").splitlines() if line.strip()]
    foreign = [line for line in lines if not (line.startswith("step ") or line.startswith("[torchir]"))]
    assert not foreign, foreign
    assert any(line.startswith("[torchir] finished 2 steps") for line in lines)


def test_a_scene_built_by_a_python_factory_runs(tmp_path, monkeypatch):
    """Mitsuba's tutorials build scenes as dicts in Python: ``model.scene: file.py:function``
    (relative to the config) is called with ``scene_options`` and ``resolution``; a factory that
    returns something else is refused with its name."""
    (tmp_path / "my_scenes.py").write_text(
        "import mitsuba as mi\n\n"
        "def box(resolution=8, red=0.6):\n"
        "    scene = mi.cornell_box()\n"
        "    scene['sensor']['film']['width'] = scene['sensor']['film']['height'] = resolution\n"
        "    scene['red']['reflectance']['value'] = [red, 0.1, 0.1]\n"
        "    return scene\n\n"
        "def broken(**_):\n"
        "    return 'not a scene'\n"
    )
    run = _fit_yaml(tmp_path, monkeypatch, "factory.yaml",
                    "model:\n  scene: my_scenes.py:box\n  resolution: 8\n  scene_options: {red: 0.7}\n  spp: 1\n"
                    "  parameters:\n    red.reflectance.value: {init: 0.3}\n"
                    "data:\n  target_spp: 4\ntrainer:\n  max_steps: 2\n  enable_progress_bar: false\n")
    assert (run / "result.yaml").is_file()
    model = InverseRenderingModule(scene=f"{tmp_path / 'my_scenes.py'}:box", resolution=8, scene_options={"red": 0.7},
                                   parameters={"red.reflectance.value": {"init": 0.3}})
    assert model.scene.resolution == (8, 8)
    torch.testing.assert_close(model.scene.get("red.reflectance.value"), torch.tensor([0.7, 0.1, 0.1]))  # the options reached it
    with pytest.raises(ValueError, match=r"my_scenes.py:broken' must return a Mitsuba scene dict .*got str"):
        InverseRenderingModule(scene=f"{tmp_path / 'my_scenes.py'}:broken", parameters={"red.reflectance.value": {}})
