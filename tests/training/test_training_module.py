"""Fast, exact tests of :mod:`torchir.training.module` (the LightningModule), written for the
mutation audit: each test calls the module's own methods with a stand-in trainer (a namespace
with the attributes the module reads) and, where an image is needed, a torch stand-in for the
render, so what is checked is module.py's own arithmetic and bookkeeping. One test renders a
real 4x4 image to tie the stand-in to the real call. No Lightning ``Trainer`` runs here.
"""
from __future__ import annotations

import importlib
import math
import re
from types import SimpleNamespace

import torchir  # noqa: F401  (before torch: sets the OpenMP policy)

import numpy as np
import pytest
import torch
from torch import nn

import torchir.samplers as samplers
import torchir.training._resolve as resolve_module
import torchir.training.module as module
from torchir import Scene, scenes
from torchir.modules import DENOISERS, LOSSES, L1Loss, L2Loss
from torchir.samplers import SAMPLERS, PixelBatch, PixelSampler, SampledLoss
from torchir.scene import _unbindable_hint
from torchir.training import InverseRenderingModule, ParameterConfig
from torchir.training.module import NonFiniteLossError, _as_config, _from_checkpoint, _to_checkpoint

from tests.helpers import DEVICE

render_module = importlib.import_module("torchir.functions.render")  # the module, not the function it exports
KEY = "red.reflectance.value"
GREEN = "green.reflectance.value"
RES = 4


def make(**kwargs) -> InverseRenderingModule:
    kwargs.setdefault("scene", "cbox")
    kwargs.setdefault("resolution", RES)
    kwargs.setdefault("parameters", {KEY: {"init": 0.3}})
    return InverseRenderingModule(**kwargs)


def attach(model, **attrs) -> SimpleNamespace:
    """A stand-in trainer with the attributes module.py reads."""
    trainer = SimpleNamespace(**{
        "world_size": 1, "global_rank": 0, "global_step": 0, "current_epoch": 0, "log_every_n_steps": 1, "loggers": [],
        "should_stop": False, "datamodule": None, "log_dir": None, "default_root_dir": "/tmp/root",
        "progress_bar_callback": None, "callbacks": [], **attrs,
    })
    model._trainer = trainer
    return trainer


def record_logs(model) -> list:
    calls = []
    model.log = lambda name, value, **kw: calls.append((name, value, kw))
    return calls


class FakeRender:
    """``render`` stand-in: view ``v`` is ``(1 + v) * red`` at every pixel (differentiable)."""

    def __init__(self) -> None:
        self.calls: list[dict] = []

    def __call__(self, scene, values, **kwargs):
        self.calls.append(kwargs)
        h, w = scene.resolution
        return (values[KEY] * (1 + kwargs["sensor"])).view(3, 1, 1).expand(3, h, w)


@pytest.fixture()
def fake_render(monkeypatch) -> FakeRender:
    fake = FakeRender()
    monkeypatch.setattr(module, "render", fake)
    return fake


class PassThrough(nn.Module):
    """A denoiser that returns the noisy image."""

    def forward(self, noisy, target):
        return noisy


class FakeLogger:
    def __init__(self) -> None:
        self.rows: list = []

    def log_metrics(self, row, step):
        self.rows.append((row, step))


class FakeRenderSampler:
    """A non-pixel sampler (like ReSTIR) registered as ``fake`` in SAMPLERS."""

    def __init__(self, scene, **options) -> None:
        self.scene, self.options, self.loaded = scene, options, []

    def diagnostics(self):
        return {"mean_m": 3, "time_ris": 0.5}

    def state_dict(self):
        return {"x": np.arange(3, dtype=np.float32)}

    def load_state_dict(self, state):
        self.loaded.append(state)


@pytest.fixture()
def fake_sampler(monkeypatch) -> list:
    checks = []
    monkeypatch.setitem(SAMPLERS, "fake", FakeRenderSampler)
    monkeypatch.setattr(render_module, "_check_sampler", lambda scene, sampler, names: checks.append((scene, sampler, names)))
    return checks


class ScriptedPixelSampler(PixelSampler):
    """A pixel sampler whose refreshes, draws and diagnostics the test sets."""

    strategy = "scripted"

    def __init__(self, scene, due_at=(), diagnostics=None, **options) -> None:
        super().__init__(scene, **options)
        self.due_at, self.diag, self.updates, self.due_calls = set(due_at), diagnostics or {}, [], []

    def due(self, step, params=None, views=None):
        self.due_calls.append((step, sorted(params), views))
        return step in self.due_at

    def update(self, params, targets, loss, views=None, step=None):
        self.updates.append((sorted(params), targets, loss, views, step))

    def sample(self, views=None):
        return PixelBatch(index=torch.arange(5), weight=torch.ones(5))

    def diagnostics(self):
        return dict(self.diag)


# ------------------------------------------------------------------------- construction
def test_defaults_and_attributes():
    model = InverseRenderingModule(resolution=RES)  # the default scene is cbox
    assert model.keys == list(scenes.get("cbox").parameters)
    for key in model.keys:
        torch.testing.assert_close(model.scene_values()[key], torch.full((3,), 0.5))
    assert (model.spp, model.spp_grad, model.seed, model.lr) == (8, 8, 0, 0.05)
    assert (model.optimizer_name, model.preview_spp, model.lr_half_life) == ("adam", 64, None)
    assert model.nonfinite is None and model.step_metrics == {} and model._write_logs_at is None
    assert type(model.loss_fn) is L2Loss and model.denoiser is None and model.sampler is None
    assert model.scene.resolution == (RES, RES) and model.scene.name == "cbox"
    other = make(spp=3, spp_grad=5, seed=9, lr=0.2, optimizer="sgd", preview_spp=2, lr_half_life=1)
    assert (other.spp, other.spp_grad, other.seed, other.lr) == (3, 5, 9, 0.2)
    assert (other.optimizer_name, other.preview_spp, other.lr_half_life) == ("sgd", 2, 1)


