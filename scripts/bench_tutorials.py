#!/usr/bin/env python
"""torchir from YAML vs a plain Mitsuba 3 tutorial loop, on the four example tasks.

    python3 scripts/bench_tutorials.py [--quick] [--tasks red_wall,pose] [--out results/bench_tutorials]

Each task of ``configs/examples/`` (red wall, texture, light, pose; scene and targets made by
``scripts/make_example_scene.py``) is fitted two ways in one process, on the same machine:

(a) torchir from the YAML config alone, through ``torchir.training.cli.main`` (overrides: the
    output folder, the seed, and in ``--quick`` mode the step count or target file);
(b) a plain Mitsuba loop written as Mitsuba's tutorials write it: ``mi.load_file``,
    ``mi.traverse``, ``mi.ad.Adam``, ``mi.render(scene, params, spp, seed=step)``,
    ``dr.backward`` of an L2 loss, ``opt.step()``; with the config's spp, steps, learning
    rates, init, bounds (clamped), ``log`` transform, the same linear target (and the same
    saturated-pixel mask for 8-bit targets), the config's ``model.integrator`` written into the
    XML's ``<integrator>`` element, and, for the pose, the tutorial's ``mi.Transform4f``
    applied to the initial vertices.

Both use seed ``(s * 2654435761 + step) mod 2^32`` at step ``step`` of seed ``s`` (torchir's own
rule), so seed 0 of both sees the same random numbers. Outputs in ``--out``: ``summary.md``
(the printed tables), ``results.json``, ``curves.png`` and each torchir run's folder.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "configs" / "examples"
GOLDEN = 2654435761  # torchir's per-step seed hash (InverseRenderingModule.step_seed)
SATURATED = 0.995  # torchir's mask threshold for 8-bit targets (data.saturation: auto -> 1.0)
WARMUP = 3  # steps left out of the mean step time: kernel compilation / recording
QUICK_STEPS: dict[str, int] = {}  # per task in --quick mode; other tasks: QUICK_DEFAULT
QUICK_DEFAULT = 25
ERROR_GOAL, TIME_GOAL = 1.10, 1.10  # torchir/Mitsuba ratios the issue asks for
FORMATS = ("png", "jpg", "exr")


@dataclass(frozen=True)
class Task:
    """One example run: its config file and the stem of its target files."""

    name: str
    config: str
    target: str


TASKS = {
    "red_wall": Task("red_wall", "red_wall.yaml", "red"),
    "texture": Task("texture", "texture.yaml", "texture"),
    "light": Task("light", "light.yaml", "light"),
    "pose": Task("pose", "pose.yaml", "pose"),
}


@dataclass
class ParamSpec:
    """One optimised quantity of a config (``model.parameters`` entry), truth resolved."""

    key: str
    init: Any
    lr: float
    transform: str
    bounds: Optional[tuple[float, float]]
    truth: Optional[np.ndarray]


@dataclass
class RunResult:
    """One fit: per-step curves, final values and errors (parameter units)."""

    method: str
    task: str
    seed: int
    target: str
    steps: int
    step_seconds: list[float]
    step_error: list[float]  # parameter error before each step's update (metrics.csv's convention)
    final: dict[str, list]
    final_error: float
    per_param_error: dict[str, float]
    wall_seconds: float
    run_dir: str = ""
    losses: list[float] = field(default_factory=list)

    @property
    def initial_error(self) -> float:
        return self.step_error[0]

    @property
    def seconds_per_step(self) -> float:
        times = self.step_seconds[WARMUP:] or self.step_seconds
        return float(np.mean(times))


# --------------------------------------------------------------------------- configs
def read_config(task: Task) -> dict:
    return yaml.safe_load((EXAMPLES / task.config).read_text())


def target_file(task: Task, fmt: str) -> Path:
    return EXAMPLES / "room" / "targets" / f"{task.target}.{fmt}"


def read_linear(path: Path) -> np.ndarray:
    """An image file as linear (H, W, C) float32, decoded exactly as torchir decodes targets."""
    from torchir.imageio import read_image

    return read_image(path).permute(1, 2, 0).contiguous().numpy()


def resolve_truth(spec: Any) -> Optional[np.ndarray]:
    if spec is None:
        return None
    if isinstance(spec, str):  # an image file, relative to the config
        return read_linear(EXAMPLES / spec)
    return np.atleast_1d(np.asarray(spec, dtype=np.float64))


def parameter_specs(config: dict) -> list[ParamSpec]:
    model = config["model"]
    default_lr = float(model.get("lr", 0.05))  # InverseRenderingModule's default
    specs = []
    for key, entry in model["parameters"].items():
        bounds = entry.get("bounds")
        specs.append(ParamSpec(
            key=key, init=entry.get("init", 0.5), lr=float(entry.get("lr") or default_lr),
            transform=entry.get("transform", "none"), bounds=None if bounds is None else (float(bounds[0]), float(bounds[1])),
            truth=resolve_truth(entry.get("truth")),
        ))
    return specs


def errors(values: dict[str, np.ndarray], specs: list[ParamSpec]) -> tuple[float, dict[str, float]]:
    """(RMSE over all entries with a truth, as torchir's param_error; RMSE per parameter)."""
    per, sq, n = {}, 0.0, 0
    for s in specs:
        if s.truth is None:
            continue
        diff = np.asarray(values[s.key], np.float64).reshape(s.truth.shape) - s.truth
        per[s.key] = float(np.sqrt(np.mean(diff**2)))
        sq, n = sq + float(np.sum(diff**2)), n + diff.size
    return math.sqrt(sq / n), per


def step_seed(seed: int, step: int) -> int:
    return (seed * GOLDEN + step) % 2**32


# ------------------------------------------------------------------- (b) plain Mitsuba
def load_mitsuba_scene(xml: Path, integrator: Optional[dict] = None, **options: Any):
    """``mi.load_file(xml, **options)``, with bitmaps stored as float and the integrator replaced
    by ``integrator`` (``{type: ..., **properties}``), as a user would edit the file.

    Mitsuba 3.9 keeps an 8-bit PNG texture as ``TensorXu8``; assigning a float tensor to it is
    silently quantised back to 8 bits, so a Mitsuba user adds ``<string name="format"
    value="variant"/>`` to the bitmap. We make that one-line edit in memory (torchir's
    ``Scene.from_file`` does the same at load). ``optimize=False`` keeps the same shapes as
    torchir's scene (Mitsuba's default merges the floor and ceiling meshes)."""
    import mitsuba as mi

    text = float_bitmaps(xml.read_text(), integrator)
    saved = mi.FileResolver(mi.file_resolver())
    mi.file_resolver().prepend(str(xml.parent.resolve()))  # meshes/textures beside the file, as load_file does
    try:
        return mi.load_string(text, optimize=False, **{k: str(v) for k, v in options.items()})
    finally:
        mi.Thread.thread().set_file_resolver(saved)


def float_bitmaps(text: str, integrator: Optional[dict] = None) -> str:
    """The XML with ``<string name="format" value="variant"/>`` in every bitmap that has no format,
    and its ``<integrator>`` element rewritten from ``integrator`` when given."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(text)
    for bitmap in root.iter("texture"):
        if bitmap.get("type") == "bitmap" and not any(c.get("name") == "format" for c in bitmap):
            ET.SubElement(bitmap, "string", name="format", value="variant")
    if integrator:
        element = root.find("integrator")
        element.attrib["type"] = integrator["type"]
        for child in list(element):
            element.remove(child)
        for name, value in integrator.items():
            if name != "type":
                tag = "boolean" if isinstance(value, bool) else "integer" if isinstance(value, int) else "float" if isinstance(value, float) else "string"
                ET.SubElement(element, tag, name=name, value=str(value).lower() if isinstance(value, bool) else str(value))
    return ET.tostring(root, encoding="unicode")


class RigidPose:
    """Mitsuba's pose tutorial: ``Transform4f`` of the initial vertices, about the bbox centre.

    torchir's convention: x' = pivot + R(x - pivot) + t, R about ``axis`` by degrees."""

    def __init__(self, params, label: str, shape: str, axis: list[float]) -> None:
        import drjit as dr
        import mitsuba as mi

        self.label, self.key, self.axis = label, f"{shape}.vertex_positions", mi.ScalarVector3f(axis)
        self.v0 = dr.unravel(mi.Point3f, params[self.key])
        pts = np.asarray(params[self.key].numpy(), np.float64).reshape(-1, 3)
        self.pivot = mi.ScalarVector3f(0.5 * (pts.min(0) + pts.max(0)))

    def apply(self, params, values: dict) -> None:
        import drjit as dr
        import mitsuba as mi

        t, angle = values[f"{self.label}.translation"], values[f"{self.label}.rotation"]
        trafo = mi.Transform4f().translate(self.pivot + t).rotate(self.axis, angle).translate(-self.pivot)
        params[self.key] = dr.ravel(trafo @ self.v0)


def mi_initial(spec: ParamSpec, params, rigid: Optional[RigidPose]):
    """The Mitsuba-typed initial scene value of one parameter."""
    import mitsuba as mi

    if rigid is not None and spec.key.startswith(rigid.label + "."):
        values = np.atleast_1d(np.asarray(spec.init, np.float64))
        if spec.key.endswith(".translation"):
            return mi.Vector3f(*np.broadcast_to(values, (3,)).tolist())
        return mi.Float(float(values[0]))
    current = params[spec.key]
    if spec.init == "scene":
        return type(current)(current)
    value = np.asarray(spec.init, np.float32)
    if isinstance(current, mi.TensorXf):
        return mi.TensorXf(np.ascontiguousarray(np.broadcast_to(value, current.shape)))
    return type(current)(*np.broadcast_to(value, (len(current),)).tolist())


def to_numpy(value) -> np.ndarray:
    return np.asarray(value.numpy(), np.float64).ravel() if hasattr(value, "numpy") else np.asarray(value, np.float64).ravel()


def mitsuba_fit(task: Task, seed: int, steps: int, fmt: str = "png") -> RunResult:
    """Fit ``task`` with a plain Mitsuba loop (module docstring, (b))."""
    import drjit as dr
    import mitsuba as mi

    config, start = read_config(task), time.perf_counter()
    model = config["model"]
    specs = parameter_specs(config)
    scene = load_mitsuba_scene(EXAMPLES / model["scene"], model.get("integrator"), **model.get("scene_options", {}))
    params = mi.traverse(scene)
    rigid = None
    for label, d in (model.get("derived") or {}).items():  # only {type: rigid} in the examples
        rigid = RigidPose(params, label, d["shape"], d.get("rotation_axis", [0, 1, 0]))

    target_np = read_linear(target_file(task, fmt))
    target = mi.TensorXf(target_np)
    # an 8-bit photo pixel with a channel at 255 only says "at least this bright": leave the whole
    # pixel out, as torchir does
    if fmt != "exr":
        clipped = np.any(target_np >= SATURATED, axis=-1, keepdims=True)
        mask = mi.TensorXb(np.ascontiguousarray(np.broadcast_to(clipped, target_np.shape)))
    else:
        mask = None

    opt = mi.ad.Adam(lr=float(model.get("lr", 0.05)))
    for s in specs:
        init = mi_initial(s, params, rigid)
        opt[s.key] = dr.log(init) if s.transform == "log" else clamp(init, s.bounds)
        opt.set_learning_rate({s.key: s.lr})

    def values() -> dict:
        return {s.key: dr.exp(opt[s.key]) if s.transform == "log" else opt[s.key] for s in specs}

    spp, times, errs, losses = int(model["spp"]), [], [], []
    for step in range(steps):
        errs.append(errors({k: to_numpy(v) for k, v in values().items()}, specs)[0])
        t0 = time.perf_counter()
        current = values()
        if rigid is not None:
            rigid.apply(params, current)
        for key, value in current.items():
            if rigid is None or not key.startswith(rigid.label + "."):
                params[key] = value
        params.update()
        img = mi.render(scene, params, spp=spp, seed=step_seed(seed, step))
        if mask is not None:
            img = dr.select(mask, target, img)
        loss = dr.mean(dr.square(img - target))
        dr.backward(loss)
        opt.step()
        for s in specs:
            if s.bounds is not None and s.transform == "none":
                opt[s.key] = clamp(opt[s.key], s.bounds)
        dr.eval(loss, *[opt[s.key] for s in specs])
        dr.sync_thread()
        losses.append(float(loss.array[0]))  # torchir reads its loss each step too (NaN check, logging)
        times.append(time.perf_counter() - t0)
    final = {k: to_numpy(v) for k, v in values().items()}
    err, per = errors(final, specs)
    return RunResult("mitsuba", task.name, seed, fmt, steps, times, errs, {k: v.tolist() for k, v in final.items()},
                     err, per, time.perf_counter() - start, losses=losses)


def clamp(value, bounds: Optional[tuple[float, float]]):
    import drjit as dr

    return value if bounds is None else dr.clip(value, bounds[0], bounds[1])


# ----------------------------------------------------------------------- (a) torchir
def torchir_fit(task: Task, seed: int, steps: Optional[int], fmt: str, out: Path) -> RunResult:
    """Fit ``task`` with ``torchir fit --config <example>.yaml`` (in-process), read its outputs."""
    from torchir.training.cli import main

    name = f"{task.name}-{fmt}-s{seed}"
    args = ["fit", "--config", str(EXAMPLES / task.config), "--trainer.logger.init_args.save_dir", str(out / "runs"),
            "--trainer.logger.init_args.name", name, "--model.seed", str(seed), "--seed_everything", str(seed)]
    if fmt != "png":
        args += ["--data.targets", f"[{target_file(task, fmt)}]"]
    if steps is not None:
        args += ["--trainer.max_steps", str(steps)]
    log = out / "logs" / f"torchir-{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(log, "w") as stream, contextlib.redirect_stdout(stream), contextlib.redirect_stderr(stream), quiet_lightning():
        code = main(args)
    wall = time.perf_counter() - start
    if code != 0:
        raise RuntimeError(f"torchir fit failed for {name} (exit {code}); see {log}")
    run_dir = max((out / "runs" / name).glob("version_*"), key=lambda p: int(p.name.split("_")[1]))
    return read_torchir_run(task, seed, fmt, run_dir, wall)


@contextlib.contextmanager
def quiet_lightning():
    """Lightning's info lines go to logging handlers bound at import, past redirect_stderr."""
    import logging

    loggers = [logging.getLogger(n) for n in ("lightning", "lightning.pytorch", "lightning.fabric")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def read_torchir_run(task: Task, seed: int, fmt: str, run_dir: Path, wall: float) -> RunResult:
    """A finished torchir run from its ``metrics.csv`` and ``result.yaml``."""
    import csv

    with open(run_dir / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("param_error") and r.get("loss")]  # the steps (not the final row)
    rows.sort(key=lambda r: int(r["step"]))
    result = yaml.safe_load((run_dir / "result.yaml").read_text())
    final = {}
    for key, entry in result["parameters"].items():
        if isinstance(entry, dict):  # a texture written beside result.yaml
            final[key] = read_linear(run_dir / entry["file"]).ravel().astype(np.float64)
        else:
            final[key] = np.atleast_1d(np.asarray(entry, np.float64))
    specs = parameter_specs(read_config(task))
    err, per = errors(final, specs)
    return RunResult("torchir", task.name, seed, fmt, len(rows), [float(r["seconds_per_step"]) for r in rows],
                     [float(r["param_error"]) for r in rows], {k: v.tolist() for k, v in final.items()}, err, per, wall,
                     run_dir=str(run_dir), losses=[float(r["loss"]) for r in rows])


# ---------------------------------------------------------------------------- summary
def mean_std(xs: list[float]) -> tuple[float, float]:
    return float(np.mean(xs)), float(np.std(xs, ddof=1)) if len(xs) > 1 else float("nan")


def compare(runs: list[RunResult]) -> dict:
    """Per task: mean ± std over seeds of each method, the ratios and the goals."""
    out = {}
    for task in dict.fromkeys(r.task for r in runs):
        both = {m: [r for r in runs if r.task == task and r.method == m and r.target == "png"] for m in ("torchir", "mitsuba")}
        entry: dict[str, Any] = {}
        for method, rs in both.items():
            e, t = mean_std([r.final_error for r in rs]), mean_std([r.seconds_per_step for r in rs])
            entry[method] = {
                "seeds": [r.seed for r in rs], "final_error": e[0], "final_error_std": e[1],
                "initial_error": float(np.mean([r.initial_error for r in rs])),
                "seconds_per_step": t[0], "seconds_per_step_std": t[1],
                "wall_seconds": float(np.mean([r.wall_seconds for r in rs])),
                "per_param_error": {k: mean_std([r.per_param_error[k] for r in rs]) for k in rs[0].per_param_error},
            }
        t, m = entry["torchir"], entry["mitsuba"]
        n = min(len(both["torchir"]), len(both["mitsuba"]))
        se = math.sqrt((t["final_error_std"] ** 2 + m["final_error_std"] ** 2) / n) if n > 1 else float("nan")
        entry["error_ratio"] = t["final_error"] / m["final_error"]
        entry["time_ratio"] = t["seconds_per_step"] / m["seconds_per_step"]
        entry["within_noise"] = bool(n > 1 and abs(t["final_error"] - m["final_error"]) <= 2 * se)
        entry["error_goal_met"] = bool(entry["error_ratio"] <= ERROR_GOAL or entry["within_noise"])
        entry["time_goal_met"] = bool(entry["time_ratio"] <= TIME_GOAL)
        out[task] = entry
    return out


def fmt_ms(x: float, sd: float) -> str:
    return f"{x:.4g}" if math.isnan(sd) else f"{x:.4g} ± {sd:.2g}"


def main_table(summary: dict) -> str:
    lines = [
        "| task | final error torchir | final error Mitsuba | ratio (goal ≤ 1.10 or within noise) "
        "| ms/step torchir | ms/step Mitsuba | ratio (goal ≤ 1.10) | run wall s torchir / Mitsuba |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for task, e in summary.items():
        t, m = e["torchir"], e["mitsuba"]
        noise = "within noise" if e["within_noise"] else ("n/a (1 seed)" if len(t["seeds"]) < 2 else "outside noise")
        lines.append(
            f"| {task} | {fmt_ms(t['final_error'], t['final_error_std'])} (from {t['initial_error']:.3g}) "
            f"| {fmt_ms(m['final_error'], m['final_error_std'])} (from {m['initial_error']:.3g}) "
            f"| {e['error_ratio']:.3f}, {noise}: {'MET' if e['error_goal_met'] else 'NOT met'} "
            f"| {fmt_ms(1e3 * t['seconds_per_step'], 1e3 * t['seconds_per_step_std'])} "
            f"| {fmt_ms(1e3 * m['seconds_per_step'], 1e3 * m['seconds_per_step_std'])} "
            f"| {e['time_ratio']:.3f}: {'MET' if e['time_goal_met'] else 'NOT met'} "
            f"| {t['wall_seconds']:.1f} / {m['wall_seconds']:.1f} |"
        )
    pose = summary.get("pose")
    if pose:
        lines.append("")
        lines.append("| pose | translation RMSE torchir | translation RMSE Mitsuba | rotation error (deg) torchir | rotation error (deg) Mitsuba |")
        lines.append("|---|---|---|---|---|")
        cells = [fmt_ms(*pose[m]["per_param_error"][k]) for k in ("blob.translation", "blob.rotation") for m in ("torchir", "mitsuba")]
        lines.append("| final | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def short(values: list[float]) -> str:
    if len(values) > 4:  # a texture
        return f"mean {np.mean(values):.4f} ({len(values)} values)"
    return "[" + ", ".join(f"{v:.4g}" for v in values) + "]"


def quantisation(task: Task, fmt: str) -> float:
    """RMS difference between an 8-bit target and the EXR one, relative to the EXR's mean,
    over pixels that did not clip (what the 8-bit encoding alone changes in the data)."""
    exr, other = read_linear(target_file(task, "exr")), read_linear(target_file(task, fmt))
    keep = (other < SATURATED) & (exr < 1.0)  # JPEG ringing leaves some over-exposed pixels below the mask
    return float(np.sqrt(np.mean((other - exr)[keep] ** 2)) / np.mean(exr[keep]))


def format_rows(runs: list[RunResult], tasks: list[Task]) -> dict:
    """Per task and target format: torchir's seed-0 answer, its error, and its difference from
    the PNG answer, beside the MC noise (seed std) and the targets' 8-bit quantisation."""
    out = {}
    for task in tasks:
        by_fmt = {r.target: r for r in runs if r.task == task.name and r.method == "torchir" and r.seed == 0}
        if "png" not in by_fmt:
            continue
        png_seeds = [r for r in runs if r.task == task.name and r.method == "torchir" and r.target == "png"]
        rows = {}
        for fmt, r in by_fmt.items():
            diffs = {k: float(np.max(np.abs(np.asarray(v) - np.asarray(by_fmt["png"].final[k])))) for k, v in r.final.items()}
            noise = {k: float(np.max(np.std([np.asarray(x.final[k]) for x in png_seeds], axis=0, ddof=1))) if len(png_seeds) > 1
                     else float("nan") for k in r.final}
            rows[fmt] = {"final": r.final, "final_error": r.final_error, "per_param_error": r.per_param_error,
                         "max_abs_diff_vs_png": diffs, "seed_std": noise,
                         "target_quantisation_rel_rms": 0.0 if fmt == "exr" else quantisation(task, fmt)}
        out[task.name] = rows
    return out


def formats_table(rows: dict) -> str:
    lines = ["| task | target | final values | error vs truth | max abs diff vs PNG answer | seed std (PNG, MC noise) | target 8-bit rel. RMS vs EXR |",
             "|---|---|---|---|---|---|---|"]
    for task, per in rows.items():
        for fmt in FORMATS:
            if fmt not in per:
                continue
            r = per[fmt]
            vals = "; ".join(f"{k.split('.')[-2] if 'blob' not in k else k}: {short(v)}" for k, v in r["final"].items())
            diff = "; ".join(f"{v:.3g}" for v in r["max_abs_diff_vs_png"].values())
            noise = "; ".join("n/a" if math.isnan(v) else f"{v:.3g}" for v in r["seed_std"].values())
            lines.append(f"| {task} | {fmt} | {vals} | {r['final_error']:.4g} | {diff} | {noise} | {r['target_quantisation_rel_rms']:.3g} |")
    return "\n".join(lines)


def plot(runs: list[RunResult], path: Path) -> None:
    """Parameter error vs step (top) and vs cumulative step time (bottom), one column per task."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r.task for r in runs))
    fig, axes = plt.subplots(2, len(tasks), figsize=(4.2 * len(tasks), 7), squeeze=False)
    colours = {"torchir": "tab:blue", "mitsuba": "tab:orange"}
    for col, task in enumerate(tasks):
        for r in (r for r in runs if r.task == task and r.target == "png"):
            label = f"{r.method}" if r.seed == 0 else None
            x_time = np.cumsum(r.step_seconds)
            for row, x in enumerate((np.arange(len(r.step_error)), x_time)):
                axes[row][col].semilogy(x, np.maximum(r.step_error, 1e-8), color=colours[r.method], alpha=0.8, lw=1, label=label)
        axes[0][col].set(title=task, xlabel="optimiser step", ylabel="parameter error (RMSE)")
        axes[1][col].set(xlabel="cumulative step time (s)", ylabel="parameter error (RMSE)")
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
        axes[0][col].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------- main
def parse_args(argv: Optional[list[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "results" / "bench_tutorials"))
    p.add_argument("--quick", action="store_true", help=f"{QUICK_DEFAULT} steps ({QUICK_STEPS} for slow tasks), 1 seed, "
                   "no pose format runs (< 3 minutes)")
    p.add_argument("--tasks", default=",".join(TASKS), help="comma-separated subset of " + ", ".join(TASKS))
    p.add_argument("--steps", type=int, default=None, help="override every task's step count")
    p.add_argument("--seeds", type=int, default=None, help="seeds per method (default 3; 1 with --quick)")
    p.add_argument("--task-steps", default="", help="per-task step counts, e.g. pose=20 (over --steps)")
    p.add_argument("--task-seeds", default="", help="per-task seed counts, e.g. pose=1 (over --seeds)")
    p.add_argument("--no-formats", action="store_true", help="skip the PNG/JPG/EXR target comparison")
    args = p.parse_args(argv)
    args.task_list = args.tasks.split(",")
    try:
        args.task_steps, args.task_seeds = per_task(args.task_steps), per_task(args.task_seeds)
    except ValueError:
        p.error("--task-steps/--task-seeds take TASK=N[,TASK=N...]")
    unknown = (set(args.task_list) | set(args.task_steps) | set(args.task_seeds)) - set(TASKS)
    if unknown:
        p.error(f"unknown task(s) {sorted(unknown)}; choose from {list(TASKS)}")
    args.seeds = args.seeds or (1 if args.quick else 3)
    return args


def per_task(text: str) -> dict[str, int]:
    return {k.strip(): int(v) for k, v in (item.split("=") for item in text.split(",") if item.strip())}


def plan(args: argparse.Namespace, task: Task) -> tuple[int, int, bool]:
    """(steps, seeds, run the target-format fits) of one task under the command line."""
    steps = args.task_steps.get(task.name) or args.steps
    if steps is None:
        steps = QUICK_STEPS.get(task.name, QUICK_DEFAULT) if args.quick else int(read_config(task)["trainer"]["max_steps"])
    seeds = args.task_seeds.get(task.name) or args.seeds
    formats = not args.no_formats and not (args.quick and task.name in QUICK_STEPS)
    return steps, seeds, formats


def run_all(args: argparse.Namespace, out: Path) -> list[RunResult]:
    """Every fit, interleaved (Mitsuba, then torchir, per seed) so machine load hits both alike."""
    runs = []
    for name in args.task_list:
        task = TASKS[name]
        steps, seeds, formats = plan(args, task)
        for seed in range(seeds):
            for method in ("mitsuba", "torchir"):
                r = mitsuba_fit(task, seed, steps) if method == "mitsuba" else torchir_fit(task, seed, steps, "png", out)
                runs.append(r)
                print(f"[bench] {name:8s} {method:7s} seed {seed}: error {r.initial_error:.4g} -> {r.final_error:.4g}, "
                      f"{1e3 * r.seconds_per_step:.1f} ms/step, run {r.wall_seconds:.1f} s", flush=True)
        if formats:
            for fmt in FORMATS[1:]:
                r = torchir_fit(task, 0, steps, fmt, out)
                runs.append(r)
                print(f"[bench] {name:8s} torchir {fmt} target: error {r.final_error:.4g}", flush=True)
    return runs


def main(argv: Optional[list[str]] = None) -> dict:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import mitsuba as mi

    from torchir import backend

    backend.set_variant("llvm_ad_rgb")  # both methods on the same backend
    start = time.perf_counter()
    runs = run_all(args, out)
    summary = compare(runs)
    formats = format_rows(runs, [TASKS[n] for n in args.task_list])
    text = "## torchir (YAML) vs plain Mitsuba loop\n\n" + main_table(summary)
    if formats:
        text += "\n\n## torchir answers by target file (seed 0)\n\n" + formats_table(formats)
    print("\n" + text + "\n")
    plot(runs, out / "curves.png")
    report = {
        "settings": {"quick": args.quick, "tasks": args.task_list, "command": " ".join(sys.argv),
                     "plan": {n: dict(zip(("steps", "seeds", "formats"), plan(args, TASKS[n]))) for n in args.task_list},
                     "config_steps": {n: int(read_config(TASKS[n])["trainer"]["max_steps"]) for n in args.task_list},
                     "warmup_steps_excluded": WARMUP, "variant": mi.variant(), "bench_seconds": time.perf_counter() - start},
        "summary": summary, "formats": formats, "runs": [asdict(r) for r in runs],
    }
    (out / "results.json").write_text(json.dumps(report, indent=1))
    (out / "summary.md").write_text(text + "\n")
    print(f"[bench] wrote {out / 'summary.md'}, {out / 'results.json'}, {out / 'curves.png'} "
          f"({time.perf_counter() - start:.0f} s)")
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
