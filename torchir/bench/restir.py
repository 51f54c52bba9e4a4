#!/usr/bin/env python
"""ReSTIR for inverse direct illumination (paper 004) against its baselines on ``oxalis_lite``.

Methods (all through ``torchir.functions.render(..., sampler=ReSTIRSampler(...))``):

* **B.1**: one light sample per camera ray, no reuse (``preset="b1"``);
* **B.2**: streaming RIS with M candidates, no reuse (``preset="b2"``);
* **ReSTIR**: RIS + spatiotemporal reuse of the previous step's reservoirs (burn-in 32).

Each baseline runs twice: at *equal samples* (the same spp as ReSTIR) and at *equal time*
(spp raised until its seconds/step matches ReSTIR's; measured once, interleaved, before the
experiments). Three experiments (spec §7):

* **T-B1 gradient error** at the initial (grey) texture: the adjoint of the L2 loss against
  the target, held fixed (so the error is the estimator's, not the loss's), relative error
  ``||g - g_ref|| / ||g_ref||`` averaged over the steps after burn-in (D9); reference: prb
  (direct light, max_depth 2) at high spp. Uniform and power emitter selection.
* **T-B2 reconstruction**: Adam (lr 0.02) from a grey texture, L2 image loss, clamp to
  [1e-3, 1]; texture RMSE against the ground truth after N steps, with ``shared`` and
  ``decorrelated`` gradient paths; all methods step in lockstep (interleaved); wall time
  includes ReSTIR's burn-in.
* **T-B4 overhead**: seconds per stage of a ReSTIR step (RIS, NN, combination, backward) and
  the overhead of reuse over a B.2 step at equal samples.

Usage:
    python scripts/bench_restir.py            # 64x64, texture 32, T-B1 32 steps, T-B2 150 steps
    python scripts/bench_restir.py --quick    # 48x48, texture 16, 12 / 40 steps (a few minutes)

Writes ``<out>/results.json``, ``<out>/gradient_error.png`` and ``<out>/reconstruction.png``.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import drjit as dr
import numpy as np
import torch

import torchir
from torchir.functions import render
from torchir.samplers import ReSTIRSampler

KEY = "canvas.bsdf.reflectance.data"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--texture", type=int, default=32)
    p.add_argument("--spp", type=int, default=4, help="ReSTIR (and equal-sample baseline) spp")
    p.add_argument("--candidates", type=int, default=8)
    p.add_argument("--burn-in", type=int, default=32)
    p.add_argument("--grad-steps", type=int, default=32, help="T-B1 steps averaged after burn-in")
    p.add_argument("--recon-steps", type=int, default=150, help="T-B2 optimisation steps")
    p.add_argument("--ref-spp", type=int, default=4096, help="reference spp (gradient and target)")
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--out", default="results/bench_restir")
    p.add_argument("--quick", action="store_true", help="48x48, texture 16, 12 gradient / 40 reconstruction steps")
    a = p.parse_args(argv)
    if a.quick:
        a.resolution, a.texture, a.grad_steps, a.recon_steps, a.ref_spp = 48, 16, 12, 40, 2048
    return a


def _sync_time() -> float:
    dr.sync_thread()
    return time.perf_counter()


def make_scene(a, emitter_pdf: str) -> torchir.Scene:
    return torchir.Scene.builtin("oxalis_lite", resolution=a.resolution, texture=a.texture, emitter_pdf=emitter_pdf)


def sampler_for(scene, method: str, a, grad_paths: str = "shared", seed: int = 0) -> ReSTIRSampler:
    if method == "B.1":
        return ReSTIRSampler(scene, preset="b1", grad_paths=grad_paths, seed=seed)
    if method == "B.2":
        return ReSTIRSampler(scene, preset="b2", candidates=a.candidates, grad_paths=grad_paths, seed=seed)
    if method == "ReSTIR-cap20":  # Bitterli's long memory (spec D2): M capped at 20 * candidates
        return ReSTIRSampler(scene, candidates=a.candidates, burn_in=a.burn_in, grad_paths=grad_paths, seed=seed,
                             m_cap=20 * a.candidates)
    return ReSTIRSampler(scene, candidates=a.candidates, burn_in=a.burn_in, grad_paths=grad_paths, seed=seed)


def step_time(scene, method, a, spp, grey, adjoint, steps=6) -> float:
    """Median seconds of a full step (render + backward) after warm-up (burn-in excluded)."""
    r = sampler_for(scene, method, a)
    times = []
    for i in range(steps + 2):
        t = grey.clone().requires_grad_()
        t0 = _sync_time()
        img = render(scene, {KEY: t}, spp=spp, seed=i, sampler=r)
        (img * adjoint).sum().backward()
        t1 = _sync_time()
        if i >= 2:
            times.append(t1 - t0)
    return float(np.median(times))


def calibrate(scene, a, grey, adjoint) -> dict:
    """Seconds/step at equal samples and the baselines' equal-time spp (interleaved)."""
    t = {m: [] for m in ("B.1", "B.2", "ReSTIR")}
    for _ in range(2):
        for m in t:
            t[m].append(step_time(scene, m, a, a.spp, grey, adjoint))
    sec = {m: float(np.median(v)) for m, v in t.items()}
    spp_eq = {m: max(a.spp, int(round(a.spp * sec["ReSTIR"] / sec[m]))) for m in ("B.1", "B.2")}
    # refine: time is not linear in spp (fixed costs per step); re-measure against ReSTIR
    for _ in range(2):
        for m in spp_eq:
            ratio = step_time(scene, "ReSTIR", a, a.spp, grey, adjoint) / step_time(scene, m, a, spp_eq[m], grey, adjoint)
            spp_eq[m] = max(a.spp, int(round(spp_eq[m] * ratio)))
    return {"seconds_per_step": sec, "equal_time_spp": spp_eq}


