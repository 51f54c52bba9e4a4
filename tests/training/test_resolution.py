"""Coarse-to-fine volume grids (ParameterConfig.resolution): the schedule's validation, the
optimiser-state swap, the resize of the latent and its Adam moments at the scheduled step, the
parameter error at the truth's resolution, and a run resumed after a resize."""
from __future__ import annotations

import csv
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from torchir import cli
from torchir.geometry import AdamUniform
from torchir.training import InverseRenderingModule
from torchir.training.param_swap import map_state, swap_parameter
from torchir.training.resolution import apply_schedule, parse_schedule
from torchir.volumes import resample

from tests.helpers import ROOT, _latents, _run_dir

KEY = "object.interior_medium.sigma_t.data"
EXAMPLE = str(ROOT / "configs" / "examples" / "volume_from_views.yaml")
BUILD = f"{ROOT}/configs/examples/volume_from_views.py:build"
TINY = {"grid": 8, "views": 2, "max_depth": 2}  # an 8² film (model.resolution), two views, an 8³ truth


# ------------------------------------------------------------------------------ the schedule
def test_schedule_forms_and_stages():
    s = parse_schedule(KEY, {"8": 0, "8x16x16": 3, "[16, 16, 32]": 5, 32: 9})
    assert s.first == (8, 8, 8)
    assert [s.shape_at(t) for t in (0, 2, 3, 4, 5, 8, 9, 100)] == [
        (8, 8, 8), (8, 8, 8), (8, 16, 16), (8, 16, 16), (16, 16, 32), (16, 16, 32), (32, 32, 32), (32, 32, 32)]


@pytest.mark.parametrize("spec, message", [
    ([16, 64], "non-empty mapping"),
    ({}, "non-empty mapping"),
    ({16: 5, 64: 20}, "must start at step 0"),
    ({16: 0, 64: 20, 32: 10}, "strictly increasing"),
    ({16: 0, 64: 0}, "strictly increasing"),
    ({16: 0, 64: -1}, "int >= 0"),
    ({16: 0, 64: True}, "int >= 0"),
    ({0: 0}, "int n >= 1"),
    ({"16x16": 0}, "int n >= 1"),
    ({"big": 0}, "int n >= 1"),
])
def test_schedule_errors_name_the_key(spec, message):
    with pytest.raises(ValueError, match=message) as error:
        parse_schedule(KEY, spec)
    assert f"parameters[{KEY!r}].resolution" in str(error.value)


# ---------------------------------------------------------------------- the optimiser surgery
@pytest.mark.parametrize("make", [lambda p: torch.optim.Adam(p, lr=0.1), lambda p: AdamUniform(p, lr=0.1),
                                  lambda p: torch.optim.SGD(p, lr=0.1, momentum=0.9)])
def test_swap_parameter_carries_a_given_state_and_keeps_the_others(make):
    """The new tensor steps from the state it was given (as the old one would, mapped), the other
    parameter keeps its own; fresh (None) starts it over."""
    torch.manual_seed(0)
    a, other = torch.nn.Parameter(torch.rand(4)), torch.nn.Parameter(torch.rand(2))
    opt = make([{"params": [a]}, {"params": [other], "lr": 0.05}])
    for _ in range(2):
        a.grad, other.grad = torch.rand(4), torch.rand(2)
        opt.step()
    twin = torch.nn.Parameter(a.detach().repeat(2))  # what "a" becomes, mapped to 8 entries
    reference = make([twin])
    reference.state[twin] = map_state(opt.state[a], a, lambda t: t.repeat(2))
    new = torch.nn.Parameter(a.detach().repeat(2))
    other_state = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in opt.state[other].items()}
    swap_parameter(opt, a, new, map_state(opt.state[a], a, lambda t: t.repeat(2)))
    assert opt.param_groups[0]["params"] == [new] and a not in opt.state
    grad = torch.rand(8)
    new.grad, twin.grad, other.grad = grad, grad.clone(), None
    opt.step()
    reference.step()
    torch.testing.assert_close(new.detach(), twin.detach())
    for k, v in other_state.items():
        assert torch.equal(torch.as_tensor(opt.state[other][k]), torch.as_tensor(v))
    fresh = torch.nn.Parameter(torch.zeros(3))
    swap_parameter(opt, new, fresh)
    assert fresh not in opt.state and opt.param_groups[0]["params"][0] is fresh
    with pytest.raises(ValueError, match="not one of the optimiser's"):
        swap_parameter(opt, new, torch.nn.Parameter(torch.zeros(1)))