def test_hyperparameters_leave_out_loss_and_denoiser_modules(monkeypatch):
    import inspect
    import os

    ignored = []
    real = InverseRenderingModule.save_hyperparameters

    def spy(self, *args, ignore=None, **kwargs):
        ignored.append(ignore)
        return real(self, *args, ignore=ignore, frame=inspect.currentframe().f_back, **kwargs)

    monkeypatch.setattr(InverseRenderingModule, "save_hyperparameters", spy)
    model = make(spp=3, loss=L1Loss(), denoiser=nn.Identity())
    assert ignored == [["loss", "denoiser"]]
    assert "loss" not in model.hparams and "denoiser" not in model.hparams
    if "MUTANT_UNDER_TEST" not in os.environ:  # mutmut's trampolines hide __init__'s frame from Lightning
        assert model.hparams["spp"] == 3 and model.hparams["scene"] == "cbox" and model.hparams["resolution"] == RES


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"spp": 0}, "model.spp must be >= 1, got 0"),
        ({"preview_spp": 0}, "model.preview_spp must be >= 1, got 0"),
        ({"spp_grad": 0}, "model.spp_grad must be >= 1, got 0"),
        ({"spp": -2}, "model.spp must be >= 1, got -2"),
        ({"lr": 0}, "model.lr must be a finite number > 0 (gradient descent), got 0"),
        ({"lr": -0.5}, "model.lr must be a finite number > 0 (gradient descent), got -0.5"),
        ({"lr": float("nan")}, "model.lr must be a finite number > 0 (gradient descent), got nan"),
        ({"lr": float("inf")}, "model.lr must be a finite number > 0 (gradient descent), got inf"),
        ({"lr_half_life": 0}, "model.lr_half_life must be a number of steps >= 1 (or null), got 0"),
        ({"lr_half_life": True}, "model.lr_half_life must be a number of steps >= 1 (or null), got True"),
        ({"lr_half_life": 2.0}, "model.lr_half_life must be a number of steps >= 1 (or null), got 2.0"),
        ({"lr_half_life": "3"}, "model.lr_half_life must be a number of steps >= 1 (or null), got '3'"),
        ({"parameters": {}}, "model.parameters is empty: nothing to optimise"),
    ],
)
def test_invalid_settings_are_refused_with_their_message(kwargs, message):
    with pytest.raises(ValueError) as error:
        make(**kwargs)
    assert str(error.value) == message


def test_smallest_valid_counts_are_accepted():
    model = make(spp=1, spp_grad=1, preview_spp=1, lr=1e-9, lr_half_life=1)
    assert (model.spp, model.spp_grad, model.preview_spp, model.lr_half_life) == (1, 1, 1, 1)


class FakeSceneLoader:
    """Stands in for ``Scene`` where a run's config is resolved (training/_resolve.py), recording how scenes are loaded."""

    calls: list = []

    @classmethod
    def builtin(cls, name, resolution=None, override_integrator=None, **options):
        cls.calls.append(("builtin", name, resolution, override_integrator, options))
        return Scene.builtin("cbox", resolution=RES)

    @classmethod
    def from_file(cls, path, override_integrator=None, **options):
        cls.calls.append(("from_file", path, override_integrator, options))
        scene = Scene.builtin("cbox", resolution=RES)
        scene.is_builtin = False
        return scene


def test_scene_loading_passes_name_resolution_options_and_integrator(monkeypatch):
    monkeypatch.setattr(resolve_module, "Scene", FakeSceneLoader)
    FakeSceneLoader.calls = []
    integrator = {"type": "prb", "max_depth": 2}
    make(scene="cbox", resolution=6, scene_options={"foo": 1}, integrator=integrator)
    make(scene="cbox", resolution=None)
    make(scene="room.xml", resolution=None, scene_options={"spp": 3}, integrator=integrator)
    assert FakeSceneLoader.calls == [
        ("builtin", "cbox", 6, integrator, {"foo": 1}),
        ("builtin", "cbox", None, None, {}),
        ("from_file", "room.xml", integrator, {"spp": 3}),
    ]
    with pytest.raises(ValueError) as error:
        make(scene="room.xml", resolution=8)
    assert str(error.value) == "resolution applies to built-in scenes and to model.sensors; set the film size in the XML file instead"
    with pytest.raises(ValueError) as error:
        make(scene="room.xml", resolution=None, parameters=None)
    assert str(error.value) == "model.parameters is required for scenes loaded from files"
    assert len(FakeSceneLoader.calls) == 4  # the refused resolution never reached a loader


def test_derived_parameters_are_declared_before_parameters_are_read(monkeypatch, fake_sampler):
    declared = []
    real = module.declare_derived
    monkeypatch.setattr(module, "declare_derived", lambda scene, label, spec: (declared.append((label, spec)), real(scene, label, spec)))
    spec = {"type": "rigid", "shape": "small-box"}
    model = make(derived={"box": spec}, parameters={"box.translation": {"init": 0.0}, KEY: {}}, sampler={"type": "fake", "k": 2})
    assert declared == [("box", spec)]
    assert model.keys == ["box.translation", KEY]
    # a non-pixel sampler is checked against the Mitsuba keys the parameters move
    (scene, sampler, names), = fake_sampler
    assert scene is model.scene and sampler is model.sampler and sampler.scene is model.scene and sampler.options == {"k": 2}
    assert names == frozenset({"small-box.vertex_positions", KEY})


def test_parameter_configs_and_field_errors():
    config = ParameterConfig(init=0.2)
    model = make(parameters={KEY: config, GREEN: None})
    assert model.configs[KEY] is config and model.configs[GREEN] == ParameterConfig()
    assert model.keys == [KEY, GREEN] and [p.key for p in model.scene_parameters] == [KEY, GREEN]
    with pytest.raises(ValueError) as error:
        make(parameters={KEY: {"init": 0.2, "bonds": [0, 1], "lrr": 1}})
    allowed = sorted(ParameterConfig.__dataclass_fields__)
    assert str(error.value) == f"parameters['{KEY}'] has unknown field(s) ['bonds', 'lrr']; allowed: {allowed}"
    with pytest.raises(TypeError) as error:
        make(parameters={KEY: 0.3})
    assert str(error.value) == f"parameters['{KEY}'] must be a mapping of ParameterConfig fields, got float"


def test_as_config_forms():
    config = ParameterConfig(lr=0.1)
    assert _as_config("k", config) is config
    assert _as_config("k", None) == ParameterConfig()
    assert _as_config("k", {"init": 0.7, "transform": "log"}) == ParameterConfig(init=0.7, transform="log")


def test_unbindable_parameter_is_refused_with_a_hint():
    key = "sensor.near_clip"
    with pytest.raises(TypeError) as error:
        make(parameters={key: {}})
    assert str(error.value) == f"parameters[{key!r}]: {key!r} has type float, which torchir cannot optimise: {_unbindable_hint(key, 'float')}"
    with pytest.raises(KeyError, match="red.reflectance.value"):
        make(parameters={"red.reflectance.valu": {}})


def test_initial_values_are_checked_as_differentiable_and_stored_detached(monkeypatch):
    seen = []
    real = Scene.check_values
    monkeypatch.setattr(Scene, "check_values", lambda self, values: (seen.append({k: (v.clone(), v.requires_grad) for k, v in values.items()}), real(self, values))[1])
    model = make(parameters={KEY: {"init": [0.1, 0.2, 0.3]}})
    value, requires_grad = seen[0][KEY]
    assert requires_grad and torch.equal(value, torch.tensor([0.1, 0.2, 0.3]))
    latent = model.scene_parameters[0].latent
    assert latent.is_leaf and latent.grad_fn is None
    with pytest.raises(ValueError, match=re.escape("parameters['red.reflectance.value'].init has shape (2,)")):
        make(parameters={KEY: {"init": [0.1, 0.2]}})
    with pytest.raises(ValueError, match=re.escape("parameters['red.reflectance.value'].init must be a number")):
        make(parameters={KEY: {"init": "bogus"}})