def methods_table(a, cal) -> list[tuple[str, str, int]]:
    """(label, method, spp) of every run."""
    return [
        ("B.1 (eq. samples)", "B.1", a.spp),
        ("B.2 (eq. samples)", "B.2", a.spp),
        (f"B.1 (eq. time, {cal['equal_time_spp']['B.1']} spp)", "B.1", cal["equal_time_spp"]["B.1"]),
        (f"B.2 (eq. time, {cal['equal_time_spp']['B.2']} spp)", "B.2", cal["equal_time_spp"]["B.2"]),
        (f"ReSTIR (m_cap {20 * a.candidates}, spec D2)", "ReSTIR-cap20", a.spp),
        ("ReSTIR", "ReSTIR", a.spp),  # default m_cap = 2 * candidates
    ]


def gradient_error(scene, a, cal, grey, adjoint, g_ref) -> dict:
    """T-B1: mean relative gradient error per step (steps interleaved across methods)."""
    runs = methods_table(a, cal)
    samplers = {label: sampler_for(scene, m, a) for label, m, _ in runs}
    errs = {label: [] for label, _, _ in runs}
    grads = {label: [] for label, _, _ in runs}
    secs = {label: [] for label, _, _ in runs}
    for i in range(a.grad_steps):
        for label, _, spp in runs:
            t = grey.clone().requires_grad_()
            t0 = _sync_time()
            img = render(scene, {KEY: t}, spp=spp, seed=1000 + i, sampler=samplers[label])
            (img * adjoint).sum().backward()
            secs[label].append(_sync_time() - t0)
            errs[label].append(float((t.grad - g_ref).norm() / g_ref.norm()))
            grads[label].append(t.grad)
    restir = np.mean(errs["ReSTIR"])
    window = min(8, a.grad_steps)

    def windowed(label: str) -> float:  # error of the mean of `window` consecutive gradients
        g = torch.stack(grads[label])
        return float(np.mean([float((g[i : i + window].mean(0) - g_ref).norm() / g_ref.norm())
                              for i in range(len(g) - window + 1)]))
    return {
        label: {
            "relerr": float(np.mean(errs[label])),
            "relerr_sd": float(np.std(errs[label])),
            "seconds_per_step": float(np.median(secs[label])),
            "ratio_to_restir": float(np.mean(errs[label]) / restir),
            f"relerr_mean_of_{window}": windowed(label),
        }
        for label, _, _ in runs
    }


