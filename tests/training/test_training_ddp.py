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
    the pmf Stage 1 assembles from the two processes' views is the single process's. (In CI, in one
    process: test_stage1_over_two_processes_gives_every_process_the_single_process_pmf below.)"""
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
    chains depend only on (seed, step, view), so 2 processes give one process's trajectory. (In CI:
    test_per_sensor_chains_give_a_view_the_same_gradients_whatever_else_a_process_renders below.)"""
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
    slow, so not in CI; the store's own tests run in one process: its chains' unbiasedness, whatever
    views feed it, in tests/samplers/test_restir.py::test_multiview_carry_over_chains_unbiased.)"""
    ddp = ("--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.accelerator", "cpu")
    store = _restir_views_run(tmp_path / "store", "carry_over", *ddp)
    for value in store.values():
        assert bool(torch.isfinite(value).all()) and not torch.allclose(value, torch.full_like(value, 0.5))


@pytest.mark.slow
def test_ddp_restir_auto_processes_agree_on_the_choice(tmp_path):
    """``{type: restir}`` under DDP: every process probes its own views, and runs with process 0's
    choice (the printed lines, which carry the probe's own figures, are the same). (In CI, in one
    process: test_processes_run_with_process_zero_s_auto_choice below.)"""
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


# --------------------------------------------- what the slow runs above check, in one process (CI)
# The slow runs spawn 2 processes; what their answers depend on is checked here without spawning:
# Stage 1's maps summed over processes (a simulated gloo group: threads, a barrier per collective),
# process 0's auto choice broadcast, and per-sensor chains whose gradients do not depend on the
# other views a process renders. The trainer's side (budget shares, the seeds of a view, the
# summed path count, DDP's averaging) is pinned in tests/samplers/test_samplers.py,
# tests/training/test_training_module.py and test_ddp_two_processes_match_one_process above.
class _SimulatedGroup:
    """``torch.distributed``'s collectives for ``world`` processes played by threads: each
    ``all_reduce`` waits for every rank's tensor (a barrier), then each rank takes the reduction
    of all of them, as gloo does. A rank that skipped a collective leaves the others waiting:
    the barrier's timeout fails the test where DDP would hang."""

    def __init__(self, world: int) -> None:
        import threading

        self.world, self.calls = world, {}
        self._local, self._slots, self._barrier = threading.local(), {}, threading.Barrier(world, timeout=20)

    @property
    def rank(self) -> int:
        """The rank the calling thread plays."""
        return self._local.rank

    def run(self, work) -> list:
        """``work(rank)`` in one thread per rank; its results in rank order (a rank's error re-raised)."""
        import threading

        results, errors = [None] * self.world, []

        def play(rank: int) -> None:
            self._local.rank, self._local.count = rank, 0
            try:
                results[rank] = work(rank)
            except BaseException as error:  # noqa: BLE001 (re-raised in the test's thread)
                errors.append(error)
                self._barrier.abort()

        threads = [threading.Thread(target=play, args=(r,)) for r in range(self.world)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        return results

    def all_reduce(self, tensor: torch.Tensor, op=None, group=None, async_op=False) -> None:  # op None: SUM, gloo's default
        import torch.distributed as dist

        rank, k = self._local.rank, self._local.count
        self._local.count += 1
        self.calls[rank] = self._local.count
        self._slots[rank, k] = tensor.clone()
        self._barrier.wait()
        total = sum(self._slots[r, k] for r in range(self.world))
        if op is None or op == dist.ReduceOp.SUM:
            reduced = total
        elif op == dist.ReduceOp.AVG:
            reduced = total / self.world
        else:
            raise NotImplementedError(f"simulated all_reduce: {op}")
        self._barrier.wait()  # every rank has read the slots before any overwrites its tensor
        tensor.copy_(reduced)


def _fake_probe(calls: list):
    """A stand-in for ``probe_pixels`` whose maps depend on the view, the level, the seed and the
    tangents (so a process that drew another view's seed or tangents gets other maps)."""

    def probe(scene, params, grids, passes=4, seed=0, sensor=0, tangents=None, step=1e-2):
        calls.append((sensor, seed))
        lean = 0.0 if tangents is None else float(sum(t.sum() for t in tangents.values()))
        radiance, derivative = [], []
        for d, (h, w) in enumerate(grids):
            g = torch.Generator(device="cpu").manual_seed((seed * 7 + 1000 * sensor + d) % 2**63)
            radiance.append(torch.rand(passes, 3, h, w, generator=g, device="cpu"))
            derivative.append(torch.randn(passes, 3, h, w, generator=g, device="cpu") + lean)
        return radiance, (derivative if tangents is not None else None)

    return probe


class _FakeScene:
    def __init__(self, resolution: tuple[int, int], views: int) -> None:
        self.resolution, self.sensor_count = resolution, views

    def sensor_resolution(self, view: int) -> tuple[int, int]:
        return self.resolution


def test_stage1_over_two_processes_gives_every_process_the_single_process_pmf(monkeypatch):
    """What test_ddp_pixel_sampling_shares_budget_and_stage1 checks, in one process: Stage 1
    with 3 views over 2 processes (rank 0 probes views 0 and 2, rank 1 view 1; their maps summed
    by all_reduce) leaves both processes with exactly the pmf one process computes, refresh after
    refresh, with each view probed once, with the seed (and tangents) one process would draw for
    it; the Stage-1 paths of the processes add up to one process's. (Each level's map is
    normalised, so maps averaged over the processes instead of summed would give the same pmf.)"""
    import torch.distributed as dist

    import torchir.functions.probe as probe_module
    from torchir.samplers import AdaptivePixelSampler

    options = dict(budget=8, levels=1, min_side=8, stage1_spp=2, alpha=0.2, seed=3, refresh_every=1)
    params = {"tex": torch.rand(4, 4, 3, device="cpu")}
    targets = torch.rand(3, 3, 16, 16, generator=torch.Generator(device="cpu").manual_seed(1), device="cpu")

    single_calls: list = []
    monkeypatch.setattr(probe_module, "probe_pixels", _fake_probe(single_calls))
    single = AdaptivePixelSampler(_FakeScene((16, 16), 3), **options)
    reference = []
    for step in range(2):
        single.update(params, targets, None, step=step)
        reference.append((single.pdf.clone(), single.diagnostics()["stage1_paths"]))
    assert not torch.allclose(reference[0][0], reference[1][0])  # a refresh draws new seeds: another pmf

    group = _SimulatedGroup(2)
    for name, value in (("is_available", lambda: True), ("is_initialized", lambda: True),
                        ("get_backend", lambda group=None: "gloo"), ("all_reduce", group.all_reduce)):
        monkeypatch.setattr(dist, name, value)
    calls: dict[int, list] = {0: [], 1: []}
    probes = {r: _fake_probe(calls[r]) for r in (0, 1)}
    monkeypatch.setattr(probe_module, "probe_pixels", lambda *a, **k: probes[group.rank](*a, **k))

    def process(rank: int) -> list:
        s = AdaptivePixelSampler(_FakeScene((16, 16), 3), **options)
        s.distribute(rank, 2)
        out = []
        for step in range(2):
            s.update(params, targets, None, step=step)
            out.append((s.pdf.clone(), s.diagnostics()["stage1_paths"]))
        return out

    ranks = group.run(process)
    assert [v for v, _ in calls[0]] == [0, 2, 0, 2] and [v for v, _ in calls[1]] == [1, 1]
    assert sorted(calls[0] + calls[1]) == sorted(single_calls)  # each view's seed as one process draws it
    for step, (pmf, paths) in enumerate(reference):
        for rank in (0, 1):
            torch.testing.assert_close(ranks[rank][step][0], pmf, rtol=0, atol=0)
        assert ranks[0][step][1] + ranks[1][step][1] == paths
    assert group.calls[0] == group.calls[1] == 2 * 2 * 2  # per refresh: p1 and p2, two levels each


def test_processes_run_with_process_zero_s_auto_choice(monkeypatch):
    """What test_ddp_restir_auto_processes_agree_on_the_choice checks, in one process: a process
    whose own probe would choose plain RIS runs with process 0's choice (persistent chains),
    received through ``broadcast_object_list`` from rank 0, and prints process 0's line."""
    import contextlib
    import dataclasses
    import io

    import torch.distributed as dist

    import torchir
    from torchir.samplers import ReSTIRSampler
    from torchir.samplers import restir as restir_module
    from torchir.samplers._restir_auto import AutoChoice, SceneProbe, choose

    base = SceneProbe(light_variance=3e4, camera_variance=1.0, camera_resolved=True, step_seconds=0.02,
                      candidate_seconds=4e-4, missed_share=0.0, geometry=False, spp=1, seconds=0.1)
    probes = {0: base, 1: dataclasses.replace(base, light_variance=1e-3, seconds=0.2)}  # rank 1's views: no light noise
    assert choose(probes[0]).strategy == "persistent" and choose(probes[1]).strategy == "plain"
    sent: dict[str, object] = {}

    def broadcast_object_list(box, src=0, group=None, device=None):
        assert src == 0
        if rank == 0:
            sent["choice"] = box[0]
        else:
            box[0] = sent["choice"]

    for name, value in (("is_available", lambda: True), ("is_initialized", lambda: True),
                        ("get_world_size", lambda group=None: 2), ("get_rank", lambda group=None: rank),
                        ("broadcast_object_list", broadcast_object_list)):
        monkeypatch.setattr(dist, name, value)
    scene = torchir.Scene.builtin("ajar_painting", resolution=8)
    key = "painting.bsdf.reflectance.data"
    lines, options = {}, {}
    for rank in (0, 1):  # process 0 first: it sends what the other receives (get_rank reads `rank`)
        monkeypatch.setattr(restir_module, "probe_scene", lambda *args, _rank=rank: probes[_rank])
        out = io.StringIO()
        r = ReSTIRSampler(scene, planned_steps=300)
        with contextlib.redirect_stdout(out):
            r.prepare({key: scene.get(key)}, frozenset({key}), 0, 1, 0)
        lines[rank], options[rank] = out.getvalue(), r.options
        assert r.choice == AutoChoice.from_dict(sent["choice"])
    assert lines[0] == lines[1] == f"[torchir] {choose(probes[0], 300).describe()}\n"
    assert options[0] == options[1] == choose(probes[0], 300).options and options[1].lane_chains


def test_per_sensor_chains_give_a_view_the_same_gradients_whatever_else_a_process_renders():
    """What test_ddp_restir_keeps_each_process_s_reservoirs checks, in one process: under DDP a
    process renders only its own views; with per-sensor chains view 1's images and texture
    gradients (the decorrelated gradient chain included) are, bit for bit, those of one process
    rendering views 0 and 1 in turn with the same seeds, while the texture changes each step."""
    import torchir
    from torchir.functions import render
    from torchir.samplers import ReSTIRSampler

    scene = torchir.Scene.builtin("oxalis_lite", resolution=8, views=2, texture=4, dim_lights=1, hidden_lights=1)
    key = "canvas.bsdf.reflectance.data"
    weights = torch.rand(3, 8, 8)
    options = dict(candidates=4, burn_in=2, multiview="per_sensor", grad_paths="decorrelated")

    def run(views: list[int]) -> dict[int, list[tuple[torch.Tensor, torch.Tensor]]]:
        sampler = ReSTIRSampler(scene, **options)
        out: dict[int, list] = {v: [] for v in views}
        for step in range(3):
            for view in views:
                texture = torch.full_like(scene.get(key), 0.5 + 0.05 * step).requires_grad_()
                image = render(scene, {key: texture}, spp=2, seed=2 * step + view, sensor=view, sampler=sampler)
                (image * weights).sum().backward()
                out[view].append((image.detach(), texture.grad))
        return out

    both, alone = run([0, 1]), run([1])
    for (image, grad), (image_alone, grad_alone) in zip(both[1], alone[1]):
        assert torch.equal(image, image_alone) and torch.equal(grad, grad_alone)
        assert bool(grad.abs().sum() > 0)
    assert not torch.equal(both[0][2][1], both[1][2][1])  # the views' gradients do differ
