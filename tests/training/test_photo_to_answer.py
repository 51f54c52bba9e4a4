"""A Mitsuba user's own scene, from photos to an answer: the example room scene (XML, OBJ/PLY
meshes, an 8-bit PNG texture) fitted from YAML; derived poses; results a person can read;
the command line around it."""
from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import torchir
from torchir import cli
from torchir.training import InverseRenderingModule

from tests.helpers import file_target_step

# New APIs are imported inside the tests that use them, so that each test fails on its own
# (not at collection) on code without them.

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "configs" / "examples"
ROOM = EXAMPLES / "room" / "scene.xml"
QUICKSTART = str(ROOT / "configs" / "quickstart.yaml")
QUIET = ["--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]


def _run(tmp_path: Path, config: str, *overrides: str) -> int:
    return cli.main(["fit", "--config", config, *QUIET, "--trainer.logger.init_args.save_dir", str(tmp_path), *overrides])


def _metrics(run: Path) -> list[dict[str, str]]:
    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


def _result(run: Path) -> dict:
    return yaml.safe_load((run / "result.yaml").read_text())


# ------------------------------------------------------------------------------ photos
def test_png_and_exr_targets_give_the_same_answer(tmp_path):
    """The red-wall tutorial from YAML: fitting the 8-bit PNG gives the EXR's answer (the same
    render seeds, so only the target's quantisation differs), and both near the truth."""
    answers = {}
    for suffix in ("png", "exr"):
        target = str(EXAMPLES / "room" / "targets" / f"red.{suffix}")
        out = tmp_path / suffix
        assert _run(out, str(EXAMPLES / "red_wall.yaml"), "--trainer.max_steps", "60", "--data.targets", f"[{target}]") == 0
        answers[suffix] = torch.tensor(_result(out / "red_wall" / "version_0")["parameters"]["red.bsdf.reflectance.value"])
    truth, init = torch.tensor([0.7, 0.3, 0.1]), torch.full((3,), 0.5)
    # before the fix the PNG was decoded twice and the fit went to (0.40, 0.02, 0.26)
    assert (answers["png"] - answers["exr"]).abs().max() < 0.02
    for answer in answers.values():
        assert (answer - truth).norm() < 0.25 * (init - truth).norm()


@pytest.mark.parametrize("suffix", ["png", "jpg"])
def test_saturated_photo_pixels_do_not_pull_a_light(tmp_path, suffix):
    """The lamp is in view and clips in the 8-bit photo: left out of the loss, the radiance
    still converges to the truth (clipping noisy renders instead drove it to ~20; a per-channel
    mask let the JPEG's lamp pixel (254, 255, 255) pull red to 8)."""
    target = str(EXAMPLES / "room" / "targets" / f"light.{suffix}")
    assert _run(tmp_path, str(EXAMPLES / "light.yaml"), "--trainer.max_steps", "60", "--data.targets", f"[{target}]") == 0
    radiance = torch.tensor(_result(tmp_path / "light" / "version_0")["parameters"]["light.emitter.radiance.value"])
    assert (radiance - 12.0).abs().max() < 1.0, radiance


def _fitted_radiance(module: InverseRenderingModule, target: Path, seeds: range) -> torch.Tensor:
    """The trainer's answer for the lamp's radiance (``transform: none``) from a target file, per
    render seed: a render is linear in the radiance and the clipped mask does not move, so the
    loss is a parabola in each channel and two gradients give its minimum exactly."""
    batch, step = file_target_step(module, target)
    assert batch["lossy"].tolist() == [target.suffix == ".jpg"]
    truth = module.scene.get("light.emitter.radiance.value")
    latent = module.scene_parameters[0].latent
    answers = []
    for seed in seeds:
        grads = []
        for value in (truth, 2 * truth):
            latent.data.copy_(value)
            latent.grad = None
            step(seed).backward()
            grads.append(latent.grad.clone())
        answers.append(truth - grads[0] * truth / (grads[1] - grads[0]))
    return torch.stack(answers)


def test_jpeg_photo_of_a_lamp_gives_the_pngs_answer(tmp_path):
    """Issue 39: a JPEG's lamp edge decodes just below the top code (true radiance ~18, target
    ~0.95) and the old mask kept those pixels: the lamp's fitted radiance came out 30-90% low
    from JPEGs at quality 75-95. Through the trainer (ViewDataModule reads the file, the
    training step masks it), a JPEG now gives the PNG's answer: per channel within 10% (what
    JPEG's chroma subsampling moves between channels at 64x64), the total within 2%."""
    import mitsuba as mi

    from torchir.imageio import write_image

    module = InverseRenderingModule(scene="cbox", resolution=64, spp=8, loss="l2",
                                    parameters={"light.emitter.radiance.value": {"init": 1.0, "transform": "none"}})
    radiance = torchir.functions.render(module.scene, {}, spp=64, seed=2)  # the lamp clips: ~34 pixels
    write_image(tmp_path / "photo.png", radiance)
    x = radiance.clamp(0, 1).permute(1, 2, 0).double().cpu().numpy()
    encoded = np.rint(255 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)).astype(np.uint8)
    bitmap = mi.Bitmap(np.ascontiguousarray(encoded), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    answers = {}
    for name, quality in (("png", None), ("q75", 75), ("q90", 90), ("q95", 95)):
        path = tmp_path / ("photo.png" if quality is None else f"{name}.jpg")
        if quality is not None:
            bitmap.write(str(path), quality=quality)
        answers[name] = _fitted_radiance(module, path, range(2)).mean(0)
    for name in ("q75", "q90", "q95"):
        relative = (answers[name] - answers["png"]) / answers["png"]
        total = float((answers[name].sum() - answers["png"].sum()) / answers["png"].sum())
        assert float(relative.abs().max()) < 0.10 and abs(total) < 0.02, (name, answers[name], answers["png"])


def test_grey_and_wrong_size_targets_name_the_fix(tmp_path, capsys):
    import mitsuba as mi

    mi.Bitmap(np.full((48, 48, 1), 77, np.uint8), mi.Bitmap.PixelFormat.Y).write(str(tmp_path / "grey.png"))
    mi.Bitmap(np.full((8, 8, 3), 77, np.uint8), mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "small.png"))
    assert _run(tmp_path, str(EXAMPLES / "red_wall.yaml"), "--data.targets", f"[{tmp_path / 'grey.png'}]") == 1
    assert "greyscale (1 channel)" in capsys.readouterr().err
    assert _run(tmp_path, str(EXAMPLES / "red_wall.yaml"), "--data.targets", f"[{tmp_path / 'small.png'}]") == 1
    err = capsys.readouterr().err
    assert "8x8 (W x H)" in err and "film's width/height in the scene file" in err and "model.resolution" not in err


