#!/usr/bin/env python
"""Mitsuba's shape tutorial two ways: ``torchir fit`` from a YAML file alone, and plain Mitsuba.

Mitsuba's ``inverse_rendering/shape_optimization.ipynb`` deforms an ico-sphere (``ico_10k.ply``,
seamed: 10593 vertices at 10242 positions) into Suzanne, seen by 8 Fibonacci cameras under
``envmap2.exr``, by ``direct_projective`` (``sppi: 0``), an L1 loss, Large Steps (λ = 25) and
uniform Adam (lr 0.1), one step per view; then it remeshes (Botsch-Kobbelt, half the mean edge)
and goes on. Both arms here run that protocol on the same cameras, targets and steps:

- **mitsuba**: the notebook's loop (``mi.ad.LargeSteps``, ``mi.ad.Adam(uniform=True)``,
  ``gpytoolbox.remesh_botsch`` on its mesh as loaded, a new Large Steps and Adam after it);
- **torchir**: ``torchir fit --config tutorial.yaml`` (written into ``--out``: a Mitsuba XML
  scene, ``model.sensors: {type: fibonacci}``, ``parametrization: large_steps``,
  ``optimizer: adam_uniform``, ``loss: l1``, ``remesh: {at: [P]}``, ``truth: suzanne.ply``).

Deviations from the notebook, the same in both arms: smaller images and spp (``--resolution``,
``--spp``), fewer iterations, and after the remesh one step per view with ``sppi: 0`` still (the
notebook then steps once per 8 views with indirect silhouettes; a YAML run keeps one protocol).
The targets are rendered once by Mitsuba (``--target-spp``) and written as EXR; both arms read them.

Reported: the squared symmetric Chamfer distance to Suzanne (20000 area-uniform samples a mesh,
``torchir.geometry.chamfer_distance``, as ``torchir fit`` logs it) one iteration before the remesh
and at the end, their torchir/Mitsuba ratios, and the median seconds per step of each arm (run
one after the other: the interleaved step cost is ``torchir bench mesh_step``).

Usage (the tutorial's assets are kept out of this repository)::

    git clone https://github.com/mitsuba-renderer/mitsuba-tutorials
    torchir bench shape_tutorial --tutorials mitsuba-tutorials/scenes [--quick]

Without ``--tutorials`` it runs a stand-in built here: a seamed UV sphere (as exporters write
it) deformed into this repository's ellipsoid (``configs/examples/mesh_from_sphere_target.ply``)
under a constant environment. Writes ``results.json``, ``summary.md`` and ``chamfer.png``.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchir.bench import environment
from torchir.bench._common import fmt, markdown_table

ROOT = Path(__file__).resolve().parents[2]
VIEWS, DISTANCE, FOV, LAMBDA, LR = 8, 5.0, 45.0, 25.0, 0.1  # the notebook's cameras and optimiser
GOAL = 1.10  # torchir/Mitsuba Chamfer ratio the issue asks for


@dataclass(frozen=True)
class Assets:
    """The start mesh, the target mesh and the emitter (a Mitsuba plugin dict) of a run."""

    start: Path
    target: Path
    emitter: dict[str, Any]
    label: str


def tutorial_assets(folder: Path) -> Assets:
    """The notebook's own files under a mitsuba-tutorials ``scenes`` folder."""
    files = (folder / "meshes" / "ico_10k.ply", folder / "meshes" / "suzanne.ply", folder / "textures" / "envmap2.exr")
    missing = [str(f) for f in files if not f.exists()]
    if missing:
        raise FileNotFoundError(f"--tutorials {folder}: missing {', '.join(missing)} (give mitsuba-tutorials/scenes)")
    return Assets(files[0], files[1], {"type": "envmap", "filename": str(files[2])}, "Mitsuba's shape tutorial (ico_10k -> suzanne, envmap2)")


def stand_in_assets(out: Path) -> Assets:
    """A seamed UV sphere written as PLY, to be deformed into the repository's ellipsoid."""
    from torchir.bench.exported_meshes import uv_sphere, write_ply

    start = out / "uv_sphere.ply"
    write_ply(uv_sphere(segments=64, rings=32, radius=1.0), start)
    target = ROOT / "configs" / "examples" / "mesh_from_sphere_target.ply"
    return Assets(start, target, {"type": "constant"}, "stand-in (seamed UV sphere -> ellipsoid, constant light)")


