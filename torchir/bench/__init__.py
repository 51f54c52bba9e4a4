"""``torchir bench``: the speed/accuracy trade of each technique, measured, in one report.

Each suite is a module of this package with ``main(argv)`` that takes ``--quick`` and
``--out DIR``, prints its tables (Markdown) and writes, through :func:`save_results`,
``results.json`` (with the run's :func:`environment`: command, commit, machine) and
``summary.md``, and PNG plots into ``DIR``; a suite may define ``summary(results) -> str``, its
tables from the JSON alone (:mod:`torchir.bench.pages`); :mod:`torchir.bench._common` holds what they share (medians,
Markdown tables, timing). The suite's output is kept in ``DIR/log.txt``. :func:`run_suites` runs suites one after another, each in a fresh process (Dr.Jit's
kernel cache and memory do not leak from one into the next), then writes the report
(:mod:`torchir.bench.report`).
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

SUITES: dict[str, str] = {  # suite -> module with main(argv)
    "overhead": "torchir.bench.overhead",
    "adaptive": "torchir.bench.adaptive",
    "denoiser": "torchir.bench.denoiser",
    "loi": "torchir.bench.loi",
    "restir": "torchir.bench.restir",
    "restir_views": "torchir.bench.restir_views",
    "restir_shadow": "torchir.bench.restir_shadow",
    "restir_antithetic": "torchir.bench.restir_antithetic",
    "restir_silhouette": "torchir.bench.restir_silhouette",
    "mesh_gradients": "torchir.bench.mesh_gradients",
    "combined": "torchir.bench.combined",
    "stepcost": "torchir.bench.stepcost",
    "scaleup": "torchir.bench.scaleup",
    "soak": "torchir.bench.soak",
    "jpeg": "torchir.bench.jpeg",
    "shape_tutorial": "torchir.bench.shape_tutorial",
    "mesh_step": "torchir.bench.mesh_step",
    "volume_tutorial": "torchir.bench.volume_tutorial",
}
ALL = tuple(SUITES)


def environment() -> dict:
    """Versions and machine facts recorded with every suite's results."""
    import os
    import platform

    import drjit as dr
    import torch

    from .. import backend

    command, suite = _command()
    return {
        "suite": suite, "command": command, "commit": _commit(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "torchir_backend": backend.describe(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
        "drjit_threads": dr.thread_count(), "cpu_count": os.cpu_count(), "load_average_1_5_15min": list(os.getloadavg()),
        "python": platform.python_version(), "platform": platform.platform(),
    }


def _command() -> tuple[str, str | None]:
    """The running suite's command line (``python -m torchir.bench.X ...``) and its suite name."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    module = spec.name if spec is not None else None
    head = f"python -m {module}" if module else Path(sys.argv[0]).name
    suite = next((name for name, path in SUITES.items() if path == module), None)
    return " ".join([head, *sys.argv[1:]]), suite


def _commit() -> str | None:
    """The torchir checkout's commit (``+changes`` when its tracked files differ), or None outside one."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "") if head.returncode == 0 else None


def run_suites(suites: Sequence[str], quick: bool, out: Path, options: Sequence[str] = ()) -> list[dict]:
    """Run ``suites`` (``"all"`` expands to every suite) and write the report into ``out``;
    ``options`` are passed on to each suite's command line."""
    from .report import write_report

    names = list(ALL) if list(suites) == ["all"] else list(suites)
    unknown = [n for n in names if n not in SUITES]
    if unknown:
        raise ValueError(f"unknown bench suite(s) {unknown}; choose from {', '.join(SUITES)} or all")
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for name in names:
        folder = out / name
        command = [sys.executable, "-m", SUITES[name], "--out", str(folder), *(["--quick"] if quick else []), *options]
        print(f"[torchir bench] {name}: {' '.join(command)}", flush=True)
        started = time.perf_counter()
        folder.mkdir(parents=True, exist_ok=True)
        with open(folder / "log.txt", "w") as log:
            process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
            for line in process.stdout:  # progress stays visible, and the log keeps the tables
                print(line, end="", flush=True)
                log.write(line)
            code = process.wait()
        seconds = time.perf_counter() - started
        print(f"[torchir bench] {name}: exit {code} after {seconds:.0f} s", flush=True)
        runs.append({"suite": name, "folder": folder, "exit_code": code, "seconds": seconds, "quick": quick})
    report = write_report(out, runs)
    print(f"[torchir bench] report: {report} (and {report.with_suffix('.html')})")
    return runs


def save_results(out: Path, results: Any, summary: str | None = None) -> None:
    """Every suite's output: ``results.json`` (a mapping gets the run's :func:`environment` unless it
    has one; a list is wrapped as ``{"runs": ..., "environment": ...}``) and, when given,
    ``summary.md`` (its Markdown tables). The docs' results page reads both (:mod:`.pages`)."""
    out.mkdir(parents=True, exist_ok=True)
    record = dict(results) if isinstance(results, dict) else {"runs": results}
    if "environment" not in record:  # (setdefault would run git and import Dr.Jit for nothing)
        record["environment"] = environment()
    (out / "results.json").write_text(json.dumps(record, indent=1))
    if summary is not None:
        (out / "summary.md").write_text(summary if summary.endswith("\n") else summary + "\n")


def write_outputs(out: Path, summary: str, results: dict, draw: Callable[[Any], None], picture: str,
                  xlabel: str, ylabel: str, log_y: bool = False) -> None:
    """Print a suite's Markdown ``summary`` and write ``summary.md``, ``results.json`` and one
    line plot (``picture``, drawn by ``draw(ax)``) into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    print(summary)
    save_results(out, results, summary)
    fig, ax = plt.subplots(figsize=(7, 4))
    draw(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log_y:
        ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / picture, dpi=110)
    plt.close(fig)