# ------------------------------------------------------------------------------ derived poses
def test_rotation_matrix_gradcheck_and_orthonormal():
    from torchir.derived import rotation_matrix

    angles = torch.tensor([10.0, -25.0, 40.0], dtype=torch.float64, requires_grad=True)
    axis = torch.tensor([0.3, 1.0, -0.2], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: rotation_matrix(a), (angles,))
    assert torch.autograd.gradcheck(lambda a: rotation_matrix(a, axis), (angles[:1].detach().clone().requires_grad_(),))
    r = rotation_matrix(angles.detach())
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert float(torch.linalg.det(r)) == pytest.approx(1.0, abs=1e-12)


def test_rigid_transform_of_vertices_matches_mitsubas_transform():
    import mitsuba as mi

    from torchir.derived import rigid_transform

    scene = torchir.Scene.from_file(ROOM)
    names = rigid_transform(scene, "blob", rotation_axis=[0, 1, 0], pivot=[0.1, -0.5, 0.2])
    assert names == ["blob.translation", "blob.rotation", "blob.scale"]
    v0 = scene.get("blob.vertex_positions").reshape(-1, 3).double().cpu().numpy()
    t, angle = [0.08, 0.0, -0.05], 15.0
    expected_t = (mi.ScalarTransform4f().translate(t).translate([0.1, -0.5, 0.2]).rotate([0, 1, 0], angle)
                  .translate([-0.1, 0.5, -0.2]))
    expected = np.array([expected_t @ mi.ScalarPoint3f(*p) for p in v0])
    values = scene.expand_derived({"blob.translation": torch.tensor(t), "blob.rotation": torch.tensor([angle])})
    got = values["blob.vertex_positions"].reshape(-1, 3).cpu().numpy()
    assert np.abs(got - expected).max() < 1e-5
    # the load-time pose is the identity: a render that gives none of them is the scene as loaded
    identity = scene.expand_derived({"blob.rotation": torch.zeros(1)})["blob.vertex_positions"]
    assert torch.allclose(identity, scene.get("blob.vertex_positions"), atol=1e-6)