# ------------------------------------------------------------------------------- the module
def _module(**entry) -> InverseRenderingModule:
    config = {"init": 0.002, "bounds": [1e-6, 1.0], "resolution": {4: 0, 8: 2}, **entry}
    return InverseRenderingModule(scene=BUILD, resolution=8, scene_options=dict(TINY), parameters={KEY: config}, spp=1, preview_spp=1)


def test_the_resize_resamples_the_value_and_adam_s_moments_and_keeps_the_step():
    """At the scheduled step the latent becomes a new 8³ parameter holding the 4³ value resampled;
    Adam's exp_avg and exp_avg_sq are the old ones resampled, its step count is kept; the
    optimiser steps the new tensor; before the step nothing changes."""
    module = _module()
    p = module.scene_parameters[0]
    assert tuple(p.latent.shape) == (4, 4, 4, 1) and bool((p() == 0.002).all())
    opt = module.configure_optimizers()
    module._trainer = SimpleNamespace(optimizers=[opt], world_size=1)
    torch.manual_seed(0)
    for _ in range(2):
        p.latent.grad = torch.randn_like(p.latent) * 1e-3
        opt.step()
        p.project()
    old, state = p.latent, {k: v.clone() for k, v in opt.state[p.latent].items()}
    assert apply_schedule(module, 1) == [] and p.latent is old
    assert apply_schedule(module, 2) == [KEY]
    new = p.latent
    assert tuple(new.shape) == (8, 8, 8, 1) and opt.param_groups[0]["params"][0] is new and old not in opt.state
    torch.testing.assert_close(new.detach(), resample(old.detach(), (8, 8, 8)))
    for name in ("exp_avg", "exp_avg_sq"):
        assert opt.state[new][name].shape == (8, 8, 8, 1)
        torch.testing.assert_close(opt.state[new][name], resample(state[name], (8, 8, 8)))
    assert float(opt.state[new]["step"]) == 2.0
    new.grad = torch.ones_like(new)
    opt.step()
    assert float(opt.state[new]["step"]) == 3.0 and bool((new.detach() < resample(old.detach(), (8, 8, 8))).all())
    assert apply_schedule(module, 3) == [] and p.latent is new


def test_density_and_rgb_albedo_grids_resize_together_and_both_get_gradients():
    """Yan et al.'s volume task, density and albedo per voxel: an RGB albedo grid (C = 3) takes a
    schedule beside the density's; at the step both become 8³ (the albedo keeps its 3 channels),
    and a render of the resized scene differentiates both."""
    from torchir.functions import render

    albedo = "object.interior_medium.albedo.data"
    schedule = {"bounds": [0.0, 1.0], "resolution": {4: 0, 8: 2}}
    module = InverseRenderingModule(
        scene=BUILD, resolution=8, scene_options={**TINY, "albedo_grid": 8}, spp=1, preview_spp=1,
        parameters={KEY: {"init": 0.05, "bounds": [1e-6, 1.0], "resolution": {4: 0, 8: 2}}, albedo: {"init": 0.5, **schedule}},
    )
    assert [tuple(p.latent.shape) for p in module.scene_parameters] == [(4, 4, 4, 1), (4, 4, 4, 3)]
    module._trainer = SimpleNamespace(optimizers=[module.configure_optimizers()], world_size=1)
    assert sorted(apply_schedule(module, 2)) == sorted([KEY, albedo])
    assert [tuple(p.latent.shape) for p in module.scene_parameters] == [(8, 8, 8, 1), (8, 8, 8, 3)]
    image = render(module.scene, module.scene_values(), spp=4, seed=0)
    image.sum().backward()
    for p in module.scene_parameters:
        assert p.latent.grad is not None and torch.isfinite(p.latent.grad).all() and float(p.latent.grad.abs().sum()) > 0