def test_random_init_uses_the_parameters_bounds_and_seed():
    model = make(parameters={KEY: {"init": "random", "bounds": [0.2, 0.4], "seed": 7}})
    # drawn on the host, as torchir draws it (the same values on every device)
    expected = (0.2 + 0.2 * torch.rand(3, generator=torch.Generator(device="cpu").manual_seed(7), device="cpu")).to(DEVICE)
    torch.testing.assert_close(model.scene_values()[KEY].detach(), expected)


def test_ground_truth_from_config_else_the_scene():
    model = make(parameters={KEY: {"truth": 0.2}, GREEN: {}})
    scene_green = model.scene.get(GREEN)
    truth = model.ground_truth()
    assert list(truth) == [KEY, GREEN]
    torch.testing.assert_close(truth[KEY], torch.full((3,), 0.2))
    torch.testing.assert_close(truth[GREEN], scene_green)
    explicit = model.ground_truth(explicit_only=True)
    assert list(explicit) == [KEY]
    later = make(parameters={GREEN: {}, KEY: {"truth": 0.2}})  # a key without truth before one with it
    assert list(later.ground_truth(explicit_only=True)) == [KEY]
    with pytest.raises(ValueError, match=re.escape(f"parameters['{KEY}'].truth must be a number")):
        make(parameters={KEY: {"truth": "bogus"}}).ground_truth()


def test_scene_values_follow_the_latents():
    model = make(parameters={KEY: {"init": 0.3, "transform": "log"}, GREEN: {"init": 0.6}})
    values = model.scene_values()
    assert list(values) == [KEY, GREEN]
    torch.testing.assert_close(values[KEY], torch.full((3,), 0.3))
    assert values[KEY].requires_grad and values[KEY].grad_fn is not None  # exp of the latent
    torch.testing.assert_close(values[GREEN], torch.full((3,), 0.6))


# ----------------------------------------------------------------------------- losses etc.
def test_loss_by_name_mapping_or_module():
    assert type(make(loss="l1").loss_fn) is L1Loss
    assert type(make(loss="relative_l2").loss_fn) is LOSSES["relative_l2"]
    custom = nn.L1Loss()
    assert make(loss=custom).loss_fn is custom
    spec = {"type": "relative_l2", "eps": 0.5}
    loss = make(loss=spec).loss_fn
    assert type(loss) is LOSSES["relative_l2"] and loss.eps == 0.5
    assert spec == {"type": "relative_l2", "eps": 0.5}  # the caller's mapping is left alone
    for bad in ("l3", 3, None):
        with pytest.raises(ValueError) as error:
            make(loss=bad)
        assert str(error.value) == (
            f"model.loss must be one of {sorted(LOSSES)}, {{type: name, ...options}} or an nn.Module class path, got {bad!r}"
        )
    with pytest.raises(ValueError) as error:
        make(loss={"type": "l3"})
    assert str(error.value) == f"model.loss.type must be one of {sorted(LOSSES)}, got 'l3'"
    with pytest.raises(ValueError) as error:
        make(loss={"eps": 1})
    assert str(error.value) == f"model.loss.type must be one of {sorted(LOSSES)}, got None"
    with pytest.raises(ValueError) as error:
        make(loss={"type": "l1", "eps": 1})
    assert str(error.value).startswith("model.loss (l1): ") and "eps" in str(error.value)
    assert isinstance(error.value.__cause__, TypeError)


def test_denoiser_forms():
    assert make(denoiser=None).denoiser is None
    assert make(denoiser={"type": "none"}).denoiser is None
    assert make(denoiser={"sigma": 1}).denoiser is None
    identity = nn.Identity()
    assert make(denoiser=identity).denoiser is identity
    name = sorted(DENOISERS)[0]
    assert type(make(denoiser={"type": name}).denoiser) is DENOISERS[name]
    with pytest.raises(ValueError) as error:
        make(denoiser="target_aware")
    assert str(error.value) == "model.denoiser must be {type: name, ...options} or an nn.Module class path, got 'target_aware'"
    with pytest.raises(ValueError) as error:
        make(denoiser={"type": "oidn"})
    assert str(error.value) == f"model.denoiser.type must be one of {sorted(DENOISERS)}, got 'oidn'"


def test_sampler_forms(fake_sampler):
    assert make(sampler=None).sampler is None
    assert make(sampler={"type": "none", "budget": 3}).sampler is None
    model = make(sampler={"type": "uniform", "budget": 5})
    assert type(model.sampler) is SAMPLERS["uniform"] and model.sampler.budget == 5 and model.sampler.scene is model.scene
    assert model.pixel_mode and fake_sampler == []  # pixel samplers are not render samplers
    with pytest.raises(ValueError) as error:
        make(sampler="uniform")
    assert str(error.value) == "model.sampler must be a mapping {type: name, ...options}, got 'uniform'"
    with pytest.raises(ValueError) as error:
        make(sampler={"type": "unifrom"})
    assert str(error.value) == f"model.sampler.type must be one of {sorted(SAMPLERS)}, got 'unifrom'"
    with pytest.raises(ValueError) as error:
        make(sampler={"type": "uniform", "budgett": 3})
    assert str(error.value).startswith("model.sampler (uniform): ")


class PixelTermsOnly(nn.Module):
    def forward(self, rendered, target):
        return (rendered - target).square().mean()

    def pixel_terms(self, rendered, target, pixel_count):
        return (rendered - target).square().mean(-1)


def test_pixel_sampler_needs_a_pixelwise_loss_and_no_denoiser():
    sampler = {"type": "uniform", "budget": 4}
    for loss, name in ((PixelTermsOnly(), "PixelTermsOnly"), (nn.MSELoss(), "MSELoss")):
        with pytest.raises(ValueError) as error:
            make(loss=loss, sampler=sampler)
        assert str(error.value) == (
            f"model.loss {name} couples pixels: it cannot be used with the pixel sampler 'uniform'; "
            "use l1, l2 or relative_l2, or drop model.sampler"
        )

    class FlagWithoutTerms(nn.Module):
        pixelwise = True

        def forward(self, rendered, target):
            return rendered.sum()

    with pytest.raises(ValueError, match="^model.loss FlagWithoutTerms couples pixels"):
        make(loss=FlagWithoutTerms(), sampler=sampler)
    terms = PixelTermsOnly()
    terms.pixelwise = True
    assert make(loss=terms, sampler=sampler).loss_fn is terms
    with pytest.raises(ValueError) as error:
        make(sampler=sampler, denoiser=nn.Identity())
    assert str(error.value) == "a denoiser needs full images: it cannot be combined with a pixel sampler (model.sampler)"