def test_rigid_transform_of_to_world_binds_a_transform_with_gradients():
    scene = torchir.Scene.from_dict(_plane_scene_dict())  # the plane fills the view: no edge moves
    assert scene.info("plane.to_world").shape == (4, 4) and scene.info("plane.to_world").bindable
    from torchir.derived import rigid_transform

    rigid_transform(scene, "plane", rotation_axis=[1, 0, 0])
    from torchir.testing import check_gradients

    def loss(params, seed):
        return torchir.functions.render(scene, params, spp=4, seed=seed).mean()

    report = check_gradients(loss, {"plane.rotation": torch.tensor([10.0], requires_grad=True)}, seeds=range(6), directions=1, eps=2.0)
    assert report.passed, str(report)
    assert abs(report.checks[0].finite_difference) > 5 * report.checks[0].tolerance  # a real derivative


def _plane_scene_dict() -> dict:
    import mitsuba as mi

    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 30, "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(4.0), "bsdf": {"type": "diffuse"}},
        "sun": {"type": "directional", "direction": [0.3, -0.2, -1.0], "irradiance": {"type": "rgb", "value": 3.0}},
    }


def test_derive_validates_its_inputs():
    scene = torchir.Scene.builtin("cbox", resolution=8)
    with pytest.raises(ValueError, match="already a parameter"):
        scene.derive("red.reflectance.value", lambda g: g.expand(3), {"green.reflectance.value": [0.5]})
    with pytest.raises(ValueError, match="gives 2 values"):
        scene.derive("red.reflectance.value", lambda g: g.expand(2), {"red.grey": [0.5]})
    with pytest.raises(KeyError, match="unknown scene parameter"):
        scene.derive("red.reflectance.valu", lambda g: g, {"red.grey": [0.5]})
    scene.derive("red.reflectance.value", lambda g: g.expand(3), {"red.grey": [0.5]})
    with pytest.raises(ValueError, match="already set by"):
        scene.derive("red.reflectance.value", lambda g: g.expand(3), {"red.grey2": [0.5]})


def test_derived_from_yaml_forms(tmp_path):
    (tmp_path / "grey.py").write_text("import torch\n\ndef grey(g):\n    return g.expand(3)\n")
    module = InverseRenderingModule(
        scene="cbox", resolution=8,
        derived={"wall": {"type": "function", "target": "red.reflectance.value", "function": f"{tmp_path / 'grey.py'}:grey",
                          "inputs": {"red.grey": [0.4]}}},
        parameters={"red.grey": {"init": 0.3, "bounds": [0.0, 1.0]}},
    )
    assert module.scene_values()["red.grey"].shape == (1,)
    image = module.render_views([0], step=0)
    image.mean().backward()
    assert float(module.scene_parameters[0].latent.grad.abs()) > 0
    with pytest.raises(ValueError, match=r"model.derived\['x'\].type must be one of"):
        InverseRenderingModule(scene="cbox", resolution=8, derived={"x": {"type": "spline"}}, parameters={"red.reflectance.value": {}})
    with pytest.raises(ValueError, match=r"model.derived\['blob'\] \(rigid\)"):
        InverseRenderingModule(scene=str(ROOM), derived={"blob": {"type": "rigid", "shape": "blob", "axis": [0, 1, 0]}},
                               parameters={"blob.rotation": {}})


def test_unbindable_parameters_are_refused_with_their_name():
    with pytest.raises(TypeError, match="'blob.faces'.*integers"):
        InverseRenderingModule(scene=str(ROOM), parameters={"blob.faces": {"init": "scene"}})


