"""The papers' claims beside torchir's measurements, read from the suites' ``results.json``.

Each claim names the paper's number (or the project's goal where the paper gives none), how to
read torchir's figure from a suite's results, and the goal; the report shows them in one table
so a reader can compare them without opening every suite.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Claim:
    suite: str
    what: str
    paper: str
    goal: str
    measure: Callable[[dict[str, Any]], float]  # results.json -> torchir's figure
    met: Callable[[float], bool]
    unit: str = "x"


def _row(rows: list[dict], **match: Any) -> dict:
    return next(r for r in rows if all(r.get(k) == v for k, v in match.items()))


CLAIMS: list[Claim] = [
    Claim("adaptive", "gradient variance, uniform / adaptive (3% budget, initial θ)", "-", ">= 5x",
          lambda r: _row(r["a"]["rows"], method="adaptive", budget=0.03)["ratio_vs_uniform_all"], lambda v: v >= 5),
    Claim("adaptive", "gradient variance, Eq. 5 / adaptive (glossy roughness, Fig. 3)", "3.35x", "> 2x",
          lambda r: r["c"]["eq5_over_adaptive"], lambda v: v > 2),
    Claim("adaptive", "wall time to uniform's final parameter error, adaptive / uniform", "faster (plots only)", "<= 0.5x",
          lambda r: r["b"]["adaptive_time_ratio"], lambda v: v <= 0.5),
    Claim("denoiser", "image error, target-aware / none (albedo, 4 spp)", "1/7.3 = 0.14x", "<= 0.2x",
          lambda r: _denoiser_ratio(r, "albedo/spp4", "target_aware"), lambda v: v <= 0.2),
    Claim("denoiser", "image error, target-aware / cross-bilateral (albedo, 4 spp)", "< 1x", "<= 1x",
          lambda r: _denoiser_ratio(r, "albedo/spp4", "target_aware") / _denoiser_ratio(r, "albedo/spp4", "cross_bilateral"), lambda v: v <= 1),
    Claim("denoiser", "forward+backward at 256², r = 15 / one 16-spp render step", "-", "<= 0.25x",
          lambda r: _row(r["timing"], size=256, radius=15)["target_aware_ratio"], lambda v: v <= 0.25),
    Claim("loi", "B1 glossy highlight: LOI successes from 6 starts", "Envlight: ~10x lower error than GP", ">= 5 of 6",
          lambda r: r["summary"]["B1"]["loi"]["successes"], lambda v: v >= 5, unit=""),
    Claim("loi", "B1: L2 successes from 6 starts", "fails", "<= 2 of 6",
          lambda r: r["summary"]["B1"]["l2"]["successes"], lambda v: v <= 2, unit=""),
    Claim("loi", "B3 known-colour disks: LOI - GP mean PSNR (dB)", "Table 1: LOI best", ">= +2 dB",
          lambda r: r["summary"]["B3"][next(iter(r["summary"]["B3"]))]["loi"]["mean_psnr"] - r["summary"]["B3"][next(iter(r["summary"]["B3"]))]["gp"]["mean_psnr"],
          lambda v: v >= 2, unit=" dB"),
    Claim("loi", "LOI forward+backward at 256² / one 4-spp render step", "-", "<= 3x (project goal)",
          lambda r: r["cost"]["ratio_to_render"]["loi"], lambda v: v <= 3),
    Claim("loi", "LOI (default) gradient error vs exact LOI, 256² renders (largest of 3)", "-", "<= 1%",
          lambda r: 100 * r["cost"]["error_vs_exact_loi"]["loi"]["gradient_relative_error"], lambda v: v <= 1, unit="%"),
    Claim("loi", "LOI (alpha = 0 only: point CDFs, no aperture) / one 4-spp render step", "-", "bound for the 3x goal",
          lambda r: r["cost"]["ratio_to_render"]["sigma_w1"], lambda v: True),
    Claim("stepcost", "5% uniform pixel step / full-image step, 256², 1 spp, through the trainer", "-", "<= 0.2x",
          lambda r: _row(r["rows"], resolution=256, sampler="uniform", budget=0.05)["ratio_to_full"], lambda v: v <= 0.2),
    Claim("stepcost", "5% adaptive pixel step / full-image step, 256², 1 spp (Stage 1 amortised)", "-", "<= 0.2x",
          lambda r: _row(r["rows"], resolution=256, sampler="adaptive", budget=0.05)["ratio_to_full_amortised"], lambda v: v <= 0.2),
    Claim("stepcost", "5% uniform pixel step / full-image step, 512², 1 spp", "-", "-",
          lambda r: _row(r["rows"], resolution=512, sampler="uniform", budget=0.05)["ratio_to_full"], lambda v: v <= 0.2),
    *(claim for workload in ("cbox_512", "multiview_16") for claim in (
        Claim("scaleup", f"{workload}: time for adaptive 5% to reach the full render's final error (decayed lr), / its time",
              "faster (plots only)", "<= 0.5x", lambda r, w=workload: _scaleup_reach(r, w, "full render, decay"), lambda v: v <= 0.5),
        Claim("scaleup", f"{workload}: time for adaptive 5% to reach uniform 5%'s final error, / its time",
              "faster (plots only)", "<= 0.5x", lambda r, w=workload: _scaleup_reach(r, w, "uniform 5%, decay"), lambda v: v <= 0.5),
    )),
    *(claim for scene in ("ajar_painting", "many_lights") for claim in (
        Claim("restir", f"{scene}: gradient error, best baseline at equal time / ReSTIR (128²)", "up to 100x (GPU)", ">= 5x",
              lambda r, s=scene: _restir_row(r, s)["gain"], lambda v: v >= 5),
        Claim("restir", f"{scene}: ReSTIR gradient error / camera floor, equal samples", "-", "<= 1.3x",
              lambda r, s=scene: _restir_row(r, s)["relerr_equal_samples"] / _restir_row(r, s)["floor"], lambda v: v <= 1.3),
        Claim("restir", f"{scene}: reconstruction RMSE at equal wall time, best baseline / ReSTIR", "up to 20x (GPU)", ">= 3x",
              lambda r, s=scene: 1.0 / _restir_row(r, s)["recon_ratio_to_best_baseline"], lambda v: v >= 3),
    )),
    Claim("restir", "ReSTIR step / B.2 step, equal samples (ajar_painting, 128²)", "<= 1.2x (GPU)", "<= 2x",
          lambda r: _restir_row(r, "ajar_painting")["step_ratio_to_B.2"], lambda v: v <= 2),
    Claim("restir", "ReSTIR training step / plain (direct) training step (ajar_painting, 128²)", "-", "<= 3x",
          lambda r: _restir_row(r, "ajar_painting")["train_step_ratio_to_direct"], lambda v: v <= 3),
    Claim("restir_views", "multi-view: error² x time, per-sensor chains / carry-over store (burn-in 32)", "carry-over (Alg. 8)",
          "> 1x", lambda r: _views_efficiency(r, 32), lambda v: v > 1),
    Claim("restir_antithetic", "derivative image error at equal time, antithetic with independent / shared reservoirs (pig)",
          "lower (Fig. 8e vs 8d, images only)", ">= 3x",
          lambda r: _antithetic_ratio(r, "material, ReSTIR, antithetic"), lambda v: v >= 3),
    Claim("restir_antithetic", "derivative image error at equal time, no antithetic / antithetic with shared reservoirs (pig)",
          "lower (Fig. 8e vs 8c, images only)", ">= 10x",
          lambda r: _antithetic_ratio(r, "material, ReSTIR"), lambda v: v >= 10),
    Claim("soak", "largest memory growth after warm-up, any technique", "-", "< 5%",
          lambda r: 100 * max(t["memory_growth"] for t in r["runs"]), lambda v: v < 5, unit="%"),
    Claim("soak", "kernel-cache misses after warm-up, all techniques", "-", "0",
          lambda r: sum(t["cache_misses_after_warmup"] for t in r["runs"]), lambda v: v == 0, unit=""),
]


def _denoiser_ratio(r: dict, task: str, method: str) -> float:
    runs = [v for k, v in r["optimisation"].items() if k.startswith(task + "/")]
    ratios = sorted(run[method]["image_final"] / run["none"]["image_final"] for run in runs)
    return ratios[len(ratios) // 2]


def _views_efficiency(r: dict, burn_in: int) -> float:
    base, carry = (r["results"][f"{m} (burn-in {burn_in})"] for m in ("per-sensor", "carry-over"))
    return (base["rms_error"] ** 2 * base["seconds"]) / (carry["rms_error"] ** 2 * carry["seconds"])


def _scaleup_reach(r: dict, workload: str, reference: str) -> float:
    """The scaleup suite's median reach fraction of adaptive 5% against ``reference`` (NaN: never)."""
    row = next(x for x in r["summary"][workload] if x["config"] == "adaptive 5%, decay")
    value, hit, _ = row[f"reach {reference}"]
    return value if hit else float("inf")