def test_a_resize_rebuilds_the_ddp_wrapper_once_and_only_when_it_resizes(monkeypatch):
    """Under DDP the reducer holds the tensors it was built with: after a step that resizes a grid
    the wrapper is rebuilt (once for all the grids resized at that step); a step that resizes
    nothing leaves it be."""
    from torchir.training import param_swap

    rewrapped = []
    monkeypatch.setattr(param_swap, "rewrap_distributed", lambda trainer: rewrapped.append(trainer))
    module = _module()
    trainer = SimpleNamespace(optimizers=[module.configure_optimizers()], world_size=2)
    module._trainer = trainer
    assert apply_schedule(module, 1) == [] and rewrapped == []
    assert apply_schedule(module, 2) == [KEY] and rewrapped == [trainer]
    assert apply_schedule(module, 3) == [] and rewrapped == [trainer]


def test_a_log_grid_resamples_its_value_and_per_entry_bounds_follow():
    """Transform log: the value (not the log) is resampled; per-entry bounds reach the new size."""
    module = _module(init="random", bounds=None, transform="log", seed=3)
    p = module.scene_parameters[0]
    before = p().detach()
    module._trainer = SimpleNamespace(optimizers=[], world_size=1)
    apply_schedule(module, 2)
    torch.testing.assert_close(p().detach(), resample(before, (8, 8, 8)), rtol=1e-5, atol=1e-7)
    bounded = _module(bounds=[[1e-6], [0.5]])
    bounded._trainer = None
    apply_schedule(bounded, 5)
    lo, hi = bounded.scene_parameters[0].bounds
    assert lo.shape == hi.shape == (8, 8, 8, 1) and bool((hi == 0.5).all())


def test_the_parameter_error_is_taken_at_the_truth_s_resolution():
    """The 4³ grid against the scene's 8³ truth: the RMSE of the grid resampled to 8³."""
    module = _module()
    truth = module.value_truth()
    assert truth[KEY].shape == (8, 8, 8, 1)
    expected = math.sqrt(float((resample(module.scene_parameters[0]().detach(), (8, 8, 8)) - truth[KEY]).square().mean()))
    assert module.parameter_error(truth) == pytest.approx(expected, rel=1e-6)
    assert module.parameter_errors(truth)[KEY] == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("entry, error, message", [
    ({"key": "light.radiance.value"}, ValueError, "applies to the data of a gridvolume"),
    ({"init": "target.png"}, ValueError, "cannot initialise a volume grid"),
    ({"init": [[0.1]] * 3}, ValueError, "does not fit"),
    ({"resolution": {4: 3}}, ValueError, "must start at step 0"),
])
def test_config_errors_are_clear(entry, error, message):
    entry = dict(entry)
    key = entry.pop("key", KEY)
    config = {"init": 0.5, "resolution": {4: 0, 8: 2}, **entry}
    with pytest.raises(error, match=message):
        InverseRenderingModule(scene=BUILD, resolution=8, scene_options=dict(TINY), parameters={key: config})


# ------------------------------------------------------------------------- runs and resumes
def _fit(save_dir: Path, *overrides: str) -> int:
    # 8² film, 2 views, 4³ from step 0 and 8³ from step 2, every step checkpointed
    return cli.main(
        ["fit", "--config", EXAMPLE, "--model.resolution", "8", "--model.scene_options", str(TINY).replace("'", ""),
         "--model.parameters", f"{{{KEY}: {{resolution: {{4: 0, 8: 2}}, lr: 0.05}}}}", "--model.spp", "1",
         "--model.preview_spp", "1", "--data.target_spp", "4", "--trainer.max_steps", "5",
         "--checkpoint.every_n_train_steps", "1", "--trainer.enable_progress_bar", "false",
         "--trainer.enable_model_summary", "false", "--trainer.logger.init_args.save_dir", str(save_dir), *overrides]
    )


def _optimiser_state(ckpt: Path) -> dict:
    return torch.load(ckpt, map_location="cpu", weights_only=False)["optimizer_states"][0]["state"][0]


