"""Remeshing on a schedule in a YAML run (``model.remesh``): the topology changes at the
scheduled steps and the fit goes on (new Large Steps latent, its optimiser state afresh, the
other parameter's state and the lr schedule kept), metrics.csv records the vertex count, the
written PLY and the checkpoint hold the new topology, a resume after a remesh ends where the
uninterrupted run ends, under DDP every process takes process 0's mesh, and the config errors.
(That a remesh keeps the surface is tests/geometry/test_remesh.py's.)"""
from __future__ import annotations

import csv
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from torchir import cli
from torchir.geometry import LargeSteps, read_mesh
from torchir.training import InverseRenderingModule, remeshing

from tests.helpers import ROOT, _latents, _run_dir

EXAMPLES = ROOT / "configs" / "examples"
CONFIG = str(EXAMPLES / "mesh_from_sphere.yaml")
FACTORY = f"{EXAMPLES / 'mesh_from_sphere.py'}:build"
TRUTH = str(EXAMPLES / "mesh_from_sphere_target.ply")
KEY, ALBEDO = "shape.vertex_positions", "shape.bsdf.reflectance.value"
STEPS, AT, HALF_LIFE, LR = 8, (2, 6), 10, 0.2
SPHERE_VERTICES, SPHERE_FACES = 162, 320  # gpytoolbox.icosphere(2)


def _fit(save_dir: Path, *overrides: str) -> int:
    """The example config at 16², one view a step, with the albedo optimised too, a decaying lr
    and remeshes before steps 2 and 6 to 0.7x the mean edge (about 2x the vertices each)."""
    return cli.main(["fit", "--config", CONFIG, "--model.resolution", "16", "--model.preview_spp", "4",
                     "--data.target_spp", "16", "--trainer.enable_progress_bar", "false",
                     "--trainer.logger.init_args.save_dir", str(save_dir), "--model.distance_every_n_steps", "2",
                     "--checkpoint.every_n_train_steps", "4", "--trainer.max_steps", str(STEPS),
                     "--model.lr_half_life", str(HALF_LIFE), "--set", f"{ALBEDO}.init=0.5",
                     "--model.remesh", f"{{at: {list(AT)}, edge_length: 0.7}}", *overrides])


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    save_dir = tmp_path_factory.mktemp("remesh")
    assert _fit(save_dir) == 0
    return _run_dir(save_dir, "mesh_from_sphere")


def _rows(folder: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(open(folder / "metrics.csv")))


def _checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)  # what a resume reads


def test_the_topology_changes_at_the_scheduled_steps_and_the_fit_goes_on(run):
    """metrics.csv's ``vertices/<key>`` is the sphere's 162 on rows 0-1, about 2x that from row 2
    (step 2 renders the remeshed mesh) and 2x again from row 6; every loss is finite and the mesh
    keeps approaching the truth after the remeshes: the final Chamfer distance is below half the
    one step 2 renders (measured 0.059 -> 0.022, floor 0.0004; a latent the optimiser no longer
    steps after the remesh would keep 0.059). The written PLY has the last topology (the checkpoint's faces)
    and holds ``(I + λL)^{-1} u`` of the final latent on it."""
    rows = _rows(run)
    counts = {int(r["step"]): int(float(r[f"vertices/{KEY}"])) for r in rows if r.get(f"vertices/{KEY}")}
    assert sorted(counts) == list(range(STEPS))
    first, second = counts[AT[0]], counts[AT[1]]
    assert [counts[s] for s in range(STEPS)] == [SPHERE_VERTICES] * 2 + [first] * 4 + [second] * 2
    assert 1.5 * SPHERE_VERTICES < first < 3 * SPHERE_VERTICES and 1.5 * first < second < 3 * first  # (1/0.7)² ≈ 2
    losses = [float(r["loss"]) for r in rows if r.get("loss")]
    assert len(losses) == STEPS and all(math.isfinite(x) for x in losses)

    result = yaml.safe_load((run / "result.yaml").read_text())
    entry = result["parameters"][KEY]
    chamfer = {int(r["step"]): float(r[f"chamfer/{KEY}"]) for r in rows if r.get(f"chamfer/{KEY}")}
    floor = entry["chamfer_floor"]
    assert entry["chamfer"] == pytest.approx(chamfer[STEPS], rel=1e-5)
    assert entry["chamfer"] - floor < 0.5 * (chamfer[AT[0]] - floor), (chamfer, floor)

    state = _checkpoint(run / "checkpoints" / "last.ckpt")
    topology = state["torchir_topology"]
    assert topology["steps"] == list(AT)
    faces = topology["meshes"][KEY]["faces"]
    v, f = read_mesh(run / entry["mesh"], device="cpu")
    assert len(v) == second and torch.equal(f, faces)
    latent = state["state_dict"]["scene_parameters.0.latent"]
    positions = LargeSteps(topology["meshes"][KEY]["vertices"], faces, lambda_=25).from_differential(latent.reshape(-1, 3))
    torch.testing.assert_close(v, positions, rtol=0, atol=1e-5)