def _antithetic_ratio(r: dict, method: str) -> float:
    """``method``'s equal-time error over shared-reservoir antithetic sampling's (restir_antithetic)."""
    errors = {name: row["equal_time_error"] for name, row in r["methods"].items()}
    return errors[method] / errors["material, ReSTIR, antithetic, shared"]


def _restir_row(r: dict, scene: str, method: str = "ReSTIR (shadowed)") -> dict:
    return r["scenes"][scene]["rows"][method]


def claims_table(out: Path) -> str:
    """Markdown table of every claim whose suite wrote results into ``out/<suite>/``."""
    lines = ["| suite | claim | paper | goal | torchir | met |", "|---|---|---|---|---|---|"]
    for claim in CLAIMS:
        path = out / claim.suite / "results.json"
        if not path.is_file():
            continue
        try:
            value = claim.measure(json.loads(path.read_text()))
            shown, met = f"{value:.3g}{claim.unit}", "yes" if claim.met(value) else "NO"
        except (KeyError, StopIteration, TypeError, ZeroDivisionError, IndexError, ValueError):
            shown, met = "not measured", "-"
        lines.append(f"| {claim.suite} | {claim.what} | {claim.paper} | {claim.goal} | {shown} | {met} |")
    return "\n".join(lines) if len(lines) > 2 else ""