def sensor_dicts(resolution: int) -> list[dict[str, Any]]:
    from torchir import rigs

    return rigs.fibonacci(VIEWS, distance=DISTANCE, fov=FOV, resolution=resolution)


def scene_dict(mesh: Path, assets: Assets) -> dict[str, Any]:
    return {"type": "scene", "integrator": {"type": "direct_projective", "sppi": 0}, "emitter": dict(assets.emitter),
            "shape": {"type": "ply", "filename": str(mesh), "bsdf": {"type": "diffuse"}}}


def write_targets(assets: Assets, resolution: int, spp: int, out: Path) -> list[Path]:
    """Render the target mesh from every camera with Mitsuba; one EXR per view."""
    import mitsuba as mi

    scene = mi.load_dict(scene_dict(assets.target, assets))
    paths = []
    for i, sensor in enumerate(sensor_dicts(resolution)):
        image = mi.render(scene, sensor=mi.load_dict(sensor), spp=spp, seed=10_000 + i)
        paths.append(out / f"target_{i}.exr")
        mi.Bitmap(image).write(str(paths[-1]))
    return paths


def read_target(path: Path) -> Any:
    import mitsuba as mi

    return mi.TensorXf(np.array(mi.Bitmap(str(path)), np.float32))


def write_scene_xml(assets: Assets, path: Path) -> None:
    """The start scene as a user writes it: XML, PLY mesh, the emitter (no sensor: the rig's)."""
    emitter = assets.emitter
    light = (f'<emitter type="envmap"><string name="filename" value="{emitter["filename"]}"/></emitter>'
             if emitter["type"] == "envmap" else '<emitter type="constant"/>')
    path.write_text(f"""<scene version="3.0.0">
    <integrator type="direct_projective"><integer name="sppi" value="0"/></integrator>
    {light}
    <shape type="ply" id="shape">
        <string name="filename" value="{assets.start}"/>
        <bsdf type="diffuse"/>
    </shape>
</scene>
""")


def write_config(assets: Assets, targets: list[Path], args: argparse.Namespace, out: Path, seed: int) -> Path:
    import yaml

    xml = out / "scene.xml"
    write_scene_xml(assets, xml)
    config = {
        "seed_everything": seed,
        "model": {
            "scene": str(xml),
            "sensors": {"type": "fibonacci", "count": VIEWS, "distance": DISTANCE, "fov": FOV, "resolution": args.resolution},
            "parameters": {"shape.vertex_positions": {"parametrization": {"type": "large_steps", "lambda": LAMBDA},
                                                      "lr": LR, "truth": str(assets.target)}},
            "optimizer": "adam_uniform", "loss": "l1", "spp": args.spp, "seed": seed,
            "distance_every_n_steps": VIEWS, "remesh": {"at": [args.phase1 * VIEWS]},
        },
        "data": {"views_per_step": 1, "views": list(range(VIEWS)), "targets": [str(t) for t in targets]},
        "trainer": {"max_steps": (args.phase1 + args.phase2) * VIEWS,
                    "logger": [{"class_path": "lightning.pytorch.loggers.CSVLogger",
                                "init_args": {"save_dir": str(out / "runs"), "name": f"torchir-s{seed}"}}]},
        "images": {"every_n_steps": 0},
    }
    path = out / f"tutorial-s{seed}.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def fit_in_process(config: Path, out: Path, name: str) -> tuple[Path, float]:
    """``torchir fit --config config`` in this process, its output in ``out/name.log``; the run's
    folder (the newest ``out/runs/name/version_*``) and its wall time in seconds."""
    from torchir.training.cli import main

    log = out / f"{name}.log"
    start = time.perf_counter()
    with open(log, "w") as stream, contextlib.redirect_stdout(stream), contextlib.redirect_stderr(stream):
        code = main(["fit", "--config", str(config)])
    wall = time.perf_counter() - start
    if code != 0:
        raise RuntimeError(f"torchir fit failed (exit {code}); see {log}")
    return max((out / "runs" / name).glob("version_*"), key=lambda p: int(p.name.split("_")[1])), wall