# ---------------------------------------------------------------------------------- seeds
def test_step_seed_is_the_documented_hash_of_seed_step_and_view():
    model = make(scene="multiview", scene_options={"views": 2, "texture": 4}, parameters=None, seed=3)
    assert model.scene.sensor_count == 2
    # (seed * 2654435761 + step * sensor_count + view) mod 2^32 (Knuth's multiplicative hash)
    assert model.step_seed(5, 1) == (3 * 2654435761 + 5 * 2 + 1) % 2**32
    seeds = [model.step_seed(step, view) for step in range(6) for view in range(2)]
    assert seeds == [(3 * 2654435761 + i) % 2**32 for i in range(12)]  # consecutive: never reused
    big = make(seed=2**31)
    assert big.step_seed(0, 0) == (2**31 * 2654435761) % 2**32 and 0 <= big.step_seed(7, 0) < 2**32
    assert make(seed=0).step_seed(4, 0) == 4


def test_render_views_renders_each_view_with_its_step_seed(fake_render):
    model = make(spp=3, spp_grad=2, seed=1)
    images = model.render_views([0, 1], step=4)
    assert images.shape == (2, 3, RES, RES)
    torch.testing.assert_close(images[1], 2 * images[0])
    assert fake_render.calls == [
        {"spp": 3, "seed": model.step_seed(4, v), "sensor": v, "spp_grad": 2} for v in (0, 1)
    ]
    fake_render.calls.clear()
    model.forward([0])
    assert fake_render.calls == [{"spp": 3, "seed": model.step_seed(0, 0), "sensor": 0, "spp_grad": 2}]


def test_render_views_passes_a_render_sampler_but_not_a_pixel_sampler(fake_render, fake_sampler):
    model = make(sampler={"type": "fake"})
    model.render_views([0], step=0)
    assert fake_render.calls[-1]["sampler"] is model.sampler
    pixel = make(sampler={"type": "uniform", "budget": 4})
    pixel.render_views([0], step=0)
    assert "sampler" not in fake_render.calls[-1]


def test_training_step_matches_an_independent_real_render():
    """The real render: the step's loss is the L2 loss of the image rendered with the
    documented seed, spp and spp_grad (renders are deterministic given the seed)."""
    from torchir.functions import render

    model = make(spp=1, spp_grad=1, seed=2, loss="l1")
    attach(model, global_step=3)
    record_logs(model)
    model._truth = {}
    targets = torch.full((1, 3, RES, RES), 0.25)
    loss = model.training_step({"view": torch.tensor([0]), "target": targets}, 0)
    image = render(model.scene, {KEY: torch.full((3,), 0.3)}, spp=1, seed=model.step_seed(3, 0), sensor=0, spp_grad=1)
    torch.testing.assert_close(loss.detach(), (image - targets[0]).abs().mean())
    loss.backward()
    assert model.scene_parameters[0].latent.grad is not None


# ----------------------------------------------------------------------------- the step
def _step(model, views, targets, step=0, **trainer):
    attach(model, global_step=step, **trainer)
    logs = record_logs(model)
    out = model.training_step({"view": torch.tensor(views), "target": targets}, 0)
    return out, logs


def test_full_image_step_loss_error_paths_and_gradient(fake_render):
    model = make(loss="l1", spp=3, spp_grad=2)
    model._truth = {KEY: torch.full((3,), 0.5)}
    targets = torch.full((2, 3, RES, RES), 0.5)
    loss, logs = _step(model, [0, 0], targets, step=6)
    # both views render 0.3 against 0.5
    torch.testing.assert_close(loss.detach(), torch.tensor(0.2))
    loss.backward()
    torch.testing.assert_close(model.scene_parameters[0].latent.grad, torch.full((3,), -1 / 3))
    metrics = model.step_metrics
    assert list(metrics) == ["loss", "image_error", "paths_per_step", "param_error"]
    assert metrics["loss"] == pytest.approx(0.2) and metrics["image_error"] == pytest.approx(0.04)
    assert metrics["paths_per_step"] == 2 * RES * RES * (3 + 2)
    assert metrics["param_error"] == pytest.approx(0.2)
    assert [c["seed"] for c in fake_render.calls] == [model.step_seed(6, 0)] * 2
    assert len(logs) == 1 and logs[0][2]["batch_size"] == 2


def test_l2_loss_is_not_logged_twice_as_image_error(fake_render):
    model = make()
    model._truth = {}
    loss, _ = _step(model, [0], torch.full((1, 3, RES, RES), 0.5))
    assert list(model.step_metrics) == ["loss", "paths_per_step"]
    assert model.step_metrics["loss"] == pytest.approx(0.04)
    summed = make(loss={"type": "l2", "reduction": "sum"})
    summed._truth = {}
    _step(summed, [0], torch.full((1, 3, RES, RES), 0.5))
    assert summed.step_metrics["image_error"] == pytest.approx(0.04)
    assert summed.step_metrics["loss"] == pytest.approx(0.04 * 3 * RES * RES)


def test_clipped_target_pixels_are_left_out_whole(fake_render):
    """With data.saturation s, a target pixel with any channel >= 0.995 s counts as clipped:
    the render takes the target's value there (no error, no gradient), in every channel."""
    model = make(loss="l2", denoiser=PassThrough())  # a denoiser: image_error is logged
    model._truth = {}
    targets = torch.full((2, 3, RES, RES), 0.5)  # two views (both sensor 0): the mask is per view
    targets[0, 0, 0, 0] = 1.99  # clipped (s = 2: 0.995 s = 1.99)
    targets[0, 2, 1, 1] = 1.989  # just below: kept
    targets[1, 1, 2, 3] = 2.5  # clipped, in the second view only
    datamodule = SimpleNamespace(saturation=2.0)
    loss, _ = _step(model, [0, 0], targets, datamodule=datamodule)
    kept_mask = torch.ones(2, 3, RES, RES)
    kept_mask[0, :, 0, 0] = 0.0
    kept_mask[1, :, 2, 3] = 0.0
    kept = torch.where(kept_mask > 0, torch.full_like(targets, 0.3), targets)
    expected = (kept - targets).square().mean()
    torch.testing.assert_close(loss.detach(), expected)
    assert model.step_metrics["image_error"] == pytest.approx(float(expected))
    loss.backward()
    expected_grad = (2 * (0.3 - targets) * kept_mask).sum((0, 2, 3)) / targets.numel()
    torch.testing.assert_close(model.scene_parameters[0].latent.grad, expected_grad)
    # without a saturation nothing is left out
    model2 = make(loss="l2", denoiser=PassThrough())
    model2._truth = {}
    loss2, _ = _step(model2, [0, 0], targets, datamodule=SimpleNamespace(saturation=None))
    torch.testing.assert_close(loss2.detach(), (torch.full_like(targets, 0.3) - targets).square().mean())


