#!/usr/bin/env python
"""Mitsuba's volume tutorial two ways: ``torchir fit`` from a YAML file alone, and plain Mitsuba.

Mitsuba's ``inverse_rendering/volume_optimization.ipynb`` recovers a heterogeneous medium's
density (``volume.vol``, ``scale: 40``, inside a ``cube`` with a ``null`` BSDF, ``prbvolpath``, a
``constant`` environment) from 5 cameras on a half circle: a 16³ grid filled with 0.002, an L2
loss, Adam (lr 0.02) one step per view with the values clipped to [1e-6, 1]; after 20 iterations
the grid is upsampled to 64³ and 20 more run at 8x the spp. Both arms here run that protocol on the
same cameras and targets:

- **mitsuba**: the notebook's loop (``mi.ad.Adam``; ``dr.resample(..., filter="linear")`` at the
  resize, which resets Adam's state for the resized key);
- **torchir**: ``torchir fit --config tutorial.yaml`` (written into ``--out``: a Mitsuba XML scene
  whose grid file is the 16³ start, ``model.sensors: {type: orbit}``, ``resolution: {16: 0, 64: P}``,
  ``spp: {8: 0, 64: P}``, ``bounds: [1e-6, 1]``, ``loss: l2``); the resize resamples Adam's moments
  too (docs/volumes.md). Run twice: to the resize, and to the end.

Reported: the grid's L1 error (mean absolute difference per voxel, in the grid's units) against the
true density sampled at the fit's voxel centres (the truth is rotated in the tutorial's scene:
Mitsuba's own ``gridvolume.eval`` samples it), just before the resize and at the end; their
torchir/Mitsuba ratios; the median seconds per step of each arm in each phase (the arms run one
after the other); and the same step interleaved in one loop at the fine grid (``--step-iterations``),
with the kernels compiled after warm-up.

Usage (the tutorial's assets are kept out of this repository)::

    git clone https://github.com/mitsuba-renderer/mitsuba-tutorials
    torchir bench volume_tutorial --tutorials mitsuba-tutorials/scenes [--quick]

Without ``--tutorials`` the truth is the procedural ring and ball of
``configs/examples/volume_from_views.py`` at 32³. Writes ``results.json``, ``summary.md`` and
``grid_l1.png``.
"""
from __future__ import annotations

import argparse
import csv
import importlib.util
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchir.bench import environment
from torchir.bench._common import fmt, markdown_table
from torchir.bench.shape_tutorial import ROOT, add_seed_options, fill_sizes, fit_in_process, read_target, tutorial_parser

VIEWS, DISTANCE, FOV, LR, SCALE, START = 5, 4.0, 45.0, 0.02, 40.0, 0.002  # the notebook's rig, optimiser, medium
BOUNDS = (1e-6, 1.0)
KEY = "object.interior_medium.sigma_t.data"
GOAL = 1.10  # torchir/Mitsuba grid L1 ratio the issue asks for


@dataclass(frozen=True)
class Assets:
    """The true density grid file, its ``to_world`` (``mi.ScalarTransform4f``), and a label."""

    truth: Path
    truth_to_world: Any
    label: str


def fit_to_world() -> Any:
    """The fitted grid's frame, as the notebook's: the unit cube onto the cube [-1, 1]³."""
    import mitsuba as mi

    return mi.ScalarTransform4f().translate(-1.0).scale(2.0)


def tutorial_assets(folder: Path) -> Assets:
    """The notebook's ``volume.vol`` under a mitsuba-tutorials ``scenes`` folder, as it places it."""
    import mitsuba as mi

    path = folder / "volume.vol"
    if not path.exists():
        raise FileNotFoundError(f"--tutorials {folder}: missing {path} (give mitsuba-tutorials/scenes)")
    to_world = mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(2).translate(-0.5)
    return Assets(path, to_world, "Mitsuba's volume tutorial (volume.vol)")


def stand_in_assets(out: Path, size: int = 32) -> Assets:
    """The repository example's procedural density (a ring and a ball) at ``size``³, as a grid file."""
    import mitsuba as mi

    source = ROOT / "configs" / "examples" / "volume_from_views.py"
    spec = importlib.util.spec_from_file_location("volume_from_views", source)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    path = out / "truth.vol"
    mi.VolumeGrid(example.truth_grid(size)).write(str(path))
    return Assets(path, fit_to_world(), f"stand-in (configs/examples/volume_from_views.py's density at {size}³)")


