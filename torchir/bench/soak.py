"""Memory and recompilation soak: many steps of the quickstart with each technique on.

Each technique runs the quickstart problem (Cornell box, red and green wall albedos) through
the real trainer for ``--steps`` steps in its own process, with Dr.Jit's kernel history on for
the whole run (switching it per step would itself force frozen passes to re-record). After
every step it records the resident memory (``/proc/self/statm``), the kernels launched and the
in-memory kernel-cache misses. After a warm-up (the first ``--warmup`` steps, Stage-1 refreshes
and reservoir burn-in included) the goals are: memory grows by less than 5 % and no kernel is
compiled or missed in the cache again.

Usage:
    torchir bench soak [--quick]
    (default: 1000 steps per technique; --quick: 150 steps)

Writes ``<out>/results.json``, ``<out>/soak.png`` (memory and cache misses against steps) and
prints the summary table.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from torchir.bench import save_results
from .. import backend

TECHNIQUES: dict[str, dict[str, Any]] = {  # technique -> InverseRenderingModule overrides
    "plain": {},
    "adaptive": {"sampler": {"type": "adaptive", "budget": 0.1, "refresh_every": 20}},
    "denoiser": {"denoiser": {"type": "target_aware", "radius": 7}},
    "loi": {"loss": {"type": "loi", "alphas": [1, 5], "sigmas": [1]}},
    "restir": {"scene_options": {"max_depth": 2}, "sampler": {"type": "restir", "burn_in": 8}},
}
MEMORY_GOAL = 0.05  # relative growth after warm-up


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def run_one(technique: str, steps: int, warmup: int, resolution: int) -> dict[str, Any]:
    """Run one technique in this process; per-step memory and kernel-cache records."""
    import drjit as dr
    import lightning.pytorch as pl

    from torchir.backend import drain_kernel_history
    from torchir.training import InverseRenderingModule, ViewDataModule

    class Recorder(pl.Callback):
        def __init__(self) -> None:
            self.rows: list[dict[str, float]] = []
            self.start = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            kernels = drain_kernel_history()
            self.rows.append({
                "step": trainer.global_step, "seconds": time.perf_counter() - self.start, "rss_mb": _rss_bytes() / 2**20,
                "launched": kernels.launched, "cache_misses": kernels.cache_misses, "compiled": kernels.compiled,
            })

    model = {
        "scene": "cbox", "resolution": resolution, "spp": 8, "lr": 0.05,
        "parameters": {k: {"init": 0.5, "bounds": [0.0, 1.0]} for k in ("red.reflectance.value", "green.reflectance.value")},
        **TECHNIQUES[technique],
    }
    module = InverseRenderingModule(**model)
    recorder = Recorder()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    trainer = pl.Trainer(accelerator=backend.device(), max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, callbacks=[recorder])
    trainer.fit(module, datamodule=ViewDataModule(target_spp=64))
    rows = recorder.rows
    after = [r for r in rows if r["step"] > warmup]
    base = next((r["rss_mb"] for r in rows if r["step"] >= warmup), rows[-1]["rss_mb"])
    return {
        "technique": technique, "steps": steps, "warmup": warmup, "rows": rows,
        "rss_after_warmup_mb": base, "rss_final_mb": rows[-1]["rss_mb"],
        "memory_growth": rows[-1]["rss_mb"] / base - 1.0,
        "cache_misses_after_warmup": sum(r["cache_misses"] for r in after),
        "compiled_after_warmup": sum(r["compiled"] for r in after),
        "kernels_per_step": sum(r["launched"] for r in after) / max(1, len(after)),
        "seconds_per_step": (after[-1]["seconds"] - after[0]["seconds"]) / max(1, len(after) - 1) if len(after) > 1 else float("nan"),
        "param_error": module.parameter_error(module.ground_truth()),
    }


def table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| technique | steps | s/step | kernels/step | RSS after warm-up (MB) | RSS final (MB) | growth | cache misses after warm-up | compiled after warm-up | goals met |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['technique']} | - | - | - | - | - | - | - | - | failed: {r['error']} |")
            continue
        met = r["memory_growth"] < MEMORY_GOAL and r["cache_misses_after_warmup"] == 0
        lines.append(
            f"| {r['technique']} | {r['steps']} | {r['seconds_per_step']:.3f} | {r['kernels_per_step']:.1f} | "
            f"{r['rss_after_warmup_mb']:.0f} | {r['rss_final_mb']:.0f} | {100 * r['memory_growth']:+.1f}% | "
            f"{r['cache_misses_after_warmup']} | {r['compiled_after_warmup']} | {'yes' if met else 'NO'} |"
        )
    return "\n".join(lines)


def plot(path: Path, results: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_mem, ax_miss) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        if "rows" not in r:
            continue
        steps = [row["step"] for row in r["rows"]]
        ax_mem.plot(steps, [row["rss_mb"] for row in r["rows"]], label=r["technique"])
        cumulative, total = [], 0
        for row in r["rows"]:
            total += row["cache_misses"]
            cumulative.append(total)
        ax_miss.plot(steps, cumulative, label=r["technique"])
    warmup = next((r["warmup"] for r in results if "warmup" in r), 0)
    for ax, label in ((ax_mem, "resident memory (MB)"), (ax_miss, "kernel-cache misses (cumulative)")):
        ax.axvline(warmup, color="grey", ls=":", lw=1)
        ax.set(xlabel="optimiser step", ylabel=label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("soak: memory and recompilations per technique (dotted: end of warm-up)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="150 steps per technique instead of 1000")
    p.add_argument("--steps", type=int, default=None, help="steps per technique (default 1000, quick 150)")
    p.add_argument("--warmup", type=int, default=None, help="warm-up steps (default 10%% of steps, at least 25)")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--techniques", nargs="+", default=list(TECHNIQUES), choices=list(TECHNIQUES))
    p.add_argument("--out", default="results/bench_soak")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: run one technique, print JSON
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    args = parse_args(argv)
    steps = args.steps or (150 if args.quick else 1000)
    warmup = args.warmup if args.warmup is not None else max(25, steps // 10)
    if args.one:
        print("SOAK-RESULT " + json.dumps(run_one(args.one, steps, warmup, args.resolution)))
        return []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for technique in args.techniques:  # one process each: memory and kernel caches start clean
        started = time.perf_counter()
        command = [sys.executable, "-m", "torchir.bench.soak", "--one", technique, "--steps", str(steps),
                   "--warmup", str(warmup), "--resolution", str(args.resolution)]
        done = subprocess.run(command, capture_output=True, text=True)
        line = next((ln for ln in done.stdout.splitlines() if ln.startswith("SOAK-RESULT ")), None)
        if line is None:
            error = (done.stderr.strip().splitlines() or ["no output"])[-1][:160]
            results.append({"technique": technique, "error": error})
        else:
            results.append(json.loads(line[len("SOAK-RESULT "):]))
        print(f"[soak] {technique}: {time.perf_counter() - started:.0f} s", flush=True)
    summary = (f"### Soak: {steps} steps per technique, warm-up {warmup} steps; goals: memory growth < "
               f"{100 * MEMORY_GOAL:.0f}% and 0 cache misses after warm-up\n\n{table(results)}")
    save_results(out, results, summary)
    plot(out / "soak.png", results)
    print(summary)
    print(f"wrote {out / 'results.json'} and {out / 'soak.png'}")
    return results


if __name__ == "__main__":
    main()