def test_image_error_is_of_the_render_before_the_denoiser(fake_render):
    calls = []

    class ToTarget(nn.Module):
        def forward(self, noisy, target):
            calls.append(noisy.detach().clone())
            return target + 0 * noisy

    model = make(loss="l1", denoiser=ToTarget())
    model._truth = {}
    model.guide_buffers = lambda views, step: pytest.fail("no guide for a denoiser that does not ask")
    loss, _ = _step(model, [0], torch.full((1, 3, RES, RES), 0.5))
    assert float(loss.detach()) == 0.0 and model.step_metrics["image_error"] == pytest.approx(0.04)
    torch.testing.assert_close(calls[0], torch.full((1, 3, RES, RES), 0.3))


def test_guide_buffers_only_for_denoisers_that_need_them(fake_render):
    guides = []

    class Guided(nn.Module):
        needs_guide = True

        def forward(self, noisy, target, guide=None, views=None):
            guides.append((guide, views))
            return noisy

    model = make(denoiser=Guided())
    model._truth = {}
    sentinel = torch.zeros(1, 7, RES, RES)
    model.guide_buffers = lambda views, step: (guides.append(("built", views, step)), sentinel)[1]
    _step(model, [0], torch.full((1, 3, RES, RES), 0.5), step=2)
    assert guides[0] == ("built", [0], 2) and guides[1][0] is sentinel and guides[1][1] == [0]
    plain = make()
    plain._truth = {}
    plain.guide_buffers = lambda views, step: pytest.fail("no denoiser, no guide")
    _step(plain, [0], torch.full((1, 3, RES, RES), 0.5))


def test_denoise_passes_guide_and_views_only_to_denoisers_that_take_them():
    seen = []

    class Plain(nn.Module):
        def forward(self, noisy, target, **kw):
            seen.append(kw)
            return noisy

    class WithViews(nn.Module):
        def forward(self, noisy, target, views=None, guide=None):
            seen.append({"views": views, "guide": guide})
            return noisy

    images, targets, guide = torch.ones(1, 3, 2, 2), torch.zeros(1, 3, 2, 2), torch.ones(1, 7, 2, 2)
    model = make(denoiser=Plain())
    assert model.denoise(images, targets, [0], None) is images
    model.denoise(images, targets, [0], guide)
    assert seen[0] == {} and seen[1].keys() == {"guide"} and seen[1]["guide"] is guide
    model = make(denoiser=WithViews())
    model.denoise(images, targets, [3], None)
    assert seen[2] == {"views": [3], "guide": None}


@pytest.mark.parametrize("bad", [float("inf"), float("nan")])
def test_nonfinite_loss_stops_before_recording(fake_render, bad):
    class Bad(nn.Module):
        def forward(self, rendered, target):
            return (rendered - target).abs().mean() * 0 + bad

    model = make(loss=Bad())
    model._truth = {}
    out, logs = _step(model, [0], torch.full((1, 3, RES, RES), 0.5), step=7)
    assert out is None and model.trainer.should_stop is True
    assert model.nonfinite == f"the loss became {bad} at step 7 (views [0]); the run stopped before applying that step"
    assert logs == [] and model.step_metrics == {} and model._write_logs_at is None
    assert issubclass(NonFiniteLossError, RuntimeError)


# --------------------------------------------------------------------------- pixel mode
@pytest.fixture()
def fake_sampled_loss(monkeypatch) -> list:
    calls = []

    def fake(scene, params, batch, targets, views, loss, seed, spp=1, spp_grad=None):
        calls.append({"scene": scene, "params": sorted(params), "batch": batch, "targets": targets, "views": views,
                      "loss": loss, "seeds": [seed(v) for v in (0, 1)], "spp": spp, "spp_grad": spp_grad})
        radiance = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
        target = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 3.0]])
        weight = torch.tensor([2.0, 0.5])
        return SampledLoss(params[KEY].sum() * 10, radiance.requires_grad_(), target, weight)

    monkeypatch.setattr(samplers, "sampled_loss", fake)
    return calls


def test_sampled_loss_weights_the_squared_error_and_counts_paths(fake_sampled_loss):
    model = make(sampler={"type": "uniform", "budget": 6}, spp=3, spp_grad=2, seed=4)
    targets = torch.zeros(1, 3, RES, RES)
    loss, error, paths = model.sampled_loss([0], targets, step=5)
    torch.testing.assert_close(loss, torch.tensor(9.0))
    # sum_n w_n mean_c (r - t)^2: 2 * (0 + 1 + 4) / 3 + 0.5 * 9 / 3
    assert float(error) == pytest.approx(2 * 5 / 3 + 0.5 * 3) and not error.requires_grad
    assert paths == 6 * (3 + 2)
    call, = fake_sampled_loss
    assert call["scene"] is model.scene and call["params"] == [KEY] and call["targets"] is targets and call["views"] == [0]
    assert call["loss"] is model.loss_fn and (call["spp"], call["spp_grad"]) == (3, 2)
    assert call["batch"].index.numel() == 6
    assert call["seeds"] == [model.step_seed(5, 0), model.step_seed(5, 1)]


def test_sampled_loss_draws_from_the_batch_views_only(fake_sampled_loss):
    model = make(scene="multiview", scene_options={"views": 2, "texture": 4}, parameters={"object.bsdf.reflectance.data": {}},
                 sampler={"type": "uniform", "budget": 32})
    values = dict(model.scene_values())
    values[KEY] = torch.zeros(3)  # the stand-in reads KEY
    model.scene_values = lambda: values
    model.sampled_loss([1], torch.zeros(1, 3, RES, RES), step=0)
    index = fake_sampled_loss[0]["batch"].index
    assert index.numel() == 32 and bool(((index >= RES * RES) & (index < 2 * RES * RES)).all())


def _scripted(monkeypatch, **options):
    monkeypatch.setitem(SAMPLERS, "scripted", ScriptedPixelSampler)
    return make(sampler={"type": "scripted", **options}, spp=2, spp_grad=1)


def test_pixel_step_refreshes_when_due_and_counts_stage1_paths(monkeypatch, fake_sampled_loss):
    model = _scripted(monkeypatch, due_at=[0], diagnostics={"stage1_paths": 100, "ess_fraction": 0.5})
    model._truth = {}
    targets = [torch.zeros(3, RES, RES)]
    data = SimpleNamespace(views=[0], targets=targets, saturation=None)
    loss, _ = _step(model, [0], torch.zeros(1, 3, RES, RES), step=0, datamodule=data)
    sampler = model.sampler
    assert sampler.updates == [([KEY], targets, model.loss_fn, [0], 0)] and sampler.due_calls == [(0, [KEY], [0])]
    call, = fake_sampled_loss
    assert call["views"] == [0] and call["targets"].shape == (1, 3, RES, RES) and call["seeds"][0] == model.step_seed(0, 0)
    assert model.step_metrics["paths_per_step"] == 5 * 3 + 100
    assert model.step_metrics["sampler/stage1_paths"] == 100.0 and model.step_metrics["sampler/ess_fraction"] == 0.5
    torch.testing.assert_close(loss.detach(), torch.tensor(9.0))
    _step(model, [0], torch.zeros(1, 3, RES, RES), step=1, datamodule=data)
    assert len(sampler.updates) == 1 and model.step_metrics["paths_per_step"] == 5 * 3