def torchir_arm(config: Path, out: Path, seed: int) -> dict[str, Any]:
    """``torchir fit --config config`` in this process; its Chamfer rows and step times."""
    run, wall = fit_in_process(config, out, f"torchir-s{seed}")
    chamfer: dict[int, float] = {}
    seconds, vertices = [], None
    with open(run / "metrics.csv") as f:
        for row in csv.DictReader(f):
            if row.get("chamfer/shape.vertex_positions"):
                chamfer[int(row["step"])] = float(row["chamfer/shape.vertex_positions"])
            if row.get("seconds_per_step"):
                seconds.append(float(row["seconds_per_step"]))
            if row.get("vertices/shape.vertex_positions"):
                vertices = int(float(row["vertices/shape.vertex_positions"]))
    return {"chamfer": chamfer, "seconds_per_step": seconds, "vertices_after_remesh": vertices, "wall_s": wall, "run": str(run)}


def mitsuba_arm(assets: Assets, targets: list[Path], args: argparse.Namespace, seed: int) -> dict[str, Any]:
    """The notebook's loop, with its remesh, at this run's sizes; Chamfer every iteration."""
    import drjit as dr
    import gpytoolbox
    import mitsuba as mi
    import torch

    from torchir.geometry import chamfer_distance, read_mesh

    truth = tuple(t.cpu() for t in read_mesh(assets.target))
    scene = mi.load_dict(scene_dict(assets.start, assets))
    params = mi.traverse(scene)
    sensors = [mi.load_dict(s) for s in sensor_dicts(args.resolution)]
    refs = [read_target(t) for t in targets]

    def optimiser() -> tuple[Any, Any]:
        ls = mi.ad.LargeSteps(params["shape.vertex_positions"], params["shape.faces"], LAMBDA)
        opt = mi.ad.Adam(lr=LR, uniform=True)
        opt["u"] = ls.to_differential(params["shape.vertex_positions"])
        return ls, opt

    def distance() -> float:
        v = torch.from_numpy(np.array(params["shape.vertex_positions"], np.float32).reshape(-1, 3))
        f = torch.from_numpy(np.array(params["shape.faces"], np.int64).reshape(-1, 3))
        return chamfer_distance((v, f), truth)

    ls, opt = optimiser()
    chamfer, seconds, vertices = {}, [], None
    total = (args.phase1 + args.phase2) * VIEWS
    for step in range(total + 1):
        if step == args.phase1 * VIEWS:  # the notebook's remesh: half the mean edge, 5 iterations, projected
            v = np.array(params["shape.vertex_positions"], np.float64).reshape(-1, 3)
            f = np.array(params["shape.faces"], np.int64).reshape(-1, 3)
            edges = np.concatenate([np.linalg.norm(v[f[:, a]] - v[f[:, b]], axis=1) for a, b in ((0, 1), (1, 2), (2, 0))])
            v_new, f_new = gpytoolbox.remesh_botsch(v, f.astype(np.int32), i=5, h=float(np.mean(edges)) / 2, project=True)
            params["shape.faces"] = mi.UInt32(np.asarray(f_new, np.uint32).ravel())
            params["shape.vertex_positions"] = mi.Float(np.asarray(v_new, np.float32).ravel())
            params["shape.vertex_texcoords"] = mi.Float()
            params.update()
            vertices = len(v_new)
            ls, opt = optimiser()
        dr.sync_thread()
        start = time.perf_counter()  # the notebook's iteration: positions from u, the update, render, backward, Adam
        params["shape.vertex_positions"] = ls.from_differential(opt["u"])
        params.update()
        dr.sync_thread()
        update_seconds = time.perf_counter() - start
        if step % VIEWS == 0:
            chamfer[step] = distance()  # not timed, as torchir's seconds_per_step leaves its distances out
        if step == total:
            break
        view = step % VIEWS
        start = time.perf_counter()
        image = mi.render(scene, params, sensor=sensors[view], seed=seed * 100_003 + step, spp=args.spp)
        loss = dr.mean(dr.abs(image - refs[view]))
        dr.backward(loss)
        opt.step()
        dr.eval(opt["u"])
        dr.sync_thread()
        seconds.append(update_seconds + time.perf_counter() - start)
    return {"chamfer": chamfer, "seconds_per_step": seconds, "vertices_after_remesh": vertices}


