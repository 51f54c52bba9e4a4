"""Pixel sampling with the renderer (spec adaptive-sampling §6.2): Stage-1 probes, the
unbiased sampled gradient against full-image gradients, and the trainer's pixel mode."""
from __future__ import annotations

import csv
from pathlib import Path

import math

import pytest
import torch
import torch.nn.functional as F

import torchir
from torchir.functions import render
from torchir.functions.probe import probe_pixels
from torchir.modules import L2Loss
from torchir.samplers import AdaptivePixelSampler, LossPixelSampler, UniformPixelSampler, sampled_loss

from .conftest import RES

KEY = "red.reflectance.value"


def test_probe_low_res_matches_box_downsampled_render(cbox):
    radiance, derivative = probe_pixels(cbox, {}, [(RES // 2, RES // 2)], passes=64, seed=3)
    assert derivative is None and radiance[0].shape == (64, 3, RES // 2, RES // 2)
    full = render(cbox, {}, spp=64, seed=4)
    reference = F.avg_pool2d(full[None], 2)[0]
    mean, se = radiance[0].mean(0), radiance[0].std(0) / 8 + 1e-4
    z = (mean - reference) / torch.sqrt(se**2 + (reference * 0 + full.std() / 64) ** 2)
    assert float((z.abs() > 4).float().mean()) < 0.02


def test_probe_derivative_matches_finite_differences(cbox, red):
    v = torch.tensor([1.0, -1.0, 1.0])
    _, derivative = probe_pixels(cbox, {KEY: red.detach()}, [(RES, RES)], passes=32, seed=5, tangents={KEY: v})
    eps = 0.05
    plus = render(cbox, {KEY: red.detach() + eps * v}, spp=128, seed=9)
    minus = render(cbox, {KEY: red.detach() - eps * v}, spp=128, seed=9)
    fd = float((plus - minus).sum()) / (2 * eps)
    probe = float(derivative[0].mean(0).sum())
    assert probe == pytest.approx(fd, rel=0.1)


def test_probe_bad_input(cbox, red):
    with pytest.raises(KeyError, match="tangents"):
        probe_pixels(cbox, {}, [(4, 4)], tangents={KEY: torch.ones(3)})
    with pytest.raises(ValueError, match="shape"):
        probe_pixels(cbox, {KEY: red.detach()}, [(4, 4)], tangents={KEY: torch.ones(4)})
    with pytest.raises(ValueError, match="grid"):
        probe_pixels(cbox, {}, [(0, 4)])


def _target(scene, truth):
    return render(scene, truth, spp=256, seed=12345)


def test_stage1_adaptive_pmf_follows_the_parameter(cbox, red):
    """Only the red wall depends on its albedo: p2 (and so the adaptive pmf) concentrates there,
    while the Eq. 5 pmf does not know which pixels the parameter moves."""
    target = _target(cbox, {KEY: torch.tensor([0.9, 0.1, 0.1])})
    params = {KEY: red.detach()}
    adaptive = AdaptivePixelSampler(cbox, budget=64, alpha=0.1, seed=0)
    eq5 = LossPixelSampler(cbox, budget=64, alpha=0.1, seed=0)
    for s in (adaptive, eq5):
        assert s.due(0, params)
        s.update(params, target[None], L2Loss(), step=0)
        assert not s.due(1, params)
        assert abs(float(s.pdf.sum()) - 1) < 1e-12 and float(s.pdf.min()) >= 0.1 / RES**2 * (1 - 1e-9)
    # Pixels whose radiance moves with the red albedo (from a finite difference of full renders).
    moved = (render(cbox, {KEY: red.detach() + 0.2}, spp=64, seed=1) - render(cbox, {KEY: red.detach()}, spp=64, seed=1)).abs().sum(0)
    mask = (moved > moved.mean()).flatten()
    assert float(adaptive.pdf[mask].sum()) > float(eq5.pdf[mask].sum()) + 0.05
    d = adaptive.diagnostics()
    # E6: g = m sum a / (sum sqrt a)^2 >= 1 always, = 1 for a flat a = p1 p2. Here a sits on
    # the ~27 % of pixels the albedo moves (the mask above): a flat a there would give
    # g = 1 / 0.27 = 3.7 (measured 7.3, a is peaked inside it too).
    assert d["predicted_gain"] > 2.0
    # Stage 1 traces S one-path passes per low-res pixel of each level, twice (radiance and the
    # derivative probe): 2 * 4 * (8^2 + 4^2) + ... for the 16x16 image's levels (16, 8, 4).
    grids = adaptive.stage1_grids
    assert d["stage1_paths"] == 2 * adaptive.stage1_spp * sum(h * w for h, w in grids)
    assert eq5.diagnostics()["stage1_paths"] == eq5.stage1_spp * sum(h * w for h, w in grids)
    assert d["stage1_seconds"] > 0


def _sampled_gradient(scene, params, sampler, step, sensor_targets):
    """The trainer's estimator (paper 000, E16) on one pixel batch over every view."""
    views = list(range(scene.sensor_count))
    scored = sampled_loss(scene, params, sampler.sample(), sensor_targets, views, L2Loss(), seed=lambda v: 1000 * step + v)
    (grad,) = torch.autograd.grad(scored.loss, list(params.values()))
    return grad.flatten()


def _full_gradient(scene, params, targets, seed):
    images = torch.stack([render(scene, params, spp=4, seed=seed * 97 + v, sensor=v) for v in range(scene.sensor_count)])
    (grad,) = torch.autograd.grad(L2Loss()(images, targets), list(params.values()))
    return grad.flatten()


def _z_scores(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    se = torch.sqrt(a.var(0) / a.shape[0] + b.var(0) / b.shape[0]) + 1e-12
    return (a.mean(0) - b.mean(0)) / se


@pytest.mark.parametrize("cls", [UniformPixelSampler, LossPixelSampler, AdaptivePixelSampler])
def test_sampled_gradient_is_unbiased(cbox, cls):
    value = torch.tensor([0.3, 0.3, 0.3], requires_grad=True)
    params = {KEY: value}
    target = _target(cbox, {})
    sampler = cls(cbox, budget=48, seed=1)
    sampler.update({KEY: value.detach()}, target[None], L2Loss(), step=0)
    sampled = torch.stack([_sampled_gradient(cbox, params, sampler, i, [target]) for i in range(100)])
    full = torch.stack([_full_gradient(cbox, params, target[None], seed) for seed in range(30)])
    z = _z_scores(sampled, full)
    assert bool((z.abs() < 4.5).all()), z
    # the test has power: the gradient itself is many standard errors away from zero
    assert float((full.mean(0).abs() / (full.std(0) / math.sqrt(full.shape[0]))).max()) > 5


def test_sampled_gradient_multiview_global_pmf():
    scene = torchir.Scene.builtin("multiview", resolution=RES, views=2, texture=4)
    key = "object.bsdf.reflectance.data"
    value = torch.full(scene.get(key).shape, 0.5, requires_grad=True)
    targets = torch.stack([render(scene, {}, spp=128, seed=77 + v, sensor=v) for v in range(2)])
    sampler = AdaptivePixelSampler(scene, budget=64, seed=2)
    sampler.update({key: value.detach()}, targets, L2Loss(), step=0)
    assert sampler.pdf.numel() == 2 * RES * RES
    sampled = torch.stack([_sampled_gradient(scene, {key: value}, sampler, i, targets) for i in range(100)])
    full = torch.stack([_full_gradient(scene, {key: value}, targets, seed) for seed in range(30)])
    z = _z_scores(sampled, full)
    assert float((z.abs() > 3).float().mean()) <= 0.02 and float(z.abs().max()) < 5.0, z


# ------------------------------------------------------------------------------ trainer
def _fit(tmp_path, steps, **model):
    import lightning.pytorch as pl

    from torchir.training import InverseRenderingModule, ViewDataModule

    module = InverseRenderingModule(**{"scene": "cbox", "resolution": RES, "spp": 1, "lr": 0.05, **model})
    trainer = pl.Trainer(
        max_steps=steps, logger=pl.loggers.CSVLogger(tmp_path), enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path, log_every_n_steps=10,
    )
    trainer.fit(module, datamodule=ViewDataModule(target_spp=64))
    return module, trainer


def test_trainer_pixel_mode_reduces_parameter_error(tmp_path):
    """Pixel mode moves the albedo towards the truth. Its bound comes from a seeds study (the
    model's and the sampler's seed varied together over 0..19, offline): the final RMSE after
    40 steps ranges 0.011-0.228 for an initial 0.261 (ratio <= 0.87), so "< 0.5 x initial"
    failed 4 of 20 seeds of correct code; the bound here is the property itself, "< initial".
    That a frozen per-step seed is not caught by it (its errors, 0.014-0.425, overlap) is
    why tests/test_guards_training.py checks the seeds themselves."""
    model = {
        "parameters": {KEY: {"init": 0.3, "bounds": [0.0, 1.0]}},
        "sampler": {"type": "adaptive", "budget": 0.25, "refresh_every": 10, "seed": 0},
    }
    module, trainer = _fit(tmp_path, 40, **model)
    truth = module.ground_truth()
    assert module.parameter_error(truth) < float((torch.full((3,), 0.3) - truth[KEY]).square().mean().sqrt())
    metrics = module.step_metrics
    # Every pixel keeps p >= alpha / m (alpha = 0.1), so no weight exceeds 1 / (N alpha):
    # max_weight_ratio = N max w <= 10 (a pmf without the uniform mix breaks it).
    assert "sampler/ess_fraction" in metrics and 0 < float(metrics["sampler/max_weight_ratio"]) <= 10.0 + 1e-4
    assert module.sampler.refreshes == 4  # steps 0, 10, 20, 30
    # the diagnostics are logged on the steps the logger writes (every 10th), and only there
    rows = list(csv.DictReader(open(Path(trainer.logger.log_dir) / "metrics.csv")))
    assert [int(r["step"]) for r in rows if r.get("sampler/ess_fraction")] == [9, 19, 29, 39]


def test_trainer_rejects_pixel_coupling_losses_and_denoisers():
    from torch import nn

    from torchir.training import InverseRenderingModule

    class Coupled(nn.Module):
        def forward(self, rendered, target):
            return (rendered.mean() - target.mean()) ** 2

    with pytest.raises(ValueError, match="couples pixels"):
        InverseRenderingModule(scene="cbox", resolution=RES, loss=Coupled(), sampler={"type": "uniform", "budget": 8})
    with pytest.raises(ValueError, match="denoiser"):
        InverseRenderingModule(scene="cbox", resolution=RES, denoiser=nn.Identity(), sampler={"type": "uniform", "budget": 8})
    with pytest.raises(ValueError, match="sampler.type"):
        InverseRenderingModule(scene="cbox", resolution=RES, sampler={"type": "importance"})
    with pytest.raises(ValueError, match="budget"):
        InverseRenderingModule(scene="cbox", resolution=RES, sampler={"type": "adaptive", "budget": 0})


def test_sampler_state_is_checkpointed(cbox):
    from torchir.training import InverseRenderingModule

    module = InverseRenderingModule(scene="cbox", resolution=RES, sampler={"type": "loss", "budget": 8, "seed": 3})
    module.sampler.update_from_maps(torch.rand(1, 4, 4))
    checkpoint: dict = {}
    module.on_save_checkpoint(checkpoint)
    other = InverseRenderingModule(scene="cbox", resolution=RES, sampler={"type": "loss", "budget": 8, "seed": 9})
    other.on_load_checkpoint(checkpoint)
    assert torch.equal(other.sampler.pdf, module.sampler.pdf)
    assert torch.equal(other.sampler.sample().index, module.sampler.sample().index)
    assert math.isclose(float(other.sampler.pdf.sum()), 1.0, rel_tol=1e-12)


def test_frozen_probe_replays_match_a_fresh_scene(red):
    """Stage-1 probes are frozen per scene; a replay (new values, tangent and seed) equals the
    same probe on a freshly loaded scene, whose first call is traced."""
    grids = [(RES // 2, RES // 2), (RES // 4, RES // 4)]
    replayed, fresh = (torchir.Scene.builtin("cbox", resolution=RES) for _ in range(2))
    for step in range(3):
        value, tangent = torch.full((3,), 0.2 + 0.1 * step), torch.tensor([1.0, -1.0, (-1.0) ** step])
        args = dict(grids=grids, passes=2, seed=11 + step, tangents={KEY: tangent})
        radiance, derivative = probe_pixels(replayed, {KEY: value}, **args)
    reference_radiance, reference_derivative = probe_pixels(fresh, {KEY: value}, **args)
    for got, want in zip(radiance + derivative, reference_radiance + reference_derivative):
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


def test_probe_records_once_across_refreshes():
    """New seeds replay one recording. Building the constant lane arrays afresh for every call
    made the frozen pass re-record on some calls, varying from run to run: this test caught
    that regression in 1 of 4 runs, so it guards it only partly."""
    from torchir.functions.render_pixels import _pixel_passes

    scene = torchir.Scene.builtin("cbox", resolution=2 * RES)
    for step in range(12):
        probe_pixels(scene, {KEY: torch.full((3,), 0.5)}, [(RES, RES)], passes=2, seed=100 + step)
    assert _pixel_passes(scene)._one_path.n_recordings == 1