def test_pixel_step_evaluates_the_parameters_once(monkeypatch, fake_sampled_loss):
    model = _scripted(monkeypatch, due_at=[0])
    model._truth = {KEY: torch.full((3,), 0.5)}
    evaluated = []
    scene_values = model.scene_values
    model.scene_values = lambda: evaluated.append(1) or scene_values()
    data = SimpleNamespace(views=[0], targets=[torch.zeros(3, RES, RES)], saturation=None)
    _step(model, [0], torch.zeros(1, 3, RES, RES), step=0, datamodule=data)
    # Stage 1, the render and the parameter error all see the one evaluation
    assert len(evaluated) == 1 and len(model.sampler.updates) == 1 and len(fake_sampled_loss) == 1
    assert model.step_metrics["param_error"] == pytest.approx(model.parameter_error(model._truth))


def test_pixel_step_without_stage1_paths_diagnostic(monkeypatch, fake_sampled_loss):
    model = _scripted(monkeypatch, due_at=[0], diagnostics={"ess_fraction": 1.0})
    model._truth = {}
    data = SimpleNamespace(views=[0], targets=[torch.zeros(3, RES, RES)], saturation=None)
    _step(model, [0], torch.zeros(1, 3, RES, RES), step=0, datamodule=data)
    assert len(model.sampler.updates) == 1 and model.step_metrics["paths_per_step"] == 5 * 3
    assert model.refresh_sampler(0) is True and model.refresh_sampler(1) is False


def test_refresh_sampler_needs_the_datamodule_targets(monkeypatch):
    model = _scripted(monkeypatch)
    message = "pixel sampling needs the target views of a ViewDataModule (trainer.datamodule)"
    with pytest.raises(RuntimeError) as error:
        model.refresh_sampler(0)
    assert str(error.value) == message
    for data in (None, SimpleNamespace(views=[0]), SimpleNamespace(views=[0], targets=[])):
        attach(model, datamodule=data)
        with pytest.raises(RuntimeError) as error:
            model.refresh_sampler(0)
        assert str(error.value) == message


# ---------------------------------------------------------------------------- logging
def test_record_step_single_process_logs_loss_once_and_keeps_the_row(fake_sampler):
    model = make(loss="l1", sampler={"type": "fake"})
    model._truth = {KEY: torch.full((3,), 0.3)}
    attach(model, global_step=4, log_every_n_steps=5, loggers=[FakeLogger()])
    logs = record_logs(model)
    loss = torch.tensor(1.5, requires_grad=True)
    model._record_step(loss, torch.tensor(0.25), 77.0, 3)
    assert model.step_metrics == {
        "loss": 1.5, "image_error": 0.25, "paths_per_step": 77.0, "sampler/mean_m": 3.0, "sampler/time_ris": 0.5, "param_error": 0.0,
    }
    assert all(type(v) is float for v in model.step_metrics.values())
    assert model._write_logs_at == 4
    assert logs == [("loss", loss, {"prog_bar": True, "on_step": True, "on_epoch": False, "batch_size": 3, "sync_dist": True, "logger": False})]
    attach(model, global_step=5, log_every_n_steps=5, loggers=[FakeLogger()])
    model._record_step(loss, torch.tensor(0.25), 77.0, 3)
    assert model._write_logs_at is None
    model.sampler = SimpleNamespace()  # a sampler without diagnostics adds no sampler/* entries
    model._record_step(loss, torch.tensor(0.25), 77.0, 3)
    assert list(model.step_metrics) == ["loss", "image_error", "paths_per_step", "param_error"]


def test_record_step_under_ddp_logs_every_metric_with_its_reduction(fake_sampler):
    model = make(loss="l1", sampler={"type": "fake"})
    model._truth = {}
    attach(model, world_size=2, global_step=0, log_every_n_steps=1, loggers=[FakeLogger()])
    logs = record_logs(model)
    loss = torch.tensor(2.0)
    model._record_step(loss, torch.tensor(0.5), 10.0, 2)
    common = {"on_step": True, "on_epoch": False, "batch_size": 2}
    assert logs == [
        ("loss", loss, {"prog_bar": True, **common, "sync_dist": True, "logger": True}),
        ("image_error", 0.5, {**common, "reduce_fx": "mean", "sync_dist": True}),
        ("paths_per_step", 10.0, {**common, "reduce_fx": "sum", "sync_dist": True}),
        ("sampler/mean_m", 3.0, {**common, "reduce_fx": "mean", "sync_dist": False}),
        ("sampler/time_ris", 0.5, {**common, "reduce_fx": "mean", "sync_dist": False}),
    ]
    # not a logging step: only the loss goes through self.log
    attach(model, world_size=2, global_step=0, log_every_n_steps=2, loggers=[FakeLogger()])
    logs = record_logs(model)
    model._record_step(loss, torch.tensor(0.5), 10.0, 2)
    assert [name for name, _, _ in logs] == ["loss"]


def test_loggers_write_follows_log_every_n_steps():
    model = make()
    assert model._loggers_write() is True  # no trainer: plain use
    attach(model, loggers=[], log_every_n_steps=1)
    assert model._loggers_write() is False
    for step, every, stop, expected in [
        (2, 3, False, True), (5, 3, False, True), (3, 3, False, False), (0, 3, False, False),
        (3, 3, True, True), (0, 1, False, True), (4, 0, True, False), (4, -1, True, False),
    ]:
        attach(model, loggers=[FakeLogger()], global_step=step, log_every_n_steps=every, should_stop=stop)
        assert model._loggers_write() is expected, (step, every, stop)


def test_on_train_batch_end_writes_the_row_once_on_logging_steps():
    model = make()
    logger_a, logger_b = FakeLogger(), FakeLogger()
    attach(model, loggers=[logger_a, logger_b], current_epoch=2)
    model.step_metrics = {"loss": 1.0, "seconds_per_step": 0.1}
    model._write_logs_at = 9
    model.on_train_batch_end(None, None, 0)
    row = {"loss": 1.0, "seconds_per_step": 0.1, "epoch": 2.0}
    assert logger_a.rows == [(row, 9)] and logger_b.rows == [(row, 9)] and type(logger_a.rows[0][0]["epoch"]) is float
    assert model._write_logs_at is None
    model.on_train_batch_end(None, None, 0)
    assert len(logger_a.rows) == 1
    model._write_logs_at = 0  # step 0 is a step, not "none"
    model.on_train_batch_end(None, None, 0)
    assert logger_a.rows[-1] == (row, 0)
    attach(model, loggers=[logger_a], world_size=2)
    model._write_logs_at = 3
    model.on_train_batch_end(None, None, 0)
    assert len(logger_a.rows) == 2 and model._write_logs_at is None  # under DDP self.log wrote it