def reconstruction(scene, a, cal, gt, target, grey, grad_paths: str) -> dict:
    """T-B2: lockstep Adam runs, texture RMSE against the ground truth."""
    runs = methods_table(a, cal)
    state = {}
    for label, m, spp in runs:
        t0 = _sync_time()
        r = sampler_for(scene, m, a, grad_paths=grad_paths)
        p = torch.nn.Parameter(grey.clone())
        state[label] = {"r": r, "p": p, "opt": torch.optim.Adam([p], lr=a.lr), "spp": spp, "time": 0.0,
                        "rmse": [float((grey - gt).pow(2).mean().sqrt())], "t": [0.0]}
    for i in range(a.recon_steps):
        for label, _, _ in runs:
            s = state[label]
            t0 = _sync_time()
            s["opt"].zero_grad()
            img = render(scene, {KEY: s["p"]}, spp=s["spp"], seed=5000 + i, sampler=s["r"])
            loss = ((img - target) ** 2).mean()
            loss.backward()
            s["opt"].step()
            with torch.no_grad():
                s["p"].clamp_(1e-3, 1.0)
            s["time"] += _sync_time() - t0
            s["rmse"].append(float((s["p"].detach() - gt).pow(2).mean().sqrt()))
            s["t"].append(s["time"])
    restir = state["ReSTIR"]["rmse"][-1]
    return {
        label: {"rmse": s["rmse"][-1], "seconds": s["time"], "ratio_to_restir": s["rmse"][-1] / restir,
                "curve": s["rmse"], "curve_t": s["t"]}
        for label, s in state.items()
    }


def overhead(scene, a, grey, adjoint, steps=8) -> dict:
    """T-B4: mean seconds per stage of a ReSTIR step and of a B.2 step (equal samples)."""
    out = {}
    for m in ("B.2", "ReSTIR"):
        r = sampler_for(scene, m, a)
        acc = {}
        total = []
        for i in range(steps + 2):
            t = grey.clone().requires_grad_()
            t0 = _sync_time()
            (render(scene, {KEY: t}, spp=a.spp, seed=9000 + i, sampler=r) * adjoint).sum().backward()
            total.append(_sync_time() - t0)
            if i >= 2:
                for k, v in r.diagnostics().items():
                    if k.startswith("time_") and k != "time_burn_in":
                        acc.setdefault(k, []).append(v)
        out[m] = {k: float(np.mean(v)) for k, v in acc.items()}
        out[m]["total"] = float(np.median(total[2:]))
    out["overhead_pct"] = 100.0 * (out["ReSTIR"]["total"] / out["B.2"]["total"] - 1.0)
    return out