def test_init_outside_bounds_is_refused():
    with pytest.raises(ValueError, match=r"init has 3 value\(s\) outside bounds \[0.0, 1.0\]"):
        InverseRenderingModule(scene="cbox", resolution=8, parameters={"red.reflectance.value": {"init": 1.5, "bounds": [0, 1]}})
    with pytest.raises(ValueError, match="outside bounds"):
        InverseRenderingModule(scene="cbox", resolution=8, parameters={"red.reflectance.value": {"init": -0.1, "bounds": [0, 1], "transform": "sigmoid"}})


# ------------------------------------------------------------------------------ results
def test_results_in_own_units_last_checkpoint_export_and_resume(tmp_path, capsys):
    overrides = ["--model.resolution", "16", "--model.spp", "2", "--model.preview_spp", "4", "--trainer.max_steps", "7",
                 "--checkpoint.every_n_train_steps", "5", "--set", "red.reflectance.value.transform=log",
                 "--set", "red.reflectance.value.bounds=null"]
    assert _run(tmp_path, QUICKSTART, *overrides) == 0
    run = tmp_path / "quickstart" / "version_0"
    last = run / "checkpoints" / "last.ckpt"
    checkpoint = torch.load(last, map_location="cpu", weights_only=False)
    assert checkpoint["global_step"] == 7  # the last step, not step 5 of every_n_train_steps
    latent = checkpoint["state_dict"]["scene_parameters.0.latent"]
    result = _result(run)
    assert result["step"] == 7
    # the value in its own units: exp(latent) under transform log, not the latent
    assert result["parameters"]["red.reflectance.value"] == pytest.approx(latent.exp().tolist(), rel=1e-5)
    assert (run / "images" / "final_v0.png").is_file() and (run / "curves.png").is_file()
    # export from any folder writes the same values
    out = tmp_path / "exported"
    assert cli.main(["export", str(last), "--out", str(out), "--spp", "4"]) == 0
    assert _result(out)["parameters"] == result["parameters"] and (out / "images" / "final_v0.exr").is_file()
    # --ckpt_path last resumes the newest run from step 7
    assert _run(tmp_path, QUICKSTART, *overrides, "--trainer.max_steps", "9", "--ckpt_path", "last") == 0
    assert "resuming from" in capsys.readouterr().out
    # a new folder with the whole run's history: the first run's steps 0-6, then its own 7 and 8
    assert [int(r["step"]) for r in _metrics(tmp_path / "quickstart" / "version_1") if r.get("loss")] == list(range(9))


def test_ckpt_path_last_without_a_run_says_so(tmp_path, capsys):
    assert _run(tmp_path, QUICKSTART, "--model.resolution", "8", "--ckpt_path", "last") == 1
    assert "no run of" in capsys.readouterr().err


def test_interrupt_keeps_the_state(tmp_path):
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import ModelCheckpoint

    from torchir.training import ViewDataModule

    class Interrupt(pl.Callback):
        def on_train_batch_end(self, trainer, *args) -> None:
            if trainer.global_step == 3:
                raise KeyboardInterrupt

    module = InverseRenderingModule(scene="cbox", resolution=8, spp=1, preview_spp=2, parameters={"red.reflectance.value": {}})
    trainer = pl.Trainer(max_steps=10, default_root_dir=tmp_path, enable_progress_bar=False, enable_model_summary=False,
                         callbacks=[Interrupt(), ModelCheckpoint(dirpath=tmp_path / "checkpoints", every_n_train_steps=50, save_last=True)],
                         logger=False)
    with pytest.raises(SystemExit):  # Lightning's graceful shutdown ends in exit(1)
        trainer.fit(module, ViewDataModule(target_spp=4))
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["global_step"] == 3
    assert _result(tmp_path)["step"] == 3


# ------------------------------------------------------------------------------ command line
def test_set_and_parameter_maps_merge(tmp_path):
    from torchir.training.cli import split_parameter_sets

    rest, sets = split_parameter_sets(["fit", "--set", "a.b.value.init=0.3", "--model.parameters={x.y: {lr: 0.1}, z: {}}", "--k", "v"])
    assert rest == ["fit", "--k", "v"] and sets == [("a.b.value", "init", 0.3), ("x.y", "lr", 0.1), ("z", None, None)]
    with pytest.raises(ValueError, match="KEY.FIELD=VALUE"):
        split_parameter_sets(["--set", "a.b.value.inti=0.3"])
    assert _run(tmp_path, QUICKSTART, "--model.resolution", "8", "--trainer.max_steps", "1", "--model.preview_spp", "2",
                "--set", "green.reflectance.value.init=0.25", "--model.parameters", "{red.reflectance.value: {lr: 0.01}}") == 0
    config = yaml.safe_load((tmp_path / "quickstart" / "version_0" / "config.yaml").read_text())
    parameters = config["model"]["parameters"]
    assert parameters["green.reflectance.value"]["init"] == 0.25 and parameters["green.reflectance.value"]["bounds"] == [0.0, 1.0]
    assert parameters["red.reflectance.value"]["lr"] == 0.01 and parameters["red.reflectance.value"]["init"] == 0.5


