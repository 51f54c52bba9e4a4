"""The Lightning side: quickstart at tiny scale, outputs, resume == uninterrupted, config and
input errors, the NaN guard (multi-view DDP against one process: ``test_training_ddp.py``)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
import yaml

from torchir import Scene, cli
from torchir.training import InverseRenderingModule, ParameterConfig, ViewDataModule, load_image

from tests.helpers import ROOT, _latents, _run_dir

QUICKSTART = str(ROOT / "configs" / "quickstart.yaml")


def _fit(tmp_path: Path, *overrides: str, config: str = QUICKSTART) -> int:
    return cli.main(
        ["fit", "--config", config, "--model.resolution", "16", "--trainer.enable_progress_bar", "false",
         "--trainer.enable_model_summary", "false", "--trainer.logger.init_args.save_dir", str(tmp_path), *overrides]
    )


def test_diagnostics_logged_on_exactly_the_steps_the_logger_writes(tmp_path):
    # paths_per_step and sampler/* are only logged on steps the logger writes (they cost
    # ~0.3 ms each): if the rule were off by a step, the written rows would lack them
    assert _fit(tmp_path, "--trainer.max_steps", "7", "--trainer.log_every_n_steps", "3", "--model.spp", "1") == 0
    rows = list(csv.DictReader(open(_run_dir(tmp_path) / "metrics.csv")))
    written = [r for r in rows if r.get("loss")]
    assert [int(r["step"]) for r in written] == [2, 5]  # every 3rd step (0-based 2, 5)
    assert all(float(r["paths_per_step"]) == 16 * 16 * 2 for r in written)


def test_quickstart_recovers_albedos_and_writes_outputs(tmp_path):
    assert _fit(tmp_path, "--trainer.max_steps", "40", "--model.spp", "4") == 0
    run = _run_dir(tmp_path)
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    errors = [float(r["param_error"]) for r in rows if r.get("param_error")]
    assert len(errors) == 41 and errors[-1] < 0.25 * errors[0], (errors[0], errors[-1])  # 40 steps' renders and the final values
    assert [int(r["step"]) for r in rows][-1] == 40 and not rows[-1].get("loss")
    # the last row: the errors of the values the run ends with (result.yaml's), not of the last step's render
    recovered = yaml.safe_load((run / "result.yaml").read_text())["parameters"]
    scene = Scene.builtin("cbox", resolution=16)
    own = {k: math.sqrt(float((torch.tensor(v) - scene.get(k)).square().mean())) for k, v in recovered.items()}
    per_key = {k.removeprefix("param_error/"): float(v) for k, v in rows[-1].items() if k.startswith("param_error/") and v}
    assert per_key.keys() == own.keys() and len(own) == 2  # each parameter's own RMSE beside the pooled one
    assert all(per_key[k] == pytest.approx(own[k], rel=1e-4, abs=1e-6) for k in own)
    assert float(rows[-1]["param_error"]) == pytest.approx(math.sqrt(sum(e * e for e in own.values()) / 2), rel=1e-4)
    assert float(rows[-1]["param_error"]) != float(rows[-2]["param_error"])  # one step later than the last render
    assert all(float(r["paths_per_step"]) == 16 * 16 * 8 for r in rows if r.get("paths_per_step"))
    for kind in ("target", "initial", "final"):
        image = load_image(run / "images" / f"{kind}_v0.exr")
        assert image.shape == (3, 16, 16) and bool(image.isfinite().all())
        assert (run / "images" / f"{kind}_v0.png").stat().st_size > 0
    assert (run / "curves.png").stat().st_size > 0
    assert "red.reflectance.value" in (run / "config.yaml").read_text()
    assert (run / "checkpoints" / "last.ckpt").is_file()
    final = load_image(run / "images" / "final_v0.exr")
    initial = load_image(run / "images" / "initial_v0.exr")
    target = load_image(run / "images" / "target_v0.exr")
    # Per-channel mean colour of the lit surfaces: Monte Carlo noise averages out over the image
    # (measured floor <= 0.003 at 64 spp), wrong albedos do not. The light's own pixels (radiance
    # ~18, partly covered at 16x16) are left out: their noise alone reaches 0.026.
    surfaces = target.amax(0) < 1.0
    colour_error = lambda image: (image[:, surfaces].mean(1) - target[:, surfaces].mean(1)).abs().sum()  # noqa: E731
    assert colour_error(final) < 0.25 * colour_error(initial), (colour_error(final), colour_error(initial))


def test_a_second_run_does_not_overwrite_the_first(tmp_path):
    assert _fit(tmp_path, "--trainer.max_steps", "2") == 0
    first = (_run_dir(tmp_path) / "metrics.csv").read_text()
    assert _fit(tmp_path, "--trainer.max_steps", "3") == 0
    assert (_run_dir(tmp_path) / "metrics.csv").read_text() == first
    assert (_run_dir(tmp_path, version=1) / "metrics.csv").is_file()


def test_resume_reproduces_the_uninterrupted_run(tmp_path):
    """Resuming at step 4 of 8 ends where the uninterrupted run ends.

    Not bitwise: Dr.Jit accumulates gradients with parallel float32 atomics, so even two
    identical render calls differ by up to ~3e-7 relative (measured). The bound 1e-5 allows
    that and nothing more: a resume that lost the optimiser state or the step counter (hence
    the seeds) lands ~1e-2 away, as the control below shows.
    """
    common = ["--checkpoint.every_n_train_steps", "4", "--model.spp", "4"]
    assert _fit(tmp_path / "a", "--trainer.max_steps", "8", *common) == 0
    full = _run_dir(tmp_path / "a") / "checkpoints"
    middle = full / "epoch=3-step=4.ckpt"
    assert middle.is_file(), sorted(p.name for p in full.iterdir())
    assert _fit(tmp_path / "b", "--trainer.max_steps", "8", *common, "--ckpt_path", str(middle)) == 0
    uninterrupted = _latents(full / "last.ckpt")
    resumed = _latents(_run_dir(tmp_path / "b") / "checkpoints" / "last.ckpt")
    assert uninterrupted.keys() == resumed.keys()
    for key in uninterrupted:
        torch.testing.assert_close(resumed[key], uninterrupted[key], rtol=1e-5, atol=1e-6)
        assert not torch.equal(_latents(middle)[key], uninterrupted[key])  # it really resumed mid-way
    # one run, one history: the resumed run's metrics.csv starts at step 0 (the first run's rows)
    first = list(csv.DictReader(open(_run_dir(tmp_path / "a") / "metrics.csv")))
    history = list(csv.DictReader(open(_run_dir(tmp_path / "b") / "metrics.csv")))
    assert [int(r["step"]) for r in history] == list(range(9))  # 8 steps and the final row
    assert [r["loss"] for r in history[:4]] == [r["loss"] for r in first[:4]]
    assert all(abs(float(a["loss"]) - float(b["loss"])) <= 1e-5 * abs(float(a["loss"])) for a, b in zip(first[4:8], history[4:8]))

    # Control: the same resume with a fresh optimiser (Adam moments lost) misses the bound.
    state = torch.load(middle, map_location="cpu", weights_only=False)
    state["optimizer_states"][0]["state"] = {}
    torch.save(state, tmp_path / "no-moments.ckpt")
    assert _fit(tmp_path / "c", "--trainer.max_steps", "8", *common, "--ckpt_path", str(tmp_path / "no-moments.ckpt")) == 0
    broken = _latents(_run_dir(tmp_path / "c") / "checkpoints" / "last.ckpt")
    assert any(not torch.allclose(broken[k], uninterrupted[k], rtol=1e-5, atol=1e-6) for k in uninterrupted)


def test_lr_half_life_decays_every_rate_per_step_and_survives_a_resume(tmp_path):
    common = ["--checkpoint.every_n_train_steps", "2", "--model.spp", "1", "--model.lr_half_life", "2"]
    assert _fit(tmp_path / "a", "--trainer.max_steps", "4", *common) == 0
    full = _run_dir(tmp_path / "a") / "checkpoints"
    state = torch.load(full / "last.ckpt", map_location="cpu", weights_only=False)
    base = state["hyper_parameters"]["lr"]
    rates = [g["lr"] for g in state["optimizer_states"][0]["param_groups"]]
    assert rates == pytest.approx([base * 0.5 ** (4 / 2)] * len(rates), rel=1e-12)  # halved every 2 steps
    assert _fit(tmp_path / "b", "--trainer.max_steps", "4", *common, "--ckpt_path", str(full / "epoch=1-step=2.ckpt")) == 0
    resumed = torch.load(_run_dir(tmp_path / "b") / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert [g["lr"] for g in resumed["optimizer_states"][0]["param_groups"]] == pytest.approx(rates, rel=1e-12)
    for bad in (0, -3, 1.5, True):
        with pytest.raises(ValueError, match=rf"^model.lr_half_life must be a number of steps >= 1 \(or null\), got {bad!r}$"):
            InverseRenderingModule(scene="cbox", resolution=8, lr_half_life=bad)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (["--model.lrr", "0.1"], "model.lrr"),
        (["--model.spp", "many"], "model.spp"),
        (["--model.parameters", '{"red.reflectance.value": {"bonds": [0, 1]}}'], "bonds"),
    ],
)
def test_config_errors_name_the_key(tmp_path, capsys, override, message):
    with pytest.raises(SystemExit) as exit_info:
        _fit(tmp_path, *override)
    assert exit_info.value.code != 0
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (["--model.parameters", '{"red.reflectance.valu": {}}'], "Did you mean 'red.reflectance.value'"),
        (["--model.parameters", '{"red.reflectance.value": {"init": [0.1, 0.2]}}'], "does not fit"),
        (["--model.spp", "0"], "model.spp must be >= 1"),
        (["--model.spp_grad", "0"], "model.spp_grad must be >= 1"),
        (["--data.views", "[]"], "data.views is empty"),
        (["--data.views", "[3]"], "has 1 sensor"),
        (["--data.targets", "[missing.exr]"], "missing.exr'"),
    ],
)
def test_bad_inputs_give_clear_errors(tmp_path, capsys, override, message):
    assert _fit(tmp_path, "--trainer.max_steps", "1", *override) == 1
    assert message in capsys.readouterr().err


def test_target_resolution_must_match(tmp_path, capsys):
    from torchir.imageio import save_png

    save_png(tmp_path / "small.png", torch.rand(3, 8, 8))
    assert _fit(tmp_path, "--trainer.max_steps", "1", "--data.targets", f"[{tmp_path / 'small.png'}]") == 1
    assert "is 8x8 (W x H), but sensor 0 renders 16x16" in capsys.readouterr().err


def test_targets_from_files(tmp_path):
    """A real-use run: the target is an EXR file and no ground truth is configured, so the run
    logs no parameter error; the test knows the albedos that made the file and checks them."""
    from torchir.functions import render
    from torchir.imageio import write_image

    scene = Scene.builtin("cbox", resolution=16)
    write_image(tmp_path / "target.exr", render(scene, {}, spp=64, seed=5))
    assert _fit(tmp_path, "--trainer.max_steps", "30", "--data.targets", f"[{tmp_path / 'target.exr'}]") == 0
    rows = list(csv.DictReader(open(_run_dir(tmp_path) / "metrics.csv")))
    assert not any(r.get("param_error") for r in rows) and any(r.get("loss") for r in rows)
    final = _latents(_run_dir(tmp_path) / "checkpoints" / "last.ckpt")
    truth = torch.stack([scene.get("red.reflectance.value"), scene.get("green.reflectance.value")])
    recovered = torch.stack([final["scene_parameters.0.latent"], final["scene_parameters.1.latent"]])
    assert (recovered - truth).norm() < 0.5 * (torch.full_like(truth, 0.5) - truth).norm()


def test_nonfinite_loss_stops_and_keeps_the_last_good_state(tmp_path, capsys):
    code = _fit(tmp_path, "--trainer.max_steps", "10", "--model.loss", "tests.helpers.NaNAfterLoss", "--model.loss.steps", "3")
    assert code == 1
    err = capsys.readouterr().err
    assert "the loss became nan at step 3" in err and "last-good.ckpt" in err
    good = _latents(_run_dir(tmp_path) / "checkpoints" / "last-good.ckpt")
    # The saved state is the one after the 3 good steps: the same as a clean 3-step run's.
    assert _fit(tmp_path / "clean", "--trainer.max_steps", "3") == 0
    clean = _latents(_run_dir(tmp_path / "clean") / "checkpoints" / "last.ckpt")
    for key in clean:
        assert bool(good[key].isfinite().all())
        torch.testing.assert_close(good[key], clean[key], rtol=1e-5, atol=1e-6)


def test_module_and_datamodule_work_in_plain_lightning(tmp_path):
    model = InverseRenderingModule(
        scene="glossy_ball", resolution=8,
        parameters={"ball.bsdf.alpha": ParameterConfig(init=0.3, bounds=(0.01, 0.5), transform="sigmoid")},
        spp=2,
    )
    trainer = pl.Trainer(max_steps=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path)
    trainer.fit(model, ViewDataModule(target_spp=16))
    alpha = model.scene_values()["ball.bsdf.alpha"]
    assert trainer.global_step == 3 and 0.01 < float(alpha) < 0.5


def test_bounds_hold_after_every_step(tmp_path):
    assert _fit(tmp_path, "--trainer.max_steps", "5", "--model.lr", "2.0") == 0
    for value in _latents(_run_dir(tmp_path) / "checkpoints" / "last.ckpt").values():
        assert float(value.min()) >= 0.0 and float(value.max()) <= 1.0


def test_tensorboard_logs_beside_the_csv_when_installed(tmp_path, monkeypatch):
    import torchir.training.cli as training_cli

    monkeypatch.setattr(training_cli, "_tensorboard_installed", lambda: True)  # tensorboardX backs it here
    assert _fit(tmp_path, "--trainer.max_steps", "2") == 0
    run = _run_dir(tmp_path)
    assert (run / "metrics.csv").is_file() and list(run.glob("events.out.tfevents.*"))