# ------------------------------------------------------------------------------ setup
def test_setup_truth_and_results_dir():
    model = make(parameters={KEY: {"truth": 0.2}, GREEN: {}})
    attach(model, datamodule=None, log_dir="/tmp/logs/v0")
    model.setup("fit")
    assert list(model._truth) == [KEY, GREEN] and str(model.results_dir) == "/tmp/logs/v0"
    attach(model, datamodule=SimpleNamespace(), log_dir=None, default_root_dir="/tmp/root")
    model.setup("fit")
    assert list(model._truth) == [KEY, GREEN] and str(model.results_dir) == "/tmp/root"
    attach(model, datamodule=SimpleNamespace(synthetic=False, saturation=1.0))
    model.setup("fit")
    assert list(model._truth) == [KEY]
    torch.testing.assert_close(model._truth[KEY], torch.full((3,), 0.2))
    attach(model, datamodule=SimpleNamespace(synthetic=True))
    model.setup("fit")
    assert list(model._truth) == [KEY, GREEN]
    trainer = attach(model, datamodule=SimpleNamespace(synthetic=False))
    del trainer.datamodule  # a trainer without one (e.g. Fabric's shim): synthetic, all truths
    model.setup("fit")
    assert list(model._truth) == [KEY, GREEN]


def test_setup_refuses_clipped_targets_in_pixel_mode():
    model = make(sampler={"type": "uniform", "budget": 4})
    attach(model, datamodule=SimpleNamespace(synthetic=False, saturation=0.75))
    with pytest.raises(ValueError) as error:
        model.setup("fit")
    assert str(error.value) == (
        "pixel sampling compares unclipped pixels, but the targets clip at 0.75 (8/16-bit files): use EXR targets, "
        "or set data.saturation: null"
    )
    attach(model, datamodule=SimpleNamespace(synthetic=False, saturation=None))
    model.setup("fit")
    attach(model, datamodule=None)
    model.setup("fit")
    full = make()
    attach(full, datamodule=SimpleNamespace(synthetic=False, saturation=0.75))
    full.setup("fit")


def test_setup_shares_the_pixel_sampler_with_the_other_processes():
    model = make(sampler={"type": "uniform", "budget": 5})
    attach(model, datamodule=None, world_size=2, global_rank=1)
    model.setup("fit")
    assert (model.sampler.rank, model.sampler.world, model.sampler.share) == (1, 2, 2)


# ------------------------------------------------------------------------- optimisers
def test_optimizer_groups_and_rates():
    model = make(parameters={KEY: {"lr": 0.2}, GREEN: {}}, lr=0.01)
    optimizer = model.configure_optimizers()
    assert type(optimizer) is torch.optim.Adam and optimizer.defaults["lr"] == 0.01
    groups = optimizer.param_groups
    assert [g["name"] for g in groups] == [KEY, GREEN] and [g["lr"] for g in groups] == [0.2, 0.01]
    assert [g["params"][0] is p.latent for g, p in zip(groups, model.scene_parameters)] == [True, True]
    assert all(len(g["params"]) == 1 for g in groups)
    sgd = make(optimizer="sgd", lr=0.3).configure_optimizers()
    assert type(sgd) is torch.optim.SGD and sgd.defaults["lr"] == 0.3 and sgd.param_groups[0]["lr"] == 0.3


def test_lr_half_life_halves_every_rate_per_half_life_of_steps():
    model = make(parameters={KEY: {"lr": 0.2}, GREEN: {}}, lr=0.01, lr_half_life=4, optimizer="sgd")
    config = model.configure_optimizers()
    assert set(config) == {"optimizer", "lr_scheduler"}
    optimizer, scheduler = config["optimizer"], config["lr_scheduler"]
    assert type(optimizer) is torch.optim.SGD and scheduler["interval"] == "step" and set(scheduler) == {"scheduler", "interval"}
    for _ in range(4):
        optimizer.step()
        scheduler["scheduler"].step()
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([0.1, 0.005], rel=1e-12)
    for _ in range(4):
        optimizer.step()
        scheduler["scheduler"].step()
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([0.05, 0.0025], rel=1e-12)


def test_callbacks_and_the_progress_bar_swap():
    from lightning.pytorch.callbacks import TQDMProgressBar

    from torchir.training.callbacks import NonFiniteLossGuard, ParameterProjection, ResultWriter, StepProgressBar, StepTimer

    model = make()
    base = [ParameterProjection, StepTimer, NonFiniteLossGuard, ResultWriter]
    assert [type(c) for c in model.configure_callbacks()] == base
    bar, other = TQDMProgressBar(), object()
    trainer = attach(model, progress_bar_callback=bar, callbacks=[other, bar])
    assert [type(c) for c in model.configure_callbacks()] == base + [StepProgressBar]
    assert trainer.callbacks == [other]
    own = StepProgressBar()
    trainer = attach(model, progress_bar_callback=own, callbacks=[own])
    assert [type(c) for c in model.configure_callbacks()] == base and trainer.callbacks == [own]
    attach(model, progress_bar_callback=None, callbacks=[])
    assert [type(c) for c in model.configure_callbacks()] == base


# -------------------------------------------------------------------------- checkpoints
def test_checkpoint_conversion_round_trips_numpy_state(tmp_path):
    array = np.arange(6, dtype=np.float32)[::-1]  # negative strides: torch.from_numpy refuses them as they are
    state = {"a": array, "b": np.float32(2.5), "c": [np.int64(4), (np.zeros(2, dtype=np.int32), "s")], "d": None,
             "e": {"__ndarray__": 1, "other": 2}}
    saved = _to_checkpoint(state)
    assert set(saved["a"]) == {"__ndarray__"} and torch.equal(saved["a"]["__ndarray__"], torch.tensor([5.0, 4, 3, 2, 1, 0], device="cpu"))
    assert type(saved["b"]) is float and saved["b"] == 2.5
    assert type(saved["c"]) is list and saved["c"][0] == 4 and type(saved["c"][0]) is int
    assert type(saved["c"][1]) is tuple and saved["c"][1][1] == "s" and saved["c"][1][0]["__ndarray__"].dtype == torch.int32
    assert saved["d"] is None and saved["e"] == {"__ndarray__": 1, "other": 2}
    array.base[0] = 99.0  # the checkpoint holds a copy
    assert float(saved["a"]["__ndarray__"][-1]) == 0.0
    torch.save(saved, tmp_path / "s.pt")
    loaded = _from_checkpoint(torch.load(tmp_path / "s.pt", weights_only=True))
    assert isinstance(loaded["a"], np.ndarray) and loaded["a"].tolist() == [5.0, 4, 3, 2, 1, 0]
    assert type(loaded["c"]) is list and type(loaded["c"][1]) is tuple and isinstance(loaded["c"][1][0], np.ndarray)
    assert loaded["c"][1][0].dtype == np.int32 and loaded["b"] == 2.5 and loaded["e"] == {"__ndarray__": 1, "other": 2}
    contiguous = np.arange(3.0)
    saved = _to_checkpoint(contiguous)
    contiguous[0] = 7.0
    assert float(saved["__ndarray__"][0]) == 0.0