def test_relative_paths_resolve_against_the_config_file(tmp_path, monkeypatch):
    shutil.copytree(EXAMPLES / "room", tmp_path / "cfg" / "room")
    shutil.copy(EXAMPLES / "red_wall.yaml", tmp_path / "cfg" / "red_wall.yaml")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert _run(tmp_path / "out", str(tmp_path / "cfg" / "red_wall.yaml"), "--trainer.max_steps", "1", "--model.preview_spp", "2") == 0
    # the checkpoint holds absolute paths: it loads from any working directory
    other = tmp_path / "other"
    other.mkdir()
    monkeypatch.chdir(other)
    last = tmp_path / "out" / "red_wall" / "version_0" / "checkpoints" / "last.ckpt"
    assert cli.main(["export", str(last), "--out", str(other / "x"), "--no-images"]) == 0
    assert "red.bsdf.reflectance.value" in _result(other / "x")["parameters"]


def test_curves_start_at_step_zero_and_l2_logs_no_repeated_image_error(tmp_path):
    assert _run(tmp_path, QUICKSTART, "--model.resolution", "8", "--trainer.max_steps", "3", "--model.preview_spp", "2") == 0
    run = tmp_path / "quickstart" / "version_0"
    rows = [r for r in _metrics(run) if r.get("loss")]
    assert [int(r["step"]) for r in rows] == [0, 1, 2]
    assert "image_error" not in rows[0] or not rows[0]["image_error"]
    history = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["callbacks"]
    curves = next(v for k, v in history.items() if "CurvePlotter" in k)
    assert [int(r["step"]) for r in curves["history"]] == [0, 1, 2]
    assert _run(tmp_path, QUICKSTART, "--model.resolution", "8", "--trainer.max_steps", "2", "--model.preview_spp", "2", "--model.loss", "l1") == 0
    assert _metrics(tmp_path / "quickstart" / "version_1")[0]["image_error"]


def test_progress_bar_counts_steps(tmp_path, capsys):
    assert cli.main(["fit", "--config", QUICKSTART, "--model.resolution", "8", "--trainer.max_steps", "3", "--model.preview_spp", "2",
                     "--trainer.enable_model_summary", "false", "--trainer.logger.init_args.save_dir", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "step" in text and "3/3" in text and "s/step" in text and "Epoch" not in text


def test_info_aligns_scene_descriptions(capsys):
    assert cli.main(["info"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  ")]
    starts = {len(line) - len(line[2:].split(None, 1)[1]) for line in lines}
    assert len(lines) == len(torchir.scenes.available()) and len(starts) == 1


def test_integrator_override_from_python_and_yaml(tmp_path):
    scene = torchir.Scene.from_file(ROOM, override_integrator={"type": "prb_projective", "guiding": "none", "max_depth": 2})
    assert type(scene.integrator).__name__ == "PathProjectiveIntegrator" and scene.integrator.max_depth == 2
    assert "direct" in str(torchir.Scene.builtin("cbox", resolution=8, override_integrator={"type": "direct"}).integrator).lower()
    module = InverseRenderingModule(scene=str(ROOM), integrator={"type": "prb", "max_depth": 2}, parameters={"red.bsdf.reflectance.value": {}})
    assert module.scene.integrator.max_depth == 2
    with pytest.raises(ValueError, match="integrator override is"):
        torchir.Scene.from_file(ROOM, override_integrator={"max_depth": 2})
    (tmp_path / "none.xml").write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.raises(ValueError, match="has no <integrator> to override"):
        torchir.Scene.from_file(tmp_path / "none.xml", override_integrator={"type": "prb"})
