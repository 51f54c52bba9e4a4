"""The four techniques inside training runs: every technique config builds, sampler state
survives checkpoints (resume == uninterrupted), and incompatible combinations are refused."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from torchir import cli
from torchir.training import InverseRenderingModule

from tests.helpers import ROOT, _latents

CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_every_config_builds_its_module(config):
    model = dict(yaml.safe_load(config.read_text())["model"])
    model["resolution"] = 16
    module = InverseRenderingModule(**model)
    assert module.keys and module.loss_fn is not None
    for section in ("denoiser", "sampler"):
        if isinstance(model.get(section), dict) and model[section].get("type") not in (None, "none"):
            assert getattr(module, section) is not None


def _fit(tmp_path: Path, config: str, *overrides: str) -> int:
    return cli.main(
        ["fit", "--config", str(ROOT / "configs" / config), "--model.resolution", "16", "--trainer.enable_progress_bar", "false",
         "--trainer.enable_model_summary", "false", "--trainer.logger.init_args.save_dir", str(tmp_path),
         "--checkpoint.every_n_train_steps", "3", "--trainer.max_steps", "6", *overrides]
    )


@pytest.mark.parametrize(
    ("config", "overrides"),
    [
        ("sampling_adaptive.yaml", ["--model.sampler.refresh_every", "2"]),
        ("restir.yaml", ["--model.sampler.burn_in", "2", "--model.spp", "1"]),
    ],
    ids=["adaptive", "restir"],
)
def test_resume_restores_the_sampler_state(tmp_path, config, overrides):
    """Resuming at step 3 of 6 ends where the uninterrupted run ends (to float32 atomics,
    rtol 1e-5, see test_training): the pmf / reservoirs and the draw generator come back from
    the checkpoint, which Lightning loads with weights_only=True."""
    name = yaml.safe_load((ROOT / "configs" / config).read_text())["trainer"]["logger"][0]["init_args"]["name"]
    assert _fit(tmp_path / "a", config, *overrides) == 0
    folder = tmp_path / "a" / name / "version_0" / "checkpoints"
    middle = folder / "epoch=2-step=3.ckpt"
    state = torch.load(middle, map_location="cpu", weights_only=True)
    assert "torchir_sampler" in state
    assert _fit(tmp_path / "b", config, *overrides, "--ckpt_path", str(middle)) == 0
    full = _latents(folder / "last.ckpt")
    resumed = _latents(tmp_path / "b" / name / "version_0" / "checkpoints" / "last.ckpt")
    for key in full:
        torch.testing.assert_close(resumed[key], full[key], rtol=1e-5, atol=1e-6)
        assert not torch.equal(_latents(middle)[key], full[key])


def test_loss_and_denoiser_by_name_with_options():
    module = InverseRenderingModule(scene="glossy_highlight", resolution=16, parameters={"light.azimuth": {"init": 0.5}},
                                    loss={"type": "loi", "alphas": [1, 5], "sigmas": [1]})
    assert type(module.loss_fn).__name__ == "LOILoss" and not module.loss_fn.pixelwise
    with pytest.raises(ValueError, match="model.loss"):
        InverseRenderingModule(scene="cbox", resolution=16, loss={"type": "l3"})
    with pytest.raises(ValueError, match="model.loss .loi."):
        InverseRenderingModule(scene="cbox", resolution=16, loss={"type": "loi", "alpha": 3})
    with pytest.raises(ValueError, match="couples pixels"):
        InverseRenderingModule(scene="cbox", resolution=16, loss={"type": "loi"}, sampler={"type": "adaptive", "budget": 8})
    assert InverseRenderingModule(scene="cbox", resolution=16, denoiser={"type": "none"}).denoiser is None
    with pytest.raises(ValueError, match="model.denoiser.type"):
        InverseRenderingModule(scene="cbox", resolution=16, denoiser={"type": "oidn"})


def test_combined_restir_and_denoiser_train_and_incompatible_combinations_are_refused(tmp_path):
    overrides = ["--model.sampler.burn_in", "2", "--trainer.max_steps", "2", "--checkpoint.every_n_train_steps", "0"]
    assert cli.main(
        ["fit", "--config", str(ROOT / "configs" / "combined_restir_target_aware.yaml"), "--model.resolution", "16",
         "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
         "--trainer.logger.init_args.save_dir", str(tmp_path), *overrides]
    ) == 0
    model = dict(yaml.safe_load((ROOT / "configs" / "combined_restir_target_aware.yaml").read_text())["model"])
    model.update(resolution=16, sampler={"type": "adaptive", "budget": 8})
    with pytest.raises(ValueError, match="denoiser needs full images"):
        InverseRenderingModule(**model)


def _restir(config: Path) -> bool:
    sampler = yaml.safe_load(config.read_text())["model"].get("sampler")
    return isinstance(sampler, dict) and sampler.get("type") == "restir"


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_every_config_runs_a_step(tmp_path, monkeypatch, config):
    """Each shipped config trains through ``torchir fit`` as written (16², one step, from a fresh
    working directory, so its ``results/`` lands there); ReSTIR's burn-in shortened to 2."""
    monkeypatch.chdir(tmp_path)
    extra = ["--model.sampler.burn_in", "2"] if _restir(config) else []
    argv = ["fit", "--config", str(config), "--model.resolution", "16", "--trainer.max_steps", "1",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false", *extra]
    assert cli.main(argv) == 0
    assert list((tmp_path / "results").rglob("result.yaml"))


OPTIONAL = ["seed_everything", "data", "images", "trainer", "trainer.logger", "model.loss", "model.lr", "model.spp",
            "model.resolution", "model.parameters.red.reflectance.value.bounds"]


@pytest.mark.parametrize("section", OPTIONAL)
def test_each_optional_section_can_be_left_out(tmp_path, monkeypatch, section):
    """The quickstart without one optional section (its defaults apply) still trains: what is
    left is the scene and a parameter. ``max_steps`` comes from the command line."""
    config = yaml.safe_load((ROOT / "configs" / "quickstart.yaml").read_text())
    keys = section.split(".")
    if keys[:2] == ["model", "parameters"]:
        keys = ["model", "parameters", ".".join(keys[2:-1]), keys[-1]]
    owner = config
    for key in keys[:-1]:
        owner = owner[key]
    del owner[keys[-1]]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    monkeypatch.chdir(tmp_path)
    argv = ["fit", "--config", "config.yaml", "--trainer.max_steps", "1", "--trainer.enable_progress_bar", "false"]
    if section != "model.resolution":
        argv += ["--model.resolution", "16"]
    assert cli.main(argv) == 0
    assert list(tmp_path.rglob("result.yaml"))