def sensor_dicts(resolution: int) -> list[dict[str, Any]]:
    from torchir import rigs

    return rigs.orbit(VIEWS, distance=DISTANCE, elevation=0.0, fov=FOV, resolution=resolution, start=-90.0, arc=180.0,
                      filter="tent", sample_border=False)


def scene_dict(volume: dict[str, Any]) -> dict[str, Any]:
    """The notebook's scene around a ``gridvolume`` dict ``volume`` (the density)."""
    return {"type": "scene", "integrator": {"type": "prbvolpath"},
            "object": {"type": "cube", "bsdf": {"type": "null"},
                       "interior": {"type": "heterogeneous", "sigma_t": volume, "scale": SCALE}},
            "emitter": {"type": "constant"}}


def start_volume(size: int) -> dict[str, Any]:
    """The notebook's start: a ``size``³ grid of 0.002 in the fit's frame."""
    import mitsuba as mi

    return {"type": "gridvolume", "grid": mi.VolumeGrid(np.full((size,) * 3 + (1,), START, np.float32)),
            "to_world": fit_to_world()}


def write_targets(assets: Assets, resolution: int, spp: int, out: Path) -> list[Path]:
    """Render the true density from every camera with Mitsuba; one EXR per view."""
    import mitsuba as mi

    scene = mi.load_dict(scene_dict({"type": "gridvolume", "filename": str(assets.truth), "to_world": assets.truth_to_world}))
    paths = []
    for i, sensor in enumerate(sensor_dicts(resolution)):
        image = mi.render(scene, sensor=mi.load_dict(sensor), spp=spp, seed=10_000 + i)
        paths.append(out / f"target_{i}.exr")
        mi.Bitmap(image).write(str(paths[-1]))
    return paths


def truth_on_grid(assets: Assets, size: int) -> np.ndarray:
    """The true density at the voxel centres of a ``size``³ grid in the fit's frame, ``(Z, Y, X, 1)``
    (Mitsuba's ``gridvolume.eval``: trilinear, in the truth's own frame)."""
    import drjit as dr
    import mitsuba as mi

    volume = mi.load_dict({"type": "gridvolume", "filename": str(assets.truth), "to_world": assets.truth_to_world})
    c = (np.arange(size) + 0.5) / size * 2 - 1  # voxel centres in world space ([-1, 1]³)
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    it = dr.zeros(mi.Interaction3f, size**3)
    it.p = mi.Point3f(*(mi.Float(a.ravel().astype(np.float32)) for a in (x, y, z)))
    return np.array(volume.eval_1(it), np.float32).reshape(size, size, size, 1)


class GridError:
    """The L1 error of a fitted grid ``(Z, Y, X, 1)`` against the truth at its resolution."""

    def __init__(self, assets: Assets) -> None:
        self.assets, self.cache = assets, {}

    def __call__(self, grid: np.ndarray) -> float:
        size = int(grid.shape[0])
        if size not in self.cache:
            self.cache[size] = truth_on_grid(self.assets, size)
        return float(np.mean(np.abs(np.asarray(grid, np.float32).reshape(self.cache[size].shape) - self.cache[size])))


def write_scene_xml(start_file: Path, path: Path) -> None:
    """The start scene as a user writes it: XML, the start grid as a file, no sensor (the rig's)."""
    path.write_text(f"""<scene version="3.0.0">
    <integrator type="prbvolpath"/>
    <shape type="cube" id="object">
        <bsdf type="null"/>
        <medium type="heterogeneous" name="interior">
            <volume type="gridvolume" name="sigma_t">
                <string name="filename" value="{start_file}"/>
                <transform name="to_world"><scale value="2"/><translate value="-1"/></transform>
            </volume>
            <float name="scale" value="{SCALE}"/>
        </medium>
    </shape>
    <emitter type="constant"/>
</scene>
""")