def compare(runs: list[dict[str, Any]], args: argparse.Namespace) -> list[dict[str, Any]]:
    """Per seed: Chamfer one iteration before the remesh and at the end, both arms, and ratios."""
    before, end = (args.phase1 - 1) * VIEWS, (args.phase1 + args.phase2) * VIEWS
    rows = []
    for run in runs:
        t, m = run["torchir"], run["mitsuba"]
        t_end = t["chamfer"].get(end, t["chamfer"][max(t["chamfer"])])
        row = {"seed": run["seed"], "steps_before": before, "steps_end": end,
               "mitsuba_before": m["chamfer"][before], "torchir_before": t["chamfer"].get(before),
               "mitsuba_end": m["chamfer"][end], "torchir_end": t_end,
               "mitsuba_s_per_step": float(np.median(m["seconds_per_step"][VIEWS:])),
               "torchir_s_per_step": float(np.median(t["seconds_per_step"][VIEWS:]))}
        for phase in ("before", "end"):
            tv, mv = row[f"torchir_{phase}"], row[f"mitsuba_{phase}"]
            row[f"ratio_{phase}"] = None if tv is None else tv / mv
        row["time_ratio"] = row["torchir_s_per_step"] / row["mitsuba_s_per_step"]
        row["vertices_after_remesh"] = {"mitsuba": m.get("vertices_after_remesh"), "torchir": t.get("vertices_after_remesh")}
        rows.append(row)
    return rows


def summary(results: dict[str, Any]) -> str:
    meta, rows = results["settings"], results["rows"]
    lines = [f"## Shape tutorial: torchir fit from YAML vs plain Mitsuba ({meta['assets']})", "",
             f"{meta['resolution']}², {meta['spp']} spp, {VIEWS} views, one step per view; "
             f"{meta['phase1']} iterations, remesh, {meta['phase2']} more. Chamfer² (20000 samples a mesh); "
             f"start {fmt(meta['start_chamfer'])}, the target against itself {fmt(meta['floor'])}. "
             f"Goal: torchir/Mitsuba Chamfer <= {GOAL}x.", ""]
    lines += markdown_table(
        ["seed", "Mitsuba before remesh", "torchir before", "ratio", "Mitsuba end", "torchir end", "ratio",
         "s/step Mitsuba", "s/step torchir", "time ratio"],
        [[r["seed"], fmt(r["mitsuba_before"]), fmt(r["torchir_before"]), fmt(r["ratio_before"]), fmt(r["mitsuba_end"]),
          fmt(r["torchir_end"]), fmt(r["ratio_end"]), fmt(r["mitsuba_s_per_step"]), fmt(r["torchir_s_per_step"]),
          fmt(r["time_ratio"])] for r in rows])
    lines += ["", f"'before': after {rows[0]['steps_before']} steps (one iteration before the remesh); 'end': after "
              f"{rows[0]['steps_end']}. Step times are medians of runs made one after the other "
              "(the interleaved comparison: `torchir bench mesh_step`)."]
    counts = [f"seed {r['seed']}: Mitsuba {r['vertices_after_remesh']['mitsuba']}, torchir {r['vertices_after_remesh']['torchir']}"
              for r in rows if r.get("vertices_after_remesh")]
    if counts:
        lines += ["", "Vertices after the remesh: " + "; ".join(counts) + " (Mitsuba remeshes the mesh as loaded, "
                  "its seams open borders the remesher keeps; torchir welds it first)."]
    return "\n".join(lines)