def _rows(folder: Path) -> list[dict[str, str]]:
    with open(folder / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    save_dir = tmp_path_factory.mktemp("volume")
    assert _fit(save_dir) == 0
    return _run_dir(save_dir, name="volume_from_views")


def test_a_fit_through_a_resize_changes_the_latent_and_the_optimiser_state_at_the_step(run):
    """Checkpoints after steps 1 and 2 hold 4³ (steps 0, 1 ran there); after step 3, 8³, with
    Adam's moments at 8³ and its step count 3; every logged loss is finite."""
    folder = run / "checkpoints"
    shapes = {}
    for n in (1, 2, 3, 5):
        ckpt = next(folder.glob(f"epoch=*-step={n}.ckpt"))
        state = _optimiser_state(ckpt)
        shapes[n] = (tuple(_latents(ckpt)["scene_parameters.0.latent"].shape), tuple(state["exp_avg"].shape), float(state["step"]))
    assert shapes == {1: ((4, 4, 4, 1), (4, 4, 4, 1), 1.0), 2: ((4, 4, 4, 1), (4, 4, 4, 1), 2.0),
                      3: ((8, 8, 8, 1), (8, 8, 8, 1), 3.0), 5: ((8, 8, 8, 1), (8, 8, 8, 1), 5.0)}
    losses = [float(r["loss"]) for r in _rows(run) if r.get("loss")]
    assert len(losses) == 5 and all(math.isfinite(x) for x in losses)


def test_a_run_resumed_after_the_resize_continues_the_uninterrupted_run(run, tmp_path):
    """Resumed from the checkpoint after step 3 (an 8³ latent), the run rebuilds the grid at 8³
    before Lightning loads it and Adam's state, and ends where the uninterrupted run ends (rtol
    1e-5: float32 atomics); its metrics.csv holds one history, steps 0..5."""
    middle = next((run / "checkpoints").glob("epoch=*-step=3.ckpt"))
    assert _fit(tmp_path, "--ckpt_path", str(middle)) == 0
    resumed_run = _run_dir(tmp_path, name="volume_from_views")
    full = _latents(run / "checkpoints" / "last.ckpt")["scene_parameters.0.latent"]
    resumed = _latents(resumed_run / "checkpoints" / "last.ckpt")["scene_parameters.0.latent"]
    torch.testing.assert_close(resumed, full, rtol=1e-5, atol=1e-7)
    assert not torch.equal(_latents(middle)["scene_parameters.0.latent"], full)
    torch.testing.assert_close(_optimiser_state(resumed_run / "checkpoints" / "last.ckpt")["exp_avg_sq"],
                               _optimiser_state(run / "checkpoints" / "last.ckpt")["exp_avg_sq"], rtol=1e-5, atol=1e-12)
    steps = [int(r["step"]) for r in _rows(resumed_run)]
    assert steps == sorted(steps) and sorted(set(steps)) == [0, 1, 2, 3, 4, 5]


@pytest.mark.slow  # two fresh processes (~40 s on 2 cores): `python3 -m pytest -m slow`
def test_ddp_two_processes_resize_as_one_process(tmp_path):
    """A resize under DDP (gloo, 2 processes, the 2 views of a step split between them) follows one
    process's trajectory: both take the same grid and the new grid's gradients are averaged over
    them (a DDP wrapper left on the 4³ tensor would not reduce the 8³ one's)."""
    import os
    import subprocess
    import sys

    args = ["fit", "--config", EXAMPLE, "--model.resolution", "8", "--model.scene_options", str(TINY).replace("'", ""),
            "--model.parameters", f"{{{KEY}: {{resolution: {{4: 0, 8: 2}}, lr: 0.05}}}}", "--model.spp", "2",
            "--model.preview_spp", "1", "--data.target_spp", "4", "--data.views_per_step", "2", "--trainer.max_steps", "4",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]
    assert cli.main([*args, "--trainer.logger.init_args.save_dir", str(tmp_path / "one")]) == 0
    ddp = ["--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu"]
    result = subprocess.run([sys.executable, "-m", "torchir", *args, "--trainer.logger.init_args.save_dir", str(tmp_path / "two"), *ddp],
                            capture_output=True, text=True, timeout=600, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr[-3000:]
    one = _latents(_run_dir(tmp_path / "one", name="volume_from_views") / "checkpoints" / "last.ckpt")["scene_parameters.0.latent"]
    two = _latents(_run_dir(tmp_path / "two", name="volume_from_views") / "checkpoints" / "last.ckpt")["scene_parameters.0.latent"]
    assert tuple(one.shape) == (8, 8, 8, 1)
    torch.testing.assert_close(two, one, rtol=1e-4, atol=1e-6)