def write_config(targets: list[Path], args: argparse.Namespace, out: Path, seed: int, steps: int, name: str) -> Path:
    import mitsuba as mi
    import yaml

    start = out / "start.vol"
    mi.VolumeGrid(np.full((args.coarse,) * 3 + (1,), START, np.float32)).write(str(start))
    write_scene_xml(start, out / "scene.xml")
    resize = args.phase1 * VIEWS
    config = {
        "seed_everything": seed,
        "model": {
            "scene": str(out / "scene.xml"),
            "sensors": {"type": "orbit", "count": VIEWS, "distance": DISTANCE, "elevation": 0.0, "fov": FOV,
                        "start": -90.0, "arc": 180.0, "filter": "tent", "sample_border": False, "resolution": args.resolution},
            "parameters": {KEY: {"init": "scene", "bounds": list(BOUNDS), "lr": LR,
                                 "resolution": {args.coarse: 0, args.fine: resize}}},
            "loss": "l2", "optimizer": "adam", "spp": {args.spp: 0, args.spp * args.spp_factor: resize}, "seed": seed,
        },
        "data": {"views_per_step": 1, "views": list(range(VIEWS)), "targets": [str(t) for t in targets]},
        "trainer": {"max_steps": steps,
                    "logger": [{"class_path": "lightning.pytorch.loggers.CSVLogger",
                                "init_args": {"save_dir": str(out / "runs"), "name": name}}]},
        "images": {"every_n_steps": 0},
    }
    path = out / f"{name}.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def torchir_arm(config: Path, out: Path, name: str) -> dict[str, Any]:
    """``torchir fit --config config`` in this process; its final grid and step times."""
    run, wall = fit_in_process(config, out, name)
    grid = np.load(run / "parameters" / f"{KEY}.npy")
    seconds = {}
    with open(run / "metrics.csv") as f:
        for row in csv.DictReader(f):
            if row.get("seconds_per_step"):
                seconds[int(row["step"])] = float(row["seconds_per_step"])
    return {"grid": grid, "seconds_per_step": [seconds[s] for s in sorted(seconds)], "wall_s": wall, "run": str(run)}


def mitsuba_arm(targets: list[Path], args: argparse.Namespace, seed: int, error: GridError) -> dict[str, Any]:
    """The notebook's loop at this run's sizes; the grid's L1 error after every iteration."""
    import drjit as dr
    import mitsuba as mi

    scene = mi.load_dict(scene_dict(start_volume(args.coarse)))
    params = mi.traverse(scene)
    sensors = [mi.load_dict(s) for s in sensor_dicts(args.resolution)]
    refs = [read_target(t) for t in targets]
    opt = mi.ad.Adam(lr=LR)
    opt[KEY] = params[KEY]
    params.update(opt)
    l1, seconds = {0: error(np.array(params[KEY]))}, []
    for it in range(args.phase1 + args.phase2):
        if it == args.phase1:  # the notebook's resize
            l1_before = l1[it * VIEWS]
            opt[KEY] = dr.resample(opt[KEY], shape=(args.fine,) * 3 + (1,), filter="linear")
            params.update(opt)
        spp = args.spp if it < args.phase1 else args.spp * args.spp_factor
        for view in range(VIEWS):
            dr.sync_thread()
            start = time.perf_counter()
            image = mi.render(scene, params, sensor=sensors[view], spp=spp, seed=seed * 100_003 + it)
            dr.backward(dr.mean(dr.square(image - refs[view])))
            opt.step()
            opt[KEY] = dr.clip(opt[KEY], *BOUNDS)
            params.update(opt)
            dr.eval(params[KEY])
            dr.sync_thread()
            seconds.append(time.perf_counter() - start)
        l1[(it + 1) * VIEWS] = error(np.array(params[KEY]))
    return {"l1": l1, "l1_before": l1_before, "l1_end": l1[(args.phase1 + args.phase2) * VIEWS], "seconds_per_step": seconds}


class MitsubaStep:
    """The notebook's fine-grid step, for the interleaved timing."""

    def __init__(self, args: argparse.Namespace, refs: list, sensors: list) -> None:
        import mitsuba as mi

        self.scene = mi.load_dict(scene_dict(start_volume(args.fine)))
        self.params = mi.traverse(self.scene)
        self.opt = mi.ad.Adam(lr=LR)
        self.opt[KEY] = self.params[KEY]
        self.params.update(self.opt)
        self.refs, self.sensors, self.spp = refs, sensors, args.spp * args.spp_factor

    def step(self, step: int, view: int) -> None:
        import drjit as dr
        import mitsuba as mi

        image = mi.render(self.scene, self.params, sensor=self.sensors[view], spp=self.spp, seed=step)
        dr.backward(dr.mean(dr.square(image - self.refs[view])))
        self.opt.step()
        self.opt[KEY] = dr.clip(self.opt[KEY], *BOUNDS)
        self.params.update(self.opt)
        dr.eval(self.params[KEY])
        dr.sync_thread()