def plot(runs: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run in runs:
        for arm, style in (("mitsuba", "-"), ("torchir", "--")):
            chamfer = run[arm]["chamfer"]
            steps = sorted(chamfer)
            values = [chamfer[s] for s in steps]
            label = f"{arm} (seed {run['seed']})"
            axes[0].plot(steps, values, style, label=label)
            step_s = float(np.median(run[arm]["seconds_per_step"]))
            axes[1].plot([s * step_s for s in steps], values, style, label=label)
    for ax, xlabel in zip(axes, ("step", "seconds (median step time x steps)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel("Chamfer² to the target")
        ax.set_yscale("log")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def tutorial_parser(doc: str, suite: str, quick: str) -> argparse.ArgumentParser:
    """The options the shape suites share: ``--tutorials``, ``--out``, ``--quick`` (``quick``: its help)."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--tutorials", type=Path, default=None, help="mitsuba-tutorials/scenes (default: a built-in stand-in)")
    p.add_argument("--out", type=Path, default=ROOT / "results" / "bench" / suite)
    p.add_argument("--quick", action="store_true", help=quick)
    return p


def add_seed_options(p: argparse.ArgumentParser) -> None:
    """``--seeds`` and ``--first-seed``: the tutorial suites' runs per arm and their first seed."""
    p.add_argument("--seeds", type=int, default=1, help="runs per arm, seeds first-seed, first-seed + 1, ...")
    p.add_argument("--first-seed", type=int, default=0)


def fill_sizes(args: argparse.Namespace, quick: dict[str, int], full: dict[str, int]) -> argparse.Namespace:
    """Each size option left unset takes its ``--quick`` or full default."""
    for key, value in (quick if args.quick else full).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def run_assets(args: argparse.Namespace, out: Path) -> Assets:
    """The tutorial's files under ``--tutorials``, else the stand-in written into ``out``."""
    return tutorial_assets(args.tutorials) if args.tutorials else stand_in_assets(out)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = tutorial_parser(__doc__, "shape_tutorial", "48², 4 spp, 6 + 3 iterations")
    p.add_argument("--resolution", type=int, default=None, help="image side (default 96; --quick 48)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default 8; --quick 4)")
    p.add_argument("--phase1", type=int, default=None, help="iterations before the remesh (default 80; --quick 6)")
    p.add_argument("--phase2", type=int, default=None, help="iterations after it (default 30; --quick 3)")
    p.add_argument("--target-spp", type=int, default=256)
    add_seed_options(p)
    args = fill_sizes(p.parse_args(argv), {"resolution": 48, "spp": 4, "phase1": 6, "phase2": 3},
                      {"resolution": 96, "spp": 8, "phase1": 80, "phase2": 30})
    if args.phase1 < 2 or args.phase2 < 1:
        p.error("--phase1 must be >= 2 and --phase2 >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    import torchir
    from torchir.bench import save_results
    from torchir.geometry import chamfer_distance, read_mesh

    torchir.backend.variant()  # selects "auto" (the tutorial's dicts need a variant)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    assets = run_assets(args, out)
    targets = write_targets(assets, args.resolution, args.target_spp, out)
    runs = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        print(f"seed {seed}: plain Mitsuba ...", flush=True)
        mitsuba = mitsuba_arm(assets, targets, args, seed)
        print(f"seed {seed}: torchir fit ...", flush=True)
        run = torchir_arm(write_config(assets, targets, args, out, seed), out, seed)
        runs.append({"seed": seed, "mitsuba": mitsuba, "torchir": run})
    start, truth = (tuple(t.cpu() for t in read_mesh(p)) for p in (assets.start, assets.target))
    results = {"settings": {"assets": assets.label, "resolution": args.resolution, "spp": args.spp, "phase1": args.phase1,
                            "phase2": args.phase2, "target_spp": args.target_spp,
                            "start_chamfer": chamfer_distance(start, truth), "floor": chamfer_distance(truth, truth, seed=1)},
               "rows": compare(runs, args),
               "runs": [{**r, **{arm: {**r[arm], "chamfer": {str(k): v for k, v in r[arm]["chamfer"].items()}}
                                 for arm in ("mitsuba", "torchir")}} for r in runs],
               "environment": environment()}
    text = summary(results)
    print(text)
    save_results(out, results, text)
    plot(runs, out / "chamfer.png")
    return results


if __name__ == "__main__":
    main()