def test_sampler_state_is_saved_and_loaded_with_the_checkpoint(fake_sampler):
    model = make(sampler={"type": "fake"})
    checkpoint = {}
    model.on_save_checkpoint(checkpoint)
    assert set(checkpoint) == {"torchir_sampler"} and torch.equal(checkpoint["torchir_sampler"]["x"]["__ndarray__"], torch.arange(3.0, device="cpu"))
    model.on_load_checkpoint(checkpoint)
    (loaded,) = model.sampler.loaded
    assert isinstance(loaded["x"], np.ndarray) and loaded["x"].tolist() == [0.0, 1.0, 2.0]
    model.on_load_checkpoint({})
    assert len(model.sampler.loaded) == 1
    plain = make()
    checkpoint = {}
    plain.on_save_checkpoint(checkpoint)
    plain.on_load_checkpoint({"torchir_sampler": {"x": 1}})
    assert checkpoint == {}
    stateless = make(sampler={"type": "fake"})
    stateless.sampler = SimpleNamespace()  # no state_dict
    stateless.on_save_checkpoint(checkpoint)
    assert checkpoint == {}


def test_pixel_sampler_state_survives_a_weights_only_checkpoint(tmp_path):
    model = make(sampler={"type": "uniform", "budget": 4, "seed": 3})
    model.sampler.sample([0])
    checkpoint = {}
    model.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, tmp_path / "c.pt")
    other = make(sampler={"type": "uniform", "budget": 4, "seed": 3})
    other.on_load_checkpoint(torch.load(tmp_path / "c.pt", weights_only=True))
    assert torch.equal(other.sampler.sample([0]).index, model.sampler.sample([0]).index)


def test_math_of_parameter_error():
    model = make(parameters={KEY: {"init": 0.3}, GREEN: {"init": 0.5}})
    error = model.parameter_error({KEY: torch.full((3,), 0.5), GREEN: torch.full((3,), 0.5)})
    assert error == pytest.approx(math.sqrt(3 * 0.04 / 6))
    assert model.parameter_error({}) is None
    truth = {KEY: torch.full((3,), 0.5)}
    assert model.parameter_error(truth, model.scene_values()) == model.parameter_error(truth)
    assert model.parameter_error(truth, {KEY: torch.full((3,), 0.5), GREEN: torch.zeros(3)}) == 0.0  # the values given


# ------------------------------------- decorated methods (mutmut leaves them unmutated)
def test_preview_renders_detached_values_with_the_preview_budget(fake_render):
    model = make(preview_spp=5)
    image = model.preview(0)
    assert fake_render.calls == [{"spp": 5, "seed": 2**32 - 7, "sensor": 0}]
    assert not image.requires_grad
    torch.testing.assert_close(image, torch.full((3, RES, RES), 0.3))
    model.preview(0, values={KEY: torch.full((3,), 0.1, requires_grad=True)}, seed=4)
    assert fake_render.calls[-1]["seed"] == 4


def test_guide_buffers_render_detached_values_with_the_step_seed(monkeypatch):
    import torchir.functions as functions

    calls = []

    def fake(scene, values, sensor=0, seed=0):
        calls.append((sorted(values), [v.requires_grad for v in values.values()], sensor, seed))
        return torch.zeros(7, RES, RES)

    monkeypatch.setattr(functions, "render_gbuffers", fake)
    model = make(seed=2)
    guide = model.guide_buffers([0, 0], step=3)
    assert guide.shape == (2, 7, RES, RES)
    assert calls == [([KEY], [False], 0, model.step_seed(3, 0))] * 2


def test_project_parameters_clamps_to_the_bounds():
    model = make(parameters={KEY: {"init": 0.3, "bounds": [0.2, 0.4]}, GREEN: {"init": 0.5}})
    with torch.no_grad():
        model.scene_parameters[0].latent.copy_(torch.tensor([0.0, 0.3, 0.9]))
        model.scene_parameters[1].latent.fill_(7.0)
    model.project_parameters()
    torch.testing.assert_close(model.scene_values()[KEY].detach(), torch.tensor([0.2, 0.3, 0.4]))
    torch.testing.assert_close(model.scene_values()[GREEN].detach(), torch.full((3,), 7.0))


# ------------------------------------------------------------------------ spp schedules
def test_an_spp_schedule_renders_each_step_at_its_stage(fake_render):
    """``spp: {2: 0, 5: 3}``: steps 0-2 render 2 spp, step 3 on 5; ``spp_grad`` follows unless set."""
    model = make(spp={2: 0, 5: 3}, loss="l1")
    model._truth = {}
    targets = torch.full((1, 3, RES, RES), 0.5)
    for step, spp in ((0, 2), (2, 2), (3, 5), (40, 5)):
        fake_render.calls.clear()
        _step(model, [0], targets, step=step)
        assert [(c["spp"], c["spp_grad"]) for c in fake_render.calls] == [(spp, spp)]
        assert model.step_metrics["paths_per_step"] == RES * RES * 2 * spp
        assert (model.spp, model.spp_grad) == (spp, spp)  # the current step's (trainer.global_step)
    fixed = make(spp={2: 0, 5: 3}, spp_grad=1)
    assert [(fixed.spp_at(s), fixed.spp_grad_at(s)) for s in (0, 3)] == [(2, 1), (5, 1)]


def test_an_spp_schedule_reaches_the_pixel_sampled_loss(fake_sampled_loss):
    model = make(sampler={"type": "uniform", "budget": 6}, spp={3: 0, 7: 10})
    _, _, early = model.sampled_loss([0], torch.zeros(1, 3, RES, RES), step=9)
    _, _, late = model.sampled_loss([0], torch.zeros(1, 3, RES, RES), step=10)
    assert [(c["spp"], c["spp_grad"]) for c in fake_sampled_loss] == [(3, 3), (7, 7)]
    assert (early, late) == (6 * (3 + 3), 6 * (7 + 7))


@pytest.mark.parametrize(("spp", "message"), [
    ({8: 5}, "model.spp: the first stage must start at step 0, got {8: 5} (the mapping is {spp: first step}, e.g. {8: 0, 64: 100})"),
    ({0: 8}, "model.spp (a key of {0: 8}: the mapping is {spp: first step}) must be >= 1, got 0"),
    ({8: 0, 64: 0}, "model.spp: list the stages in the order they are used, with strictly increasing first steps, got {8: 0, 64: 0}"),
    ({8: 0, 64: -1}, "model.spp: the first step of 64 spp must be an int >= 0, got -1 (the mapping is {spp: first step}, e.g. {8: 0, 64: 100})"),
    ({}, "model.spp must be a count >= 1 or a mapping {spp: first step}, e.g. {8: 0, 64: 100}; got {}"),
])
def test_bad_spp_schedules_are_refused_with_their_message(spp, message):
    with pytest.raises(ValueError) as error:
        make(spp=spp)
    assert str(error.value) == message