class TorchirStep:
    """The same step through ``torchir.functions.render`` and ``torch.optim.Adam``."""

    def __init__(self, args: argparse.Namespace, refs: list, sensor_specs: list) -> None:
        import torch

        import torchir

        self.scene = torchir.Scene.from_dict(scene_dict(start_volume(args.fine)), sensors=sensor_specs)
        self.grid = self.scene.get(KEY).detach().clone().requires_grad_()
        self.opt = torch.optim.Adam([self.grid], lr=LR)
        self.refs = [torch.from_numpy(np.array(r)).permute(2, 0, 1).contiguous() for r in refs]
        self.spp = args.spp * args.spp_factor

    def step(self, step: int, view: int) -> None:
        import torch

        from torchir.functions import render

        self.opt.zero_grad()
        image = render(self.scene, {KEY: self.grid}, spp=self.spp, seed=step, sensor=view)
        (image - self.refs[view]).square().mean().backward()
        self.opt.step()
        with torch.no_grad():
            self.grid.clamp_(*BOUNDS)


def compare(runs: list[dict[str, Any]], args: argparse.Namespace) -> list[dict[str, Any]]:
    """Per seed: the grid's L1 error before the resize and at the end, both arms, and ratios."""
    split = args.phase1 * VIEWS
    rows = []
    for run in runs:
        m, t = run["mitsuba"], run["torchir"]
        row = {"seed": run["seed"], "mitsuba_before": m["l1_before"], "torchir_before": t["l1_before"],
               "mitsuba_end": m["l1_end"], "torchir_end": t["l1_end"]}
        for phase in ("before", "end"):
            row[f"ratio_{phase}"] = row[f"torchir_{phase}"] / row[f"mitsuba_{phase}"]
        for name, arm in (("mitsuba", m), ("torchir", t)):
            s = arm["seconds_per_step"]
            row[f"{name}_s_coarse"] = float(np.median(s[VIEWS:split]))
            row[f"{name}_s_fine"] = float(np.median(s[split + VIEWS:]))
        for phase in ("coarse", "fine"):
            row[f"time_ratio_{phase}"] = row[f"torchir_s_{phase}"] / row[f"mitsuba_s_{phase}"]
        rows.append(row)
    return rows


def summary(results: dict[str, Any]) -> str:
    s, rows, steps = results["settings"], results["rows"], results["steps"]
    lines = [f"## Volume tutorial: torchir fit from YAML vs plain Mitsuba ({s['assets']})", "",
             f"{s['resolution']}², {VIEWS} views, one step per view; {s['phase1']} iterations at {s['coarse']}³ and "
             f"{s['spp']} spp, the resize, {s['phase2']} at {s['fine']}³ and {s['spp'] * s['spp_factor']} spp. Grid L1 "
             f"(mean |fit - truth| per voxel); the start grid's {fmt(s['start_l1'])}. Goal: torchir/Mitsuba <= {GOAL}x.", ""]
    lines += markdown_table(
        ["seed", "Mitsuba before resize", "torchir before", "ratio", "Mitsuba end", "torchir end", "ratio",
         "s/step coarse M / t", "s/step fine M / t"],
        [[r["seed"], fmt(r["mitsuba_before"]), fmt(r["torchir_before"]), fmt(r["ratio_before"]), fmt(r["mitsuba_end"]),
          fmt(r["torchir_end"]), fmt(r["ratio_end"]), f"{fmt(r['mitsuba_s_coarse'])} / {fmt(r['torchir_s_coarse'])}",
          f"{fmt(r['mitsuba_s_fine'])} / {fmt(r['torchir_s_fine'])}"] for r in rows])
    base = steps["mitsuba"]["step_s"]
    lines += ["", f"The fine-grid step ({s['fine']}³, {s['spp'] * s['spp_factor']} spp) interleaved, "
              f"{s['step_iterations']} iterations (the first {2 * VIEWS} steps left out):", ""]
    lines += markdown_table(["arm", "step (ms)", "vs mitsuba", "kernels after warm-up"],
                            [[name, fmt(1e3 * steps[name]["step_s"]), fmt(steps[name]["step_s"] / base),
                              steps[name]["kernels_after_warmup"]] for name in steps])
    lines += ["", "Before the resize: after the coarse phase (torchir: a run that stops there). Step times in the first "
              "table are medians of runs made one after the other; the second table's are interleaved."]
    return "\n".join(lines)