def test_the_optimiser_restarts_the_new_latent_and_keeps_the_rest(run):
    """In the last checkpoint (step 8, remeshed before step 6) the uniform-Adam state of the mesh
    latent has counted 2 steps (fresh at step 6) and has its new shape, the albedo's has counted
    all 8, and the lr schedule has decayed both groups over all 8 steps (a rebuilt scheduler, or
    a fresh optimiser for all, would restart them)."""
    state = _checkpoint(run / "checkpoints" / "last.ckpt")
    optimizer = state["optimizer_states"][0]
    latent = state["state_dict"]["scene_parameters.0.latent"]
    mesh_state, albedo_state = optimizer["state"][0], optimizer["state"][1]
    assert int(mesh_state["step"]) == STEPS - AT[1] and mesh_state["exp_avg"].shape == latent.shape
    assert int(albedo_state["step"]) == STEPS
    gamma = 0.5 ** (1 / HALF_LIFE)
    mesh_group, albedo_group = optimizer["param_groups"]
    assert mesh_group["lr"] == pytest.approx(LR * gamma**STEPS, rel=1e-6)
    assert albedo_group["lr"] == pytest.approx(0.05 * gamma**STEPS, rel=1e-6)
    assert state["lr_schedulers"][0]["last_epoch"] == STEPS


def test_a_resume_after_a_remesh_ends_where_the_uninterrupted_run_ends(run, tmp_path):
    """Resumed from step 4 (after the remesh at 2, before the one at 6), the run rebuilds the
    scene and the latent at the checkpoint's topology before loading their state, remeshes again
    at 6, and ends where the uninterrupted run ends: within float noise (Dr.Jit's float32 atomics
    make the two runs' gradients differ at ~1e-7, which the remesh at 6 and the latent's (I + λL),
    λ = 25, amplify: measured up to 1.5e-5 for entries up to ~8, so 1e-5 of the largest entry is
    allowed; a resume that lost the albedo's optimiser state lands 4e-3 away, one that lost the
    mesh's remeshes at 6 to another vertex count).
    Its metrics.csv holds the whole history, vertex counts included."""
    middle = run / "checkpoints" / "epoch=0-step=4.ckpt"
    assert middle.is_file(), sorted(p.name for p in (run / "checkpoints").iterdir())
    assert _checkpoint(middle)["torchir_topology"]["steps"] == [AT[0]]
    assert _fit(tmp_path, "--ckpt_path", str(middle)) == 0
    resumed_run = _run_dir(tmp_path, "mesh_from_sphere")
    full, resumed = _latents(run / "checkpoints" / "last.ckpt"), _latents(resumed_run / "checkpoints" / "last.ckpt")
    assert set(full) == set(resumed) and len(full) == 2
    for key in full:
        assert resumed[key].shape == full[key].shape
        torch.testing.assert_close(resumed[key], full[key], rtol=0, atol=1e-5 * float(full[key].abs().max()))
    column = f"vertices/{KEY}"
    assert [r.get(column) for r in _rows(resumed_run)] == [r.get(column) for r in _rows(run)]
    assert [int(r["step"]) for r in _rows(resumed_run)] == list(range(STEPS + 1))


