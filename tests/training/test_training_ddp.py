"""Multi-view runs over 2 DDP processes (gloo) against one process: full renders, pixel
sampling and ReSTIR. A file of its own, so that the test run's file-wise distribution can put
these slow subprocess runs beside the rest of ``test_training.py``."""
from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchir import cli

from tests.helpers import ROOT, _latents, _run_dir


def _two_view_fit(tmp_path: Path, config: str, scene_options: str, *extra: str) -> None:
    """``torchir fit`` of ``config`` on 2 views of 8x8 (2 SGD steps, both views a step) in
    ``tmp_path``: in this process, or in a fresh one when ``extra`` asks for DDP (Lightning
    launches the second process from the command line it was started with). In-process saves
    the ~10 s a fresh process spends importing Lightning and torch."""
    args = [
        "fit", "--config", str(ROOT / "configs" / config),
        "--model.resolution", "8", "--model.scene_options", scene_options, "--model.spp", "2",
        "--model.optimizer", "sgd", "--model.lr", "5.0", "--data.views_per_step", "2", "--data.target_spp", "8",
        "--trainer.max_steps", "2", "--trainer.enable_progress_bar", "false", "--images.exr", "false",
        "--trainer.logger.init_args.save_dir", str(tmp_path), *extra,
    ]
    tmp_path.mkdir(parents=True, exist_ok=True)
    if "ddp" not in extra:
        assert cli.main(args) == 0
        return
    result = subprocess.run([sys.executable, "-m", "torchir", *args], capture_output=True, text=True, timeout=600,
                            cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr[-3000:]


def _multiview_run(tmp_path: Path, *extra: str, paths_per_step: int = 2 * 8 * 8 * (2 + 2)) -> dict[str, torch.Tensor]:
    _two_view_fit(tmp_path, "multiview.yaml", "{views: 2, texture: 4}", *extra)
    rows = list(csv.DictReader(open(_run_dir(tmp_path, "multiview") / "metrics.csv")))
    paths = {float(r["paths_per_step"]) for r in rows if r.get("paths_per_step")}
    assert paths == {paths_per_step}  # summed over processes: 2 views in all, not 2 per process
    return _latents(_run_dir(tmp_path, "multiview") / "checkpoints" / "last.ckpt")


def test_ddp_two_processes_match_one_process(tmp_path):
    """Views split over 2 processes (gloo) must give the single process's SGD trajectory."""
    single = _multiview_run(tmp_path / "one")
    ddp = _multiview_run(tmp_path / "two", "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu")
    initial = torch.full_like(next(iter(single.values())), 0.5)
    for key in single:
        assert not torch.allclose(single[key], initial)  # the run moved the texture
        torch.testing.assert_close(ddp[key], single[key], rtol=1e-4, atol=1e-6)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_ddp_pixel_sampling_shares_budget_and_stage1(tmp_path):
    """Pixel sampling over 2 processes: the 21-pixel budget and Stage 1 are shared, not repeated
    per process (paths per step summed over processes equal one process's: 11 + 10 draws), and
    the pmf Stage 1 assembles from the two processes' views is the single process's."""
    sampler = ("--model.sampler", "{type: adaptive, budget: 21, refresh_every: 1000, seed: 4}", "--trainer.log_every_n_steps", "1")
    paths = 21 * (2 + 2)  # + Stage 1 on step 0: 2 views x 4 passes x (8x8 + 4x4) px x 2 (probe)
    stage1 = 2 * 4 * (8 * 8 + 4 * 4) * 2
    rows = {}
    for name, extra in (("one", ()), ("two", ("--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu"))):
        latents = _multiview_run(tmp_path / name, *sampler, *extra, "--trainer.max_steps", "1", paths_per_step=paths + stage1)
        assert not torch.allclose(next(iter(latents.values())), torch.tensor(0.5, device="cpu"))  # the step moved the texture
        state = torch.load(_run_dir(tmp_path / name, "multiview") / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
        rows[name] = state["torchir_sampler"]
    assert rows["one"]["refreshes"] == rows["two"]["refreshes"] == 1
    assert not torch.allclose(rows["one"]["pmf"], torch.full_like(rows["one"]["pmf"], 1 / rows["one"]["pmf"].numel()))
    torch.testing.assert_close(rows["two"]["pmf"], rows["one"]["pmf"], rtol=0, atol=0)


def _restir_views_run(tmp_path: Path, multiview: str, *extra: str) -> dict[str, torch.Tensor]:
    sampler = f"{{type: restir, candidates: 4, burn_in: 2, multiview: {multiview}}}"
    _two_view_fit(tmp_path, "restir.yaml", "{views: 2, texture: 4, dim_lights: 1, hidden_lights: 1}",
                  "--model.sampler", sampler, *extra)
    return _latents(_run_dir(tmp_path, "restir") / "checkpoints" / "last.ckpt")


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_ddp_restir_keeps_each_process_s_reservoirs(tmp_path):
    """ReSTIR under DDP: each process keeps the reservoirs of the views it renders. Per-sensor
    chains depend only on (seed, step, view), so 2 processes give one process's trajectory."""
    ddp = ("--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu")
    single = _restir_views_run(tmp_path / "one", "per_sensor")
    split = _restir_views_run(tmp_path / "two", "per_sensor", *ddp)
    for key, value in single.items():
        assert not torch.allclose(value, torch.full_like(value, 0.5))  # the runs moved the texture
        torch.testing.assert_close(split[key], value, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_ddp_restir_carry_over_store_fits(tmp_path):
    """The carried-over store under DDP holds each process's own views (it cannot see the other
    process's reservoirs of this step), and the run still fits. (A smoke run of 2 processes:
    slow, so not in CI; the store's own tests run in one process.)"""
    ddp = ("--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu")
    store = _restir_views_run(tmp_path / "store", "carry_over", *ddp)
    for value in store.values():
        assert bool(torch.isfinite(value).all()) and not torch.allclose(value, torch.full_like(value, 0.5))


@pytest.mark.slow
def test_ddp_restir_auto_processes_agree_on_the_choice(tmp_path):
    """``{type: restir}`` under DDP: every process probes its own views, and runs with process 0's
    choice (the printed lines, which carry the probe's own figures, are the same)."""
    import yaml

    config = {"model": {"scene": "oxalis_lite", "resolution": 12, "scene_options": {"views": 2, "texture": 4},
                        "parameters": {"canvas.bsdf.reflectance.data": {"init": 0.5}}, "sampler": {"type": "restir"}},
              "data": {"target_spp": 8, "views_per_step": 2},
              "trainer": {"max_steps": 1, "strategy": "ddp", "devices": 2, "accelerator": "cpu", "enable_progress_bar": False}}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    result = subprocess.run([sys.executable, "-m", "torchir", "fit", "--config", "run.yaml"], capture_output=True, text=True,
                            timeout=600, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr[-3000:]
    # the two processes write to one pipe: their lines may interleave, so each is read by its pattern
    lines = re.findall(r"\[torchir\] ReSTIR auto: .*?\(probe [0-9.]+ s\)", result.stdout + result.stderr)
    assert len(lines) == 2 and lines[0] == lines[1]