def plot(runs: list[dict[str, Any]], args: argparse.Namespace, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    split, end = args.phase1 * VIEWS, (args.phase1 + args.phase2) * VIEWS
    for run in runs:
        l1 = run["mitsuba"]["l1"]
        line = ax.plot(sorted(l1), [l1[k] for k in sorted(l1)], label=f"mitsuba (seed {run['seed']})")[0]
        ax.plot([split, end], [run["torchir"]["l1_before"], run["torchir"]["l1_end"]], "o--", color=line.get_color(),
                label=f"torchir (seed {run['seed']})")
    ax.axvline(split, color="grey", lw=0.5)
    ax.set_xlabel("step")
    ax.set_ylabel("grid L1 error")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = tutorial_parser(__doc__, "volume_tutorial", "32², 8³ -> 16³, 3 + 2 iterations")
    p.add_argument("--resolution", type=int, default=None, help="image side (default 64, the notebook's; --quick 32)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel before the resize (default 8; --quick 4)")
    p.add_argument("--spp-factor", type=int, default=8, help="the spp's factor after the resize (the notebook's 8)")
    p.add_argument("--coarse", type=int, default=None, help="the start grid's side (default 16)")
    p.add_argument("--fine", type=int, default=None, help="the grid's side after the resize (default 64)")
    p.add_argument("--phase1", type=int, default=None, help="iterations before the resize (default 20; --quick 3)")
    p.add_argument("--phase2", type=int, default=None, help="iterations after it (default 20; --quick 2)")
    p.add_argument("--target-spp", type=int, default=None, help="default 512 (the notebook's); --quick 64")
    p.add_argument("--step-iterations", type=int, default=None, help="interleaved fine-grid iterations (default 4; --quick 3)")
    add_seed_options(p)
    args = fill_sizes(p.parse_args(argv),
                      {"resolution": 32, "spp": 4, "coarse": 8, "fine": 16, "phase1": 3, "phase2": 2, "target_spp": 64,
                       "step_iterations": 3},
                      {"resolution": 64, "spp": 8, "coarse": 16, "fine": 64, "phase1": 20, "phase2": 20, "target_spp": 512,
                       "step_iterations": 4})
    if args.phase1 < 2 or args.phase2 < 2 or args.step_iterations < 3:
        p.error("--phase1 and --phase2 must be >= 2 (the first iteration of each is left out of the step times), "
                "--step-iterations >= 3 (two are warm-up)")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    import mitsuba as mi

    import torchir
    from torchir.bench.mesh_step import time_steps

    torchir.backend.variant()  # selects "auto" (the tutorial's dicts need a variant)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    assets = tutorial_assets(args.tutorials) if args.tutorials else stand_in_assets(out)
    targets = write_targets(assets, args.resolution, args.target_spp, out)
    error = GridError(assets)
    runs = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        print(f"seed {seed}: plain Mitsuba ...", flush=True)
        mitsuba = mitsuba_arm(targets, args, seed, error)
        print(f"seed {seed}: torchir fit (to the resize, then to the end) ...", flush=True)
        split, end = args.phase1 * VIEWS, (args.phase1 + args.phase2) * VIEWS
        before = torchir_arm(write_config(targets, args, out, seed, split, f"torchir-s{seed}-resize"), out, f"torchir-s{seed}-resize")
        whole = torchir_arm(write_config(targets, args, out, seed, end, f"torchir-s{seed}"), out, f"torchir-s{seed}")
        torchir_run = {"l1_before": error(before["grid"]), "l1_end": error(whole["grid"]),
                       "seconds_per_step": whole["seconds_per_step"], "wall_s": whole["wall_s"], "run": whole["run"]}
        runs.append({"seed": seed, "mitsuba": mitsuba, "torchir": torchir_run})
    print("interleaved fine-grid steps ...", flush=True)
    refs = [read_target(t) for t in targets]
    specs = sensor_dicts(args.resolution)
    arms = {"mitsuba": MitsubaStep(args, refs, [mi.load_dict(s) for s in specs]), "torchir": TorchirStep(args, refs, specs)}
    steps = time_steps(arms, args.step_iterations, views=VIEWS)
    for record in steps.values():
        record.pop("steps")
    results = {"settings": {"assets": assets.label, "resolution": args.resolution, "spp": args.spp,
                            "spp_factor": args.spp_factor, "coarse": args.coarse, "fine": args.fine, "phase1": args.phase1,
                            "phase2": args.phase2, "target_spp": args.target_spp, "step_iterations": args.step_iterations,
                            "start_l1": error(np.full((args.coarse,) * 3 + (1,), START, np.float32))},
               "rows": compare(runs, args),
               "runs": [{**r, "mitsuba": {**r["mitsuba"], "l1": {str(k): v for k, v in r["mitsuba"]["l1"].items()}}}
                        for r in runs],
               "steps": steps, "environment": environment()}
    from torchir.bench import save_results

    text = summary(results)
    print(text)
    save_results(out, results, text)
    plot(runs, args, out / "grid_l1.png")
    return results


if __name__ == "__main__":
    main()