def test_export_of_a_remeshed_checkpoint_writes_its_topology(run, tmp_path):
    """``torchir export`` of the last checkpoint builds the module at the checkpoint's topology
    (else loading the latent fails on its shape) and writes the run's mesh and distances."""
    assert cli.main(["export", str(run / "checkpoints" / "last.ckpt"), "--out", str(tmp_path), "--no-images"]) == 0
    exported = yaml.safe_load((tmp_path / "result.yaml").read_text())["parameters"][KEY]
    original = yaml.safe_load((run / "result.yaml").read_text())["parameters"][KEY]
    assert exported["chamfer"] == original["chamfer"] and exported["shape"] == original["shape"]
    v, f = read_mesh(tmp_path / exported["mesh"], device="cpu")
    v_run, f_run = read_mesh(run / original["mesh"], device="cpu")
    assert torch.equal(f, f_run) and torch.equal(v, v_run)


def _module(**overrides) -> InverseRenderingModule:
    parameters = {KEY: {"parametrization": {"type": "large_steps", "lambda": 25}, "truth": TRUTH, "lr": LR}}
    kwargs = {"scene": FACTORY, "resolution": 16, "parameters": parameters, "optimizer": "adam_uniform",
              "remesh": {"at": [1]}, "spp": 4, "preview_spp": 4, **overrides}
    return InverseRenderingModule(**kwargs)


def test_in_a_lightning_run_the_optimiser_and_sampler_hold_the_new_latent_and_scene(tmp_path):
    """In plain Lightning, after the remesh before step 1: the trainer's optimiser (the one object
    the strategy and lr scheduler hold) has the parameter's new latent in its group, whose state
    has counted one step at the end of step 1; the pixel sampler draws for the new scene."""
    import lightning.pytorch as pl

    from torchir.training import ViewDataModule

    seen = {}

    class Probe(pl.Callback):
        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
            (optimizer,) = trainer.optimizers
            latent = module.scene_parameters[0].latent
            seen[trainer.global_step] = (optimizer.param_groups[0]["params"][0] is latent, int(optimizer.state[latent]["step"]),
                                         latent.numel() // 3, module.sampler.scene is module.scene,
                                         trainer.lr_scheduler_configs[0].scheduler.optimizer is optimizer)

    # pixel sampling renders with path replay (prb): interior gradients only, enough to step the mesh
    module = _module(sampler={"type": "uniform", "budget": 0.5}, loss="l1", lr_half_life=10, integrator={"type": "prb", "max_depth": 2})
    trainer = pl.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path, callbacks=[Probe()])
    trainer.fit(module, ViewDataModule(target_spp=4, views_per_step=1))
    assert seen[1] == (True, 1, SPHERE_VERTICES, True, True)
    holds, steps, vertices, sampler_follows, scheduled = seen[2]
    assert holds and steps == 1 and vertices > 1.5 * SPHERE_VERTICES and sampler_follows and scheduled


def test_every_process_takes_process_zero_s_mesh(monkeypatch):
    """Under DDP, process 0 remeshes and broadcasts its mesh; another process, whose positions
    here differ (a remesh of them would give another mesh), takes process 0's mesh and does not
    remesh its own: both end with the same faces and positions, and each rebuilds its DDP wrapper."""
    from torchir.training import param_swap

    rewrapped = []
    monkeypatch.setattr(param_swap, "rewrap_distributed", lambda trainer: rewrapped.append(trainer.is_global_zero))
    sent = {}

    def trainer(rank: int) -> SimpleNamespace:
        def broadcast(obj, src=0):
            assert src == 0
            if rank == 0:
                sent["mesh"] = obj
            return sent["mesh"]

        return SimpleNamespace(is_global_zero=rank == 0, world_size=2, optimizers=[], strategy=SimpleNamespace(broadcast=broadcast))

    modules = [_module(), _module()]
    with torch.no_grad():
        modules[1].scene_parameters[0].latent.mul_(1.1)
    for rank, module in enumerate(modules):
        module._trainer = trainer(rank)
        if rank == 1:
            monkeypatch.setattr(remeshing, "_remesh", lambda *a: pytest.fail("process 1 remeshed its own mesh"))
        assert remeshing.apply_remesh_schedule(module, 1)
    assert rewrapped == [True, False]
    faces = [m.mesh_faces(KEY) for m in modules]
    assert len(faces[0]) > 2 * SPHERE_FACES and torch.equal(faces[0], faces[1])
    assert torch.equal(modules[0].topology.meshes[KEY][1], faces[0])
    torch.testing.assert_close(modules[1].scene_values()[KEY], modules[0].scene_values()[KEY], rtol=0, atol=1e-5)


