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
from torchir.samplers import AdaptivePixelSampler, LossPixelSampler, PixelBatch, UniformPixelSampler, sampled_loss

from tests.helpers import DEVICE, RES, run_in_fresh_process

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
    mask = (moved > moved.mean()).flatten().cpu()  # where the pmf is
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
    why tests/training/test_guards_training.py checks the seeds themselves."""
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


def test_frozen_probe_replays_match_a_fresh_scene():
    """Stage-1 probes are frozen per scene; a replay (new values, tangent and seed) equals the
    same probe on a freshly loaded scene, whose first call is traced. In a fresh process, as
    :func:`tests.helpers.run_in_fresh_process` says why."""
    code = f"""
import torch, torchir
from torchir.functions.probe import probe_pixels

key = "{KEY}"
grids = [({RES // 2}, {RES // 2}), ({RES // 4}, {RES // 4})]
replayed, fresh = (torchir.Scene.builtin("cbox", resolution={RES}) for _ in range(2))
for step in range(3):
    value, tangent = torch.full((3,), 0.2 + 0.1 * step), torch.tensor([1.0, -1.0, (-1.0) ** step])
    args = dict(grids=grids, passes=2, seed=11 + step, tangents={{key: tangent}})
    radiance, derivative = probe_pixels(replayed, {{key: value}}, **args)
reference_radiance, reference_derivative = probe_pixels(fresh, {{key: value}}, **args)
for got, want in zip(radiance + derivative, reference_radiance + reference_derivative):
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
print("ok")
"""
    assert run_in_fresh_process(code).split()[-1] == "ok"


@pytest.mark.frozen
def test_probe_records_once_across_refreshes():
    """New seeds replay one recording. Building the constant lane arrays afresh for every call
    made the frozen pass re-record on some calls, varying from run to run. Run in a fresh
    process: Dr.Jit keys a recording on every instance in its registry, so a scene of another
    test freed between two calls re-records too, whatever the code under test does (it failed
    once in eleven full-suite orders, with the garbage collected and paused beforehand)."""
    code = (
        "import torch, torchir\n"
        "from torchir.functions.probe import probe_pixels\n"
        "from torchir.functions.render_pixels import _pixel_passes\n"
        f"scene = torchir.Scene.builtin('cbox', resolution={2 * RES})\n"
        "for step in range(12):\n"
        f"    probe_pixels(scene, {{'{KEY}': torch.full((3,), 0.5)}}, [({RES}, {RES})], passes=2, seed=100 + step)\n"
        "print('recordings', _pixel_passes(scene)._one_path.n_recordings)\n"
    )
    out = run_in_fresh_process(code)
    assert out.split()[-2:] == ["recordings", "1"], out[-500:]


# ------------------------------------------- Stage 1 and the sampled loss, renderer faked (issue 19)
class _FakeScene:
    """The scene attributes the samplers and ``sampled_loss`` read; the renderer is faked."""

    def __init__(self, resolution, views):
        self.resolution, self.sensor_count = resolution, views

    def sensor_resolution(self, view):
        return self.resolution


def _fake_probe(calls):
    """A stand-in for probe_pixels: radiance and derivative passes that depend only on
    (sensor, level), recording each call's arguments."""

    def probe(scene, params, grids, passes=4, seed=0, sensor=0, tangents=None, step=1e-2):
        calls.append(dict(params=params, grids=list(grids), passes=passes, seed=seed, sensor=sensor, tangents=tangents, step=step))
        radiance, derivative = [], []
        for d, (h, w) in enumerate(grids):
            g = torch.Generator(device=DEVICE).manual_seed(100 * sensor + d)
            radiance.append(torch.rand(passes, 3, h, w, generator=g))
            derivative.append(torch.randn(passes, 3, h, w, generator=g))
        return radiance, (derivative if tangents is not None else None)

    return probe


def _stage1_maps(calls, targets, views, count):
    """Independently: p1 ∝ mean_i sum_c (I - area(t))^2 (the L2 adjoint up to a constant per
    level, which the per-level normalisation cancels) and p2 = mean_i sum_c t^2, per level."""
    probe = _fake_probe([])
    grids = calls[0]["grids"]
    p1 = [torch.zeros(count, h, w, dtype=torch.float64) for h, w in grids]
    p2 = [torch.zeros(count, h, w, dtype=torch.float64) for h, w in grids]
    for target, v in zip(targets, views):
        radiance, derivative = probe(None, None, grids, calls[0]["passes"], sensor=v, tangents={})
        for d, (h, w) in enumerate(grids):
            small = F.avg_pool2d(target[None].double(), target.shape[-1] // w)[0]
            p1[d][v] = (radiance[d].double() - small).square().sum(1).mean(0)
            p2[d][v] = derivative[d].double().square().sum(1).mean(0)
    return p1, p2


@pytest.mark.parametrize("cls", [AdaptivePixelSampler, LossPixelSampler])
def test_stage1_pmf_is_built_from_the_probe_moments(monkeypatch, cls):
    """update() = update_from_maps(p1, p2) of the Stage-1 probes' second moments (E13, E14),
    each view's maps in its own slot, the probe called once per view with the sampler's
    passes, finite-difference step, a fresh seed and Rademacher tangents over the float
    parameters (for the adaptive strategy only)."""
    import time

    import torchir.functions.probe as probe_module

    calls: list[dict] = []
    monkeypatch.setattr(probe_module, "probe_pixels", _fake_probe(calls))
    n = 16
    options = dict(budget=8, levels=1, min_side=8, stage1_spp=3, fd_step=0.03, alpha=0.2, seed=5)
    s = cls(_FakeScene((n, n), 2), **options)
    assert s.stage1_grids == [(8, 8), (4, 4)]
    targets = torch.rand(2, 3, n, n, generator=torch.Generator(device=DEVICE).manual_seed(1))
    params = {"tex": torch.rand(4, 4, 3, requires_grad=True), "count": torch.tensor([2, 3])}
    started = time.perf_counter()
    s.update(params, targets, None, step=7)  # default loss: L2
    elapsed = time.perf_counter() - started
    adaptive = cls is AdaptivePixelSampler
    p1, p2 = _stage1_maps(calls, targets, [0, 1], 2)
    reference = cls(resolution=(n, n), views=2, **options)
    torch.testing.assert_close(s.pdf, reference.update_from_maps(p1, p2 if adaptive else None).reshape(-1), rtol=1e-5, atol=0)
    assert [c["sensor"] for c in calls] == [0, 1]
    for c in calls:
        assert c["passes"] == 3 and c["step"] == 0.03 and c["grids"] == s.stage1_grids
        assert set(c["params"]) == {"tex", "count"} and not c["params"]["tex"].requires_grad
        if adaptive:  # a ±1 direction over the float parameters only
            assert set(c["tangents"]) == {"tex"} and c["tangents"]["tex"].shape == (4, 4, 3)
            assert set(c["tangents"]["tex"].unique().tolist()) == {-1.0, 1.0}
        else:
            assert c["tangents"] is None
    d = s.diagnostics()
    assert d["stage1_paths"] == 2 * 3 * (64 + 16) * (2 if adaptive else 1)
    assert 0 < d["stage1_seconds"] <= elapsed
    assert (s.last_update, s.refreshes) == (7, 1) and not s.due(8, params)

    # one view, its target given as a single (C, H, W) image: only that view's maps are set
    first_seeds = [c["seed"] for c in calls]
    calls.clear()
    s.update(params, targets[1], L2Loss(), views=[1], step=9)
    assert [c["sensor"] for c in calls] == [1] and s.due(10, params) and not s.due(10, params, [1])
    p1, p2 = _stage1_maps(calls, targets[1:], [1], 2)
    torch.testing.assert_close(s.pdf, reference.update_from_maps(p1, p2 if adaptive else None).reshape(-1), rtol=1e-5, atol=0)
    # every refresh draws its probe seeds from the sampler's generator: new ones, in [0, 2^32)
    seeds = first_seeds + [c["seed"] for c in calls]
    again: list[dict] = []
    monkeypatch.setattr(probe_module, "probe_pixels", _fake_probe(again))
    twin = cls(_FakeScene((n, n), 2), **options)
    twin.update(params, targets, None, step=7)
    twin.update(params, targets[1], L2Loss(), views=[1], step=9)
    twin_seeds = [c["seed"] for c in again]
    assert twin_seeds == seeds and len(set(seeds)) == 3  # reproducible, and distinct
    assert all(0 <= x < 2**32 for x in twin_seeds)
    if adaptive:  # the tangents too come from the sampler's generator
        assert torch.equal(again[-1]["tangents"]["tex"], calls[-1]["tangents"]["tex"])
    # a fresh seed per probe: 40 refreshes draw 40 distinct seeds (for seeds uniform in
    # [0, 2^32 - 1), a repeat has probability 40^2 / 2 / 2^32 < 2e-7)
    many = cls(_FakeScene((n, n), 1), **options)
    again.clear()
    for step in range(40):
        many.update(params, targets[:1], None, step=step)
    assert len({c["seed"] for c in again}) == 40


def test_stage1_adaptive_without_float_parameters_probes_no_derivative(monkeypatch):
    import torchir.functions.probe as probe_module

    calls: list[dict] = []
    monkeypatch.setattr(probe_module, "probe_pixels", _fake_probe(calls))
    s = AdaptivePixelSampler(_FakeScene((8, 8), 1), budget=4, levels=0, min_side=4, stage1_spp=2)
    s.update({"count": torch.tensor([1])}, torch.rand(1, 3, 8, 8), step=0)
    assert calls[0]["tangents"] is None
    assert s.diagnostics()["stage1_paths"] == 2 * 4 * 4  # one pass per low-res pixel, no probe


def test_stage1_uses_the_given_per_pixel_loss(monkeypatch):
    """L1's adjoint is sign(I - t) / n: its squared sum over the 3 channels is the same at every
    pixel (no ties here), so the Eq. 5 pmf is uniform; L2's follows (I - t)^2."""
    import torchir.functions.probe as probe_module
    from torchir.modules import L1Loss

    calls: list[dict] = []
    monkeypatch.setattr(probe_module, "probe_pixels", _fake_probe(calls))
    target = torch.rand(1, 3, 8, 8, generator=torch.Generator(device=DEVICE).manual_seed(2))
    options = dict(budget=4, levels=0, min_side=4, sigma=0.0)
    l1 = LossPixelSampler(_FakeScene((8, 8), 1), **options)
    l1.update({}, target, L1Loss(), step=0)
    torch.testing.assert_close(l1.pdf, torch.full((64,), 1 / 64, dtype=torch.float64, device="cpu"), rtol=1e-9, atol=0)
    l2 = LossPixelSampler(_FakeScene((8, 8), 1), **options)
    l2.update({}, target, L2Loss(), step=0)
    p1, _ = _stage1_maps(calls, target, [0], 1)
    expected = LossPixelSampler(resolution=(8, 8), **options).update_from_maps(p1).reshape(-1)
    torch.testing.assert_close(l2.pdf, expected, rtol=1e-5, atol=0)
    assert float(expected.max() / expected.min()) > 1.5  # not flat: L1 and L2 differ


def test_stage1_argument_errors():
    from torch import nn

    class Coupled(nn.Module):
        def forward(self, rendered, target):
            return (rendered.mean() - target.mean()) ** 2

    class Undeclared(L2Loss):
        pixelwise = False

    s = AdaptivePixelSampler(_FakeScene((8, 6), 2), budget=4)  # not square: H and W told apart
    good = torch.rand(2, 3, 8, 6)
    with pytest.raises(ValueError, match=r"^update needs the target images \(one per view\)$"):
        s.update({}, None)
    with pytest.raises(ValueError, match=r"^got 1 target\(s\) for 2 view\(s\)$"):
        s.update({}, good[:1])
    with pytest.raises(ValueError, match=r"^got 2 target\(s\) for 1 view\(s\)$"):
        s.update({}, good, views=[1])
    with pytest.raises(ValueError, match=r"^targets must be \(C, 8, 6\) images, got \(3, 8, 4\)$"):
        s.update({}, [good[0], good[1, :, :, :4]])
    with pytest.raises(ValueError, match=r"^targets must be \(C, 8, 6\) images, got \(1, 3, 8, 6\)$"):
        s.update({}, [good[:1], good[1]])
    bad = good.clone()
    bad[1, 0, 2, 2] = float("inf")
    with pytest.raises(ValueError, match=r"^targets contain NaN/Inf$"):
        s.update({}, bad)
    tail = r"couples pixels \(or does not declare pixelwise = True\): pixel sampling needs a per-pixel loss \(l1, l2, relative_l2\); LOI, pyramid and SSIM losses need full images$"
    for loss in (Coupled(), Undeclared()):
        with pytest.raises(ValueError, match=f"^{type(loss).__name__} {tail}"):
            s.update({}, good, loss)
    # none of the refreshes above finished: none counts, and Stage 1 is still due at step 0
    assert s.refreshes == 0 and s.last_update is None and s.due(0, {})


def _fake_render(calls, images):
    def render_pixels(scene, params, index, spp=1, seed=0, sensor=0, spp_grad=None):
        calls.append(dict(index=index.clone(), spp=spp, seed=seed, sensor=sensor, spp_grad=spp_grad))
        listed = sensor if isinstance(sensor, list) else [sensor]  # a list: index k * H * W + pixel of listed[k]
        return params["x"] * images[listed].flatten(2).transpose(1, 2).flatten(0, 1)[index]

    return render_pixels


@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_sampled_loss_of_every_pixel_is_the_full_loss(monkeypatch, reduction):
    """A batch holding every pixel once with weight 1/m scores exactly the full-image loss
    (loss(image) = mean_j l_j), with its gradient; rows come grouped by view in the order of
    ``views``, raster order within a view, every view in one render_pixels call (one
    wavefront) with the first view's seed."""
    import torchir.functions as functions

    h, w, m = 4, 6, 2 * 4 * 6
    g = torch.Generator(device=DEVICE).manual_seed(3)
    images, targets = torch.rand(2, 3, h, w, generator=g), torch.rand(2, 3, h, w, generator=g)
    calls: list[dict] = []
    monkeypatch.setattr(functions, "render_pixels", _fake_render(calls, images))
    x = torch.tensor(0.7, requires_grad=True)
    order = torch.randperm(m, generator=g)
    weight = torch.rand(m, generator=g) + 0.5
    batch = PixelBatch(order, torch.full((m,), 1.0 / m))
    loss = L2Loss(reduction=reduction)
    scored = sampled_loss(_FakeScene((h, w), 2), {"x": x}, batch, [targets[1], targets[0]], [1, 0], loss, seed=lambda v: 50 + v, spp=3, spp_grad=5)
    full = loss(x * images, targets)
    torch.testing.assert_close(scored.loss, full, rtol=1e-5, atol=0)
    torch.testing.assert_close(torch.autograd.grad(scored.loss, x)[0], torch.autograd.grad(full, x)[0], rtol=1e-5, atol=0)
    raster = lambda t: torch.cat([t[1].flatten(1).t(), t[0].flatten(1).t()])
    torch.testing.assert_close(scored.radiance, raster(x * images))
    torch.testing.assert_close(scored.target, raster(targets))
    assert [(c["sensor"], c["seed"], c["spp"], c["spp_grad"]) for c in calls] == [([1, 0], 51, 3, 5)]
    assert torch.equal(calls[0]["index"], torch.arange(2 * h * w))  # view 1's pixels, then view 0's
    # arbitrary weights follow their pixels: loss = sum_n w_n l_n
    calls.clear()
    scored = sampled_loss(_FakeScene((h, w), 2), {"x": x}, PixelBatch(order, weight), targets, [0, 1], loss, seed=lambda v: v)
    terms = (x * images - targets).square().flatten(1).reshape(2, 3, -1).transpose(1, 2).reshape(m, 3)
    terms = terms.mean(1) if reduction == "mean" else terms.sum(1) * m
    by_pixel = torch.empty(m)
    by_pixel[order] = weight
    torch.testing.assert_close(scored.weight, by_pixel)
    assert [(c["sensor"], c["seed"], c["spp"], c["spp_grad"]) for c in calls] == [([0, 1], 0, 1, None)]  # defaults
    torch.testing.assert_close(scored.loss, (by_pixel * terms).sum(), rtol=1e-5, atol=0)


def test_sampled_loss_skips_views_without_draws(monkeypatch):
    import torchir.functions as functions

    h, w = 4, 6
    g = torch.Generator(device=DEVICE).manual_seed(4)
    images, targets = torch.rand(3, 3, h, w, generator=g), torch.rand(3, 3, h, w, generator=g)
    calls: list[dict] = []
    monkeypatch.setattr(functions, "render_pixels", _fake_render(calls, images))
    local = torch.tensor([5, 2, 5, 23])
    batch = PixelBatch(2 * h * w + local, torch.tensor([1.0, 2.0, 3.0, 4.0]))  # all in view 2
    x = torch.tensor(1.0)
    scored = sampled_loss(_FakeScene((h, w), 3), {"x": x}, batch, targets, [0, 1, 2], L2Loss(), seed=lambda v: v)
    assert [c["sensor"] for c in calls] == [2] and calls[0]["index"].tolist() == [2, 5, 5, 23]
    # raster order: the two draws of pixel 5 (weights 1 and 3) may come in either order
    assert scored.weight[[0, 3]].tolist() == [2.0, 4.0] and sorted(scored.weight[1:3].tolist()) == [1.0, 3.0]
    torch.testing.assert_close(scored.target, targets[2].flatten(1).t()[[2, 5, 5, 23]])
    # a view with a single draw is rendered like any other; views without draws are not listed
    calls.clear()
    batch = PixelBatch(torch.tensor([2 * h * w + 3, 7]), torch.tensor([0.25, 0.5]))
    scored = sampled_loss(_FakeScene((h, w), 3), {"x": x}, batch, targets, [0, 1, 2], L2Loss(), seed=lambda v: v)
    assert [(c["sensor"], c["index"].tolist()) for c in calls] == [([0, 2], [7, h * w + 3])]  # k * H * W + pixel of listed[k]
    assert scored.weight.tolist() == [0.5, 0.25]
    torch.testing.assert_close(scored.radiance, torch.stack([images[0].flatten(1)[:, 7], images[2].flatten(1)[:, 3]]))
    torch.testing.assert_close(scored.target, torch.stack([targets[0].flatten(1)[:, 7], targets[2].flatten(1)[:, 3]]))


def test_sampled_loss_of_one_view_matches_the_per_view_path(monkeypatch):
    """A batch of one view is sorted without per-view filtering; the draws, their order
    (raster, duplicates as argsort leaves them), weights and loss are those of the general path;
    draws outside that view are still left out."""
    import torchir.functions as functions

    h, w = 8, 8
    g = torch.Generator(device=DEVICE).manual_seed(5)
    images, targets = torch.rand(3, 3, h, w, generator=g), torch.rand(3, 3, h, w, generator=g)
    local = torch.randint(0, h * w, (500,), generator=g)  # many repeated pixels
    batch = PixelBatch(h * w + local, torch.rand(500, generator=g))
    runs = []
    for views, wanted in (([1], targets[1:2]), ([0, 1], targets[:2])):  # view 0 has no draws: the general path
        calls: list[dict] = []
        monkeypatch.setattr(functions, "render_pixels", _fake_render(calls, images))
        runs.append((calls, sampled_loss(_FakeScene((h, w), 3), {"x": torch.tensor(2.0)}, batch, wanted, views, L2Loss(), seed=lambda v: v)))
    (one_calls, one), (general_calls, general) = runs
    assert [c["sensor"] for c in one_calls] == [c["sensor"] for c in general_calls] == [1]
    assert torch.equal(one_calls[0]["index"], general_calls[0]["index"]) and one_calls[0]["index"].tolist() == sorted(local.tolist())
    for field in ("radiance", "target", "weight"):
        assert torch.equal(getattr(one, field), getattr(general, field)), field
    assert torch.equal(one.loss, general.loss)
    calls = []
    monkeypatch.setattr(functions, "render_pixels", _fake_render(calls, images))
    mixed = PixelBatch(torch.tensor([3, h * w + 9, 2 * h * w + 1, h * w + 4]), torch.tensor([1.0, 2.0, 3.0, 4.0]))
    scored = sampled_loss(_FakeScene((h, w), 3), {"x": torch.tensor(1.0)}, mixed, targets[1:2], [1], L2Loss(), seed=lambda v: v)
    assert [(c["sensor"], c["index"].tolist()) for c in calls] == [(1, [4, 9])] and scored.weight.tolist() == [4.0, 2.0]