def print_table(title: str, header: list[str], rows: list[list]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        lines.append("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row) + " |")
    text = "\n".join(lines)
    print(text + "\n", flush=True)
    return text


def main(argv=None) -> None:
    a = parse_args(argv)
    torchir.backend.set_variant("auto")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"config": vars(a), "machine": platform.platform(), "T-B1": {}, "T-B2": {}}
    tables = []
    t_start = time.perf_counter()
    # One reference for both emitter pdfs (the pdf changes the noise, not the expectation):
    # target, the L2 adjoint at the grey texture and its prb gradient, from the uniform scene.
    ref_scene = make_scene(a, "uniform")
    gt = ref_scene.get(KEY)
    grey = torch.full_like(gt, 0.5)
    target = render(ref_scene, {}, spp=a.ref_spp, seed=1)
    ref_img = render(ref_scene, {KEY: grey}, spp=a.ref_spp, seed=2)
    adjoint = (2.0 * (ref_img - target) / ref_img.numel()).detach()  # d(L2)/dI at the grey texture
    gs = []
    for s in range(4):
        t = grey.clone().requires_grad_()
        (render(ref_scene, {KEY: t}, spp=a.ref_spp // 4, seed=3 + s) * adjoint).sum().backward()
        gs.append(t.grad)
    g_ref = torch.stack(gs).mean(0)
    results["reference_gradient_relative_se"] = float(torch.stack(gs).std(0).norm() / 2.0 / g_ref.norm())
    for pdf in ("uniform", "power"):
        scene = ref_scene if pdf == "uniform" else make_scene(a, pdf)
        cal = calibrate(scene, a, grey, adjoint)
        results.setdefault("calibration", {})[pdf] = cal
        print(f"[{pdf}] seconds/step at {a.spp} spp: {cal['seconds_per_step']}; equal-time spp: {cal['equal_time_spp']}", flush=True)
        tb1 = gradient_error(scene, a, cal, grey, adjoint, g_ref)
        results["T-B1"][pdf] = tb1
        tables.append(print_table(
            f"T-B1 gradient relative error, emitter pdf = {pdf} ({a.grad_steps} steps after burn-in)",
            ["method", "relerr", "sd", "s/step", "error / ReSTIR", f"relerr of {min(8, a.grad_steps)}-step mean"],
            [[k, v["relerr"], v["relerr_sd"], v["seconds_per_step"], v["ratio_to_restir"],
              v[f"relerr_mean_of_{min(8, a.grad_steps)}"]] for k, v in tb1.items()],
        ))
        for mode in ("shared", "decorrelated"):
            tb2 = reconstruction(scene, a, cal, gt, target, grey, mode)
            results["T-B2"][f"{pdf}/{mode}"] = tb2
            tables.append(print_table(
                f"T-B2 albedo RMSE after {a.recon_steps} steps, emitter pdf = {pdf}, grad_paths = {mode} "
                f"(initial RMSE {tb2['ReSTIR']['curve'][0]:.4f})",
                ["method", "RMSE", "seconds (total)", "RMSE / ReSTIR"],
                [[k, v["rmse"], v["seconds"], v["ratio_to_restir"]] for k, v in tb2.items()],
            ))
        if pdf == "uniform":
            tb4 = overhead(scene, a, grey, adjoint)
            results["T-B4"] = tb4
            stages = sorted(k for k in tb4["ReSTIR"] if k != "total")
            tables.append(print_table(
                f"T-B4 seconds per stage at {a.spp} spp (overhead of reuse over B.2: {tb4['overhead_pct']:.0f} %)",
                ["method", *stages, "total"],
                [[m, *[tb4[m].get(k, 0.0) for k in stages], tb4[m]["total"]] for m in ("B.2", "ReSTIR")],
            ))
    results["wall_seconds"] = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(results, indent=1))
    (out / "tables.md").write_text("\n\n".join(tables) + "\n")
    _plots(results, out)
    print(f"wrote {out}/results.json, tables.md and plots ({results['wall_seconds']:.0f} s)")


def _plots(results: dict, out: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(1, len(results["T-B1"]), figsize=(5 * len(results["T-B1"]), 3.5), squeeze=False)
    for ax, (pdf, tb1) in zip(axes[0], results["T-B1"].items()):
        labels = list(tb1)
        ax.bar(range(len(labels)), [tb1[k]["relerr"] for k in labels], yerr=[tb1[k]["relerr_sd"] for k in labels])
        ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=7)
        ax.set_ylabel("gradient relative error")
        ax.set_title(f"T-B1, emitter pdf {pdf}")
    fig.tight_layout()
    fig.savefig(out / "gradient_error.png", dpi=120)
    plt.close(fig)
    if results["T-B2"]:
        fig, axes = plt.subplots(2, len(results["T-B2"]), figsize=(5 * len(results["T-B2"]), 7), squeeze=False)
        for j, (mode, tb2) in enumerate(results["T-B2"].items()):
            for label, v in tb2.items():
                axes[0][j].plot(v["curve"], label=label)
                axes[1][j].plot(v["curve_t"], v["curve"], label=label)
            axes[0][j].set(xlabel="step", ylabel="albedo RMSE", title=f"T-B2 ({mode})", yscale="log")
            axes[1][j].set(xlabel="seconds", ylabel="albedo RMSE", yscale="log")
            axes[0][j].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "reconstruction.png", dpi=120)
        plt.close(fig)


if __name__ == "__main__":
    main()