def test_a_plain_mesh_parameter_is_rebuilt_at_the_remeshed_positions():
    """Without Large Steps the parameter is the positions themselves: after the remesh its value
    is the new mesh's vertex list (the scene's, the record's; not the config's ``init``, here
    explicit positions of the old vertex list), with the faces of the scene's new mesh, and the
    module's own Adam (``configure_optimizers``) steps the new tensor."""
    start = read_mesh(TRUTH, device="cpu")[0].mul(0.9).tolist()
    module = _module(parameters={KEY: {"init": start, "truth": TRUTH}}, optimizer="adam")
    optimizer = module.configure_optimizers()
    module._trainer = SimpleNamespace(is_global_zero=True, world_size=1, optimizers=[optimizer],
                                      strategy=SimpleNamespace(broadcast=lambda obj, src=0: obj))
    assert remeshing.apply_remesh_schedule(module, 1) and not remeshing.apply_remesh_schedule(module, 1)  # once a step
    (p,) = module.scene_parameters
    vertices, faces = module.topology.meshes[KEY]
    assert type(p).__name__ == "SceneParameter" and p.latent.numel() == vertices.numel() > 2 * 3 * SPHERE_VERTICES
    torch.testing.assert_close(p().detach().cpu(), vertices.reshape(-1), rtol=0, atol=0)
    assert torch.equal(module.mesh_faces(KEY), faces) and optimizer.param_groups[0]["params"][0] is p.latent
    assert remeshing.vertex_counts(module) == {f"vertices/{KEY}": float(len(vertices))}


def test_restir_moves_to_the_remeshed_scene_with_its_reservoirs_dropped():
    """ReSTIR's reservoirs belong to the old surface: after a remesh (the built-in pig, 1106
    vertices, to twice its mean edge) the same sampler (its options kept) draws for the new
    scene with no chain left, and a differentiable render through it reaches the new latent."""
    module = InverseRenderingModule(scene="pig", resolution=8, spp=1, remesh={"at": [0], "edge_length": 2.0},
                                    parameters={"pig.vertex_positions": {"parametrization": {"type": "large_steps"}}},
                                    sampler={"type": "restir", "preset": "b2", "candidates": 2})
    sampler = module.sampler
    module.render_views([0], 0)
    assert len(sampler.integrator.states) == 1
    module._trainer = SimpleNamespace(is_global_zero=True, world_size=1, optimizers=[],
                                      strategy=SimpleNamespace(broadcast=lambda obj, src=0: obj))
    assert remeshing.apply_remesh_schedule(module, 0)
    assert module.sampler is sampler and sampler.scene is module.scene and len(sampler.integrator.states) == 0
    (p,) = module.scene_parameters
    assert p.large_steps.vertex_count < 1106 // 2
    module.render_views([0], 1).sum().backward()
    assert p.latent.grad is not None and float(p.latent.grad.abs().sum()) > 0


@pytest.mark.parametrize("overrides, message", [
    ({"remesh": [80]}, r"model.remesh must be a mapping \{at: \[steps\], edge_length: 0.5, iterations: 5, project: true\}"),
    ({"remesh": {"at": [4], "edges": 0.5}}, r"model.remesh has unknown key\(s\) \['edges'\]; allowed: \['at', 'edge_length', 'iterations', 'project'\]"),
    ({"remesh": {"edge_length": 0.5}}, r"model.remesh.at is required"),
    ({"remesh": {"at": []}}, r"model.remesh.at must be a non-empty list of steps >= 0 .* got \[\]"),
    ({"remesh": {"at": [4, -1]}}, r"model.remesh.at must be a non-empty list of steps >= 0 .* got \[4, -1\]"),
    ({"remesh": {"at": [8, 4]}}, r"model.remesh.at must list its steps in increasing order, each once, got \[8, 4\]"),
    ({"remesh": {"at": [4, 4]}}, r"increasing order, each once, got \[4, 4\]"),
    ({"remesh": {"at": [4], "edge_length": 0}}, r"model.remesh.edge_length must be a finite number > 0 .* got 0"),
    ({"remesh": {"at": [4], "edge_length": -0.5}}, r"edge_length must be a finite number > 0 .* got -0.5"),
    ({"remesh": {"at": [4], "iterations": 0}}, r"model.remesh.iterations must be an int >= 1 .* got 0"),
    ({"remesh": {"at": [4], "project": "yes"}}, r"model.remesh.project must be true or false, got 'yes'"),
    ({"parameters": {ALBEDO: {}}}, r"model.remesh: no mesh to remesh; .* the parameters are \['shape.bsdf.reflectance.value'\]"),
    ({"parameters": {KEY: {"truth": "scene"}}}, r"parameters\['shape.vertex_positions'\].truth is a vertex list \('scene'\).* truth: file.ply"),
    ({"parameters": {KEY: {"init": "scene", "bounds": [[-2] * 3 * SPHERE_VERTICES, [2] * 3 * SPHERE_VERTICES]}}}, r"bounds are given per entry, which a remesh does not keep"),
])
def test_config_errors_are_clear(overrides, message):
    with pytest.raises(ValueError, match=message):
        _module(**overrides)


def test_a_synthetic_run_without_a_truth_mesh_is_refused_at_setup():
    """Without ``truth`` a synthetic run's parameter error is per vertex against the loaded mesh:
    refused when the run sets up (before any step), naming the remedy."""
    module = _module(parameters={KEY: {"parametrization": {"type": "large_steps"}}})
    module._trainer = SimpleNamespace(datamodule=None, max_steps=0, log_dir=None, default_root_dir=".")
    with pytest.raises(ValueError, match=r"parameters\['shape.vertex_positions'\] has no truth mesh.* truth: file.ply"):
        module.setup("fit")


@pytest.mark.slow  # two fresh processes (~40 s on 2 cores): `python3 -m pytest -m slow`
def test_ddp_two_processes_remesh_as_one_process(tmp_path):
    """A remesh under DDP (gloo, 2 processes, 2 views a step split between them) follows one
    process's trajectory: the processes take one mesh and the new latent's gradients are
    averaged over them (a DDP wrapper left on the replaced parameter would not reduce them)."""
    import os
    import subprocess
    import sys

    args = ["fit", "--config", CONFIG, "--model.resolution", "8", "--model.preview_spp", "2", "--model.spp", "2",
            "--data.target_spp", "8", "--data.views_per_step", "2", "--trainer.enable_progress_bar", "false",
            "--images.exr", "false", "--model.distance_every_n_steps", "100", "--trainer.max_steps", "4",
            "--model.remesh", "{at: [2]}"]
    assert cli.main([*args, "--trainer.logger.init_args.save_dir", str(tmp_path / "one")]) == 0
    ddp = ["--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu"]
    result = subprocess.run([sys.executable, "-m", "torchir", *args, "--trainer.logger.init_args.save_dir", str(tmp_path / "two"), *ddp],
                            capture_output=True, text=True, timeout=600, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr[-3000:]
    one = _latents(_run_dir(tmp_path / "one", "mesh_from_sphere") / "checkpoints" / "last.ckpt")
    two = _latents(_run_dir(tmp_path / "two", "mesh_from_sphere") / "checkpoints" / "last.ckpt")
    for key in one:
        assert one[key].numel() > 3 * 1.5 * SPHERE_VERTICES
        torch.testing.assert_close(two[key], one[key], rtol=1e-4, atol=1e-4)
