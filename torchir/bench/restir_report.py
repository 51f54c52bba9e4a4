"""``torchir bench restir``'s analysis and report: equal-time interpolation, the camera-sampling
floor, one summary row per method, the Markdown tables and the plots."""
from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ._common import fmt, markdown_table, median

DEFAULT_SCENES = ("ajar_painting", "many_lights", "oxalis_lite")
BASELINES = ("direct", "B.1", "B.2")
AUTO = "ReSTIR (auto)"  # preset="auto": the sampler probes the scene and picks its own settings
ALL_RESTIRS = ("ReSTIR (shadowed)", "ReSTIR (unshadowed)", "ReSTIR (persistent)", AUTO)
DEFAULT_RESTIRS = ("shadowed", "unshadowed", "persistent")  # --restirs without the option
METHODS = (*BASELINES, *ALL_RESTIRS)  # every method; a run's own are ``a.methods`` (--restirs)
VARIANTS = {m[len("ReSTIR ("):-1]: m for m in ALL_RESTIRS}  # "shadowed" -> "ReSTIR (shadowed)"


def restir_variants(names: Sequence[str]) -> tuple[str, ...]:
    """The ReSTIR methods named ``names`` ("shadowed", "unshadowed", "persistent", "auto"), in
    table order. The slowest of a run's variants sets the equal-time budget, so one variant alone
    is compared at its own cost."""
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or not names:
        raise ValueError(f"--restirs takes some of {', '.join(VARIANTS)}; got {','.join(names)}")
    chosen = {VARIANTS[n] for n in names}
    return tuple(m for m in ALL_RESTIRS if m in chosen)


def methods_in(methods: Any) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(methods, ReSTIR variants)`` present in ``methods`` (method names, e.g. a summary's
    rows or a list of runs' methods), in table order: the baselines, then the variants run."""
    present = set(methods)
    restirs = tuple(m for m in ALL_RESTIRS if m in present)
    return (*BASELINES, *restirs), restirs
ORACLE = "floor (oracle)"  # RIS over the larger --oracle-candidates count
ORACLE_LOW = "oracle (fewer candidates)"  # the smaller count: with ORACLE, extrapolates the floor
REFERENCE_BATCHES = 16  # the reference gradient's batches: their spread gives its own error
STAGES = ("pass", "ris", "nn", "combine", "develop", "backward")  # "pass": a frozen (dr.freeze) pass has one timer
def error_beyond_reference(errors: Sequence[float], ref_se: float) -> tuple[float, float]:
    """RMS over steps of relative errors measured against a reference of relative standard
    error ``ref_se``, that error removed in quadrature (squared errors add): ``(rms, s.e. of
    the mean square)``; the s.e. is 0 for a single step."""
    squares = [e * e - ref_se * ref_se for e in errors]
    se = statistics.stdev(squares) / math.sqrt(len(squares)) if len(squares) > 1 else 0.0
    return math.sqrt(max(statistics.fmean(squares), 0.0)), se


def camera_floor(e_low: float | None, m_low: int | None, e_high: float, m_high: int) -> float:
    """The error left with perfect light sampling: ``e(M)² = floor² + L / M`` for RIS over M
    independent candidates (light variance falls as 1/M), solved from two oracles; with one
    oracle, its error (an upper bound: at 256 candidates B.2 over 8 can look at most
    sqrt(256 / 8) = 5.7x worse however hard the lighting)."""
    if e_low is None or m_low is None:
        return e_high
    floor_sq = (m_high * e_high**2 - m_low * e_low**2) / (m_high - m_low)
    return math.sqrt(max(floor_sq, 0.0))


def equal_time_estimate(probes: list[dict[str, float]], budget: float, spp: int, max_spp: int) -> float:
    """The (fractional) spp whose charged seconds per step meet ``budget``, within [spp, max_spp]:
    linear interpolation between the probes that bracket the budget, else the secant through the
    two probes nearest to it (step time is not proportional to spp: fixed costs per step, frozen
    kernels that change with the lane count), else proportional from the nearest probe."""
    if probes[0]["charged"] >= budget:
        return float(spp)
    below = [q for q in probes if q["charged"] < budget]
    above = [q for q in probes if q["charged"] >= budget]
    near = min(probes, key=lambda q: abs(q["charged"] - budget))
    estimate = near["spp"] * budget / near["charged"]
    if below and above:
        lo, hi = max(below, key=lambda q: q["spp"]), min(above, key=lambda q: q["spp"])
        pair = (lo, hi) if hi["spp"] > lo["spp"] else None
    else:
        ranked = sorted(probes, key=lambda q: abs(q["charged"] - budget))[:2]
        pair = tuple(sorted(ranked, key=lambda q: q["spp"])) if len(ranked) == 2 else None
    if pair is not None and pair[1]["spp"] > pair[0]["spp"] and pair[1]["charged"] > pair[0]["charged"]:
        lo, hi = pair
        estimate = lo["spp"] + (budget - lo["charged"]) * (hi["spp"] - lo["spp"]) / (hi["charged"] - lo["charged"])
    return float(min(max_spp, max(spp, estimate)))


def equal_time_spp(probes: list[dict[str, float]], budget: float, spp: int, max_spp: int) -> int:
    """:func:`equal_time_estimate` rounded to a whole spp."""
    return int(round(equal_time_estimate(probes, budget, spp, max_spp)))


def bracketing_spps(estimate: float, spp: int, max_spp: int) -> tuple[int, ...]:
    """The whole spps around a fractional equal-time ``estimate`` (one when it is whole or at a limit)."""
    lo = min(max_spp, max(spp, math.floor(estimate)))
    hi = min(max_spp, max(spp, math.ceil(estimate)))
    return (lo,) if lo == hi else (lo, hi)


def equal_time_error(points: Sequence[tuple[float, float]], budget: float) -> float:
    """A method's gradient error at exactly ``budget`` charged seconds per step, from its runs
    ``points`` = ``[(charged seconds per step, relerr)]`` at whole spps. ``1 / e²`` (the
    effective sample count) is linear in time when the variance falls as 1/spp and the step
    time is affine in spp, so it is interpolated linearly between the runs that bracket the
    budget. A budget below every run's time gives the fastest run's error (the method had more
    time: the comparison favours it); above every run's, ``1 / e²`` is extended along the last
    two runs' line, or proportionally to time from the last run."""
    pts = sorted((t, e) for t, e in points if e > 0)
    if not pts:
        return 0.0
    if budget <= pts[0][0]:
        return pts[0][1]
    inv = [(t, 1.0 / (e * e)) for t, e in pts]
    for (t0, v0), (t1, v1) in zip(inv, inv[1:]):
        if t0 <= budget <= t1 and t1 > t0:
            return (v0 + (budget - t0) * (v1 - v0) / (t1 - t0)) ** -0.5
    t1, v1 = inv[-1]
    if len(inv) > 1:
        t0, v0 = inv[-2]
        if t1 > t0 and v1 > v0:
            return (v1 + (budget - t1) * (v1 - v0) / (t1 - t0)) ** -0.5
    return (v1 * budget / t1) ** -0.5


def error_at_spp(points: Sequence[tuple[float, float]], spp: float) -> float:
    """A method's gradient error at a fractional ``spp`` from its runs ``points`` = ``[(spp,
    relerr)]`` at whole spps: ``1 / e²`` (the effective sample count) is linear in spp (the
    variance falls as 1/spp), so it is interpolated between the runs that bracket ``spp``, or
    extended proportionally from the nearest run. Unlike :func:`equal_time_error` it does not
    read the gradient runs' own step times, which two runs at nearby spps can measure in the
    wrong order on a loaded machine; the time enters only through ``spp`` (the calibration's)."""
    pts = sorted((float(n), e) for n, e in points if e > 0 and n > 0)
    if not pts:
        return 0.0
    inv = [(n, 1.0 / (e * e)) for n, e in pts]
    for (n0, v0), (n1, v1) in zip(inv, inv[1:]):
        if n0 <= spp <= n1:
            return (v0 + (spp - n0) * (v1 - v0) / (n1 - n0)) ** -0.5
    n, v = inv[0] if spp < inv[0][0] else inv[-1]
    return (v * spp / n) ** -0.5


# ----------------------------------------------------------------------------- summary
def summarize_scene(runs: list[dict[str, Any]], spp: int, spp_eq: dict[str, int],
                    recon: dict[str, list[dict[str, Any]]] | None = None,
                    oracle_candidates: tuple[int | None, int] = (None, 256), budget: float | None = None,
                    spp_exact: dict[str, float] | None = None) -> dict[str, Any]:
    """One row per method (and the floor oracle) from the gradient runs and training runs.

    Row fields: ``relerr_equal_samples``, ``floor`` (the oracle at ``spp``), ``light``
    (``sqrt(max(e² − floor², 0))``), ``relerr_equal_time``, ``spp_equal_time``,
    ``seconds_equal_time`` (charged), ``relerr_equal_time_measured`` (the run at
    ``spp_equal_time``); with ``budget`` (the equal-time seconds per step) a baseline's
    ``relerr_equal_time`` is its error at exactly the budget (:func:`equal_time_error` over its
    runs: whole spps round the budget either way, which can favour either side by up to one
    spp) and its ``seconds_equal_time`` the budget; with ``spp_exact`` too (the calibration's
    fractional equal-time spp per method) the error is read at that spp instead
    (:func:`error_at_spp`: the runs' variance is exactly linear in spp, their step times are
    noisy); ``floor_equal_time`` (the oracle at that spp, where
    measured), ``gain`` (best baseline's equal-time error / this one's), ``bound`` (best
    baseline's equal-time error / ``floor_equal_time``), ``seconds_per_step``,
    ``burn_in_seconds``, ``charged_seconds_per_step``, ``stages`` and ``step_ratio_to_B.2`` at
    equal samples. ``recon``: ``{grad_paths mode: training runs}``; per mode
    ``reconstruction_summary[mode]`` gives per method ``recon_rmse`` (median over seeds),
    ``recon_initial_rmse``, ``recon_steps``, ``recon_seconds``, ``train_step_seconds`` (median
    step after the first), ``train_step_ratio_to_direct`` and ``recon_ratio_to_best_baseline``
    (RMSE / the best baseline's), and the rows carry the first mode's (``recon_grad_paths``).
    Also returns ``best_baseline`` (equal time) and ``best_recon_baseline`` (first mode)."""
    by = {(r["method"], r["spp"]): r for r in runs}
    methods, restirs = methods_in(r["method"] for r in runs)
    m_low, m_high = oracle_candidates
    floors = {
        s: camera_floor(by[(ORACLE_LOW, s)]["relerr"] if (ORACLE_LOW, s) in by else None, m_low, r["relerr"], m_high)
        for (m, s), r in by.items() if m == ORACLE
    }
    floor = floors[spp]
    rows: dict[str, dict[str, Any]] = {}
    for m in methods:
        eqs, eqt = by[(m, spp)], by[(m, spp_eq[m])]
        e = eqs["relerr"]
        e_eqt, t_eqt = eqt["relerr"], eqt["charged_seconds_per_step"]
        if budget is not None and m in BASELINES:
            if spp_exact and m in spp_exact:
                e_eqt = error_at_spp([(r["spp"], r["relerr"]) for (mm, _), r in by.items() if mm == m], spp_exact[m])
            else:
                e_eqt = equal_time_error([(r["charged_seconds_per_step"], r["relerr"]) for (mm, _), r in by.items() if mm == m], budget)
            t_eqt = budget
        rows[m] = {
            "relerr_equal_samples": e, "floor": floor, "light": math.sqrt(max(e * e - floor * floor, 0.0)),
            "relerr_equal_time": e_eqt, "relerr_equal_time_measured": eqt["relerr"], "spp_equal_time": spp_eq[m],
            "seconds_equal_time": t_eqt,
            "floor_equal_time": floors.get(spp_eq[m]) if m in restirs else None,
            "seconds_per_step": eqs["seconds_per_step"], "burn_in_seconds": eqs["burn_in_seconds"],
            "charged_seconds_per_step": eqs["charged_seconds_per_step"], "stages": eqs["stages"],
        }
    best = min(BASELINES, key=lambda m: rows[m]["relerr_equal_time"])
    e_best = rows[best]["relerr_equal_time"]
    for m, row in rows.items():
        row["gain"] = e_best / row["relerr_equal_time"] if row["relerr_equal_time"] > 0 else float("inf")
        row["bound"] = e_best / row["floor_equal_time"] if row["floor_equal_time"] else None
        row["step_ratio_to_B.2"] = row["seconds_per_step"] / rows["B.2"]["seconds_per_step"]
        row["charged_step_ratio_to_B.2"] = row["charged_seconds_per_step"] / rows["B.2"]["seconds_per_step"]
    oracle = by[(ORACLE, spp)]
    rows[ORACLE] = {"relerr_equal_samples": floor, "floor": floor, "light": 0.0, "relerr_equal_time": None, "relerr_equal_time_measured": None,
                    "spp_equal_time": None, "seconds_equal_time": None, "floor_equal_time": None, "gain": None, "bound": None,
                    "seconds_per_step": oracle["seconds_per_step"], "burn_in_seconds": 0.0,
                    "charged_seconds_per_step": oracle["charged_seconds_per_step"], "stages": oracle["stages"],
                    "step_ratio_to_B.2": oracle["seconds_per_step"] / rows["B.2"]["seconds_per_step"],
                    "charged_step_ratio_to_B.2": oracle["charged_seconds_per_step"] / rows["B.2"]["seconds_per_step"]}
    rows[ORACLE]["oracle_errors"] = {str(m_high): oracle["relerr"]}
    if (ORACLE_LOW, spp) in by:
        rows[ORACLE]["oracle_errors"][str(m_low)] = by[(ORACLE_LOW, spp)]["relerr"]
    out: dict[str, Any] = {"rows": rows, "best_baseline": best, "floors": {str(s): f for s, f in sorted(floors.items())}}
    if recon:
        out["reconstruction_summary"] = {}
        for mode, mode_runs in recon.items():
            summary = {}
            for m in methods:
                mine = [r for r in mode_runs if r["method"] == m]
                summary[m] = {
                    "recon_rmse": median([r["final_param_error"] for r in mine]),
                    "recon_initial_rmse": median([r["param_error"][0] for r in mine]),
                    "recon_steps": median([float(r["steps"]) for r in mine]),
                    "recon_seconds": median([r["train_seconds"] for r in mine]),
                    "train_step_seconds": median([median(r["step_seconds"][1:] or r["step_seconds"]) for r in mine]),
                }
            best_recon = min(BASELINES, key=lambda m: summary[m]["recon_rmse"])
            for m in methods:
                summary[m]["train_step_ratio_to_direct"] = summary[m]["train_step_seconds"] / summary["direct"]["train_step_seconds"]
                summary[m]["recon_ratio_to_best_baseline"] = summary[m]["recon_rmse"] / summary[best_recon]["recon_rmse"]
            out["reconstruction_summary"][mode] = {"best_baseline": best_recon, "rows": summary}
            oracle = [r for r in mode_runs if r["method"] == ORACLE]
            if oracle:  # the floor oracle trained for the budget's steps, its time not charged
                floor = median([r["final_param_error"] for r in oracle])
                out["reconstruction_summary"][mode].update(
                    floor_rmse=floor, floor_steps=median([float(r["steps"]) for r in oracle]),
                    bound=summary[best_recon]["recon_rmse"] / floor if floor > 0 else None)
        primary = next(iter(recon))
        for m in methods:
            rows[m].update(out["reconstruction_summary"][primary]["rows"][m], recon_grad_paths=primary)
        out["best_recon_baseline"] = out["reconstruction_summary"][primary]["best_baseline"]
    return out


def file_stem(scene: str) -> str:
    """A scene's name in file names (a held-out spec's ``:`` become ``_``)."""
    return scene.replace(":", "_")


def _heldout_line(scene: dict[str, Any]) -> list[str]:
    """The note under a held-out scene's heading (none for a built-in scene)."""
    h = scene.get("heldout")
    if not h:
        return []
    kind = "light-bound" if h["light_bound"] else "not light-bound: reuse has little to gain and must not lose"
    return [f"Held-out scene (family {h['family']}, seed {h['seed']}: no setting was tuned against it; {kind}).", ""]


def _oracle_counts(cfg: dict[str, Any]) -> str:
    low = cfg.get("oracle_low")
    return f"{low} and {cfg['oracle_candidates']}" if low else str(cfg["oracle_candidates"])


def gain_text(row: dict[str, Any], best: str, method: str) -> str:
    """``"gain 3.1x of possible 8.2x"`` (bound where the floor at that spp was measured)."""
    if row.get("gain") is None:
        return "-"
    def x(v: float) -> str:  # two significant digits, no exponent
        return f"{v:.2g}x" if v < 100 else f"{v:.0f}x"

    text = x(row["gain"]) + (" (best)" if method == best else "")
    if row.get("bound") is not None:
        text = f"gain {x(row['gain'])} of possible {x(row['bound'])}"
    return text


def _chain_options(cfg: dict[str, Any]) -> str:
    """The persistent chains' own options, where given (older results have none)."""
    parts = [f"{label} {cfg[key]}" for key, label in (("chain_candidates", "chains' M"), ("chain_cap", "chain cap"),
                                                      ("light_guide", "light guide")) if cfg.get(key)]
    return "".join(part + ", " for part in parts)


def tables(results: dict[str, Any]) -> str:
    """The suite's Markdown: per scene the method table and the per-stage costs, then the
    overview across scenes."""
    cfg = results["config"]
    spp = cfg["spp"]
    lines = [
        f"### ReSTIR benchmark ({cfg['resolution']}², {spp} spp, M = {cfg['candidates']}, burn-in {cfg['burn_in']}, "
        f"{_chain_options(cfg)}"
        f"floor oracle: RIS over {_oracle_counts(cfg)} shadowed candidates, no reuse)",
        "",
        (f"Gradient error: RMS over {cfg['grad_steps']} steps of ||g − g_ref|| / ||g_ref|| at the grey texture (fixed L2 adjoint; "
         f"g_ref: prb at {cfg['ref_spp']} spp; its own error, measured from {REFERENCE_BATCHES} batches, is removed in quadrature). "
         "Floor: the camera-sampling floor, from the oracles at the same seeds and spp (same camera rays), extrapolated to "
         "infinitely many candidates with e² = floor² + L/M (one oracle: its error, a bound that caps at sqrt(M_oracle / M)); light part = "
         "sqrt(max(e² − floor², 0)). Equal time: every method's spp raised to the seconds per step of the slower ReSTIR variant "
         "at equal samples, burn-in charged over the gradient steps; a baseline's equal-time error is read at exactly that budget "
         "from its runs at the whole spps on either side (1/e², the effective sample count, linear in time; its spp column gives "
         "the nearer whole spp); gain = the best baseline's equal-time error / the method's (best of direct, B.1 and B.2: "
         "no reuse, unbiased gradients); "
         "'of possible' = the best baseline's error / the floor under the method (the most any light sampler can gain). "
         f"Reconstruction: the trainer, Adam lr {cfg['lr']}, L2, {spp} spp for every method, the slower ReSTIR's wall time "
         f"for {cfg['recon_steps']} steps (burn-in included) for all; texture RMSE after it, median of {cfg['recon_seeds']} seed(s)"
         + (f", targets rendered at {cfg['target_spp']} spp by the scene's own integrator (their noise is the RMSE every fit "
            "stalls at); " if cfg.get("target_spp") else "; ")
         + f"the samplers' gradient paths: {', '.join(cfg['grad_paths'])} (the main table, gradient error included: "
         f"{cfg['grad_paths'][0]}; shared paths correlate the image and its gradient, a bias of the L2 loss that grows with "
         "the image noise; decorrelated paths cost a second resampling pass a step; direct (prb) always uses "
         "decorrelated paths)."),
    ]
    overview = []
    for name, scene in results["scenes"].items():
        rows, best = scene["rows"], scene["best_baseline"]
        methods, restirs = methods_in(rows)
        recon = "recon_rmse" in rows[methods[0]]
        ref = scene["reference"]
        lines += ["", f"#### {name}", "", *_heldout_line(scene),
                  (f"Floor at {spp} spp: {fmt(rows[ORACLE]['floor'])} (oracle errors: "
                   + ", ".join(f"{m} candidates {fmt(e)}" for m, e in sorted(rows[ORACLE].get("oracle_errors", {}).items(), key=lambda kv: int(kv[0])))
                   + f"); reference relative SE {fmt(ref['relative_se'])} (removed from "
                   f"every error, in quadrature); best baseline at equal time: {best}; equal-time budget "
                   f"{fmt(scene['calibration']['budget_seconds'])} s/step ({scene['calibration']['budget_method']})."
                   + (" Warning: the reference's noise is over a third of the floor: raise --ref-spp." if ref["relative_se"] > rows[ORACLE]["floor"] / 3 else "")),
                  ""]
        header = ["method", f"relerr ({spp} spp)", "floor", "light part", "relerr eq. time", "spp eq. time", "s/step eq. time (burn-in charged)",
                  "gain vs best baseline (eq. time)"]
        if recon:
            header += [f"recon RMSE (eq. wall time, {rows[methods[0]]['recon_grad_paths']})", "recon steps", "x best baseline's RMSE"]
        header += [f"s/step ({spp} spp)", "x B.2 step"]
        if recon:
            header += ["train s/step", "x direct train step"]
        body = []
        for m in (*methods, ORACLE):
            r = rows[m]
            line = [m, r["relerr_equal_samples"], r["floor"], r["light"], r["relerr_equal_time"], r["spp_equal_time"],
                    r["seconds_equal_time"], gain_text(r, best, m)]
            if recon:
                line += [r["recon_rmse"], r["recon_steps"], r["recon_ratio_to_best_baseline"]] if m != ORACLE else [None] * 3
            line += [r["seconds_per_step"], r["step_ratio_to_B.2"]]
            if recon:
                line += [r.get("train_step_seconds"), r.get("train_step_ratio_to_direct")] if m != ORACLE else [None, None]
            body.append(line)
        lines += markdown_table(header, body)
        extra = scene.get("unfrozen_stages") or {}
        stage_rows = [(m, rows[m]) for m in (*methods, ORACLE)] + list(extra.items())
        present = [st for st in STAGES if any(st in r["stages"] for _, r in stage_rows)]
        lines += ["", f"Cost per stage at {spp} spp (seconds per step: median of gradient steps 2..{cfg['grad_steps']}, "
                  "without the burn-in, which is given once; stages: medians of the integrator's timers (pass: a frozen "
                  "resampling pass, replayed by dr.freeze, has one timer; the rows marked unfrozen show where its time goes "
                  "when traced); other: the rest of the step, e.g. the torch/Dr.Jit boundary):", ""]
        lines += markdown_table(["method", "s/step", "burn-in (once)", *present, "other", "x B.2 step"],
                        [[m, r["seconds_per_step"], r.get("burn_in_seconds") if m in restirs else None,
                          *[r["stages"].get(st) for st in present], r["stages"].get("other"),
                          r["seconds_per_step"] / rows["B.2"]["seconds_per_step"]] for m, r in stage_rows])
        modes = scene.get("reconstruction_summary") or {}
        if len(modes) > 1:
            lines += ["", "Reconstruction by the samplers' gradient paths (texture RMSE after the equal wall time; steps; "
                      "x the best baseline's RMSE in that mode):", ""]
            lines += markdown_table(["method", *[f"{mode}: RMSE (steps)" for mode in modes], *[f"{mode}: x best baseline" for mode in modes],
                             *[f"{mode}: train s/step" for mode in modes]],
                            [[m, *[f"{fmt(v['rows'][m]['recon_rmse'])} ({fmt(v['rows'][m]['recon_steps'])})" for v in modes.values()],
                              *[v["rows"][m]["recon_ratio_to_best_baseline"] for v in modes.values()],
                              *[v["rows"][m]["train_step_seconds"] for v in modes.values()]] for m in methods])
        primary = next(iter(modes.values()), {})
        if primary.get("bound") is not None:
            lines += ["", f"Reconstruction bound: the floor oracle ({_oracle_counts(cfg).split(' and ')[-1]} candidates, no reuse) "
                      f"trained {fmt(primary['floor_steps'])} steps (the budget's ReSTIR's), its time not charged, reached RMSE "
                      f"{fmt(primary['floor_rmse'])}: no light sampler gains more than {fmt(primary['bound'])}x over the best "
                      f"baseline ({primary['best_baseline']}) in this run."]
        for m in restirs:
            overview.append([name, m, rows[ORACLE]["floor"], rows[m]["relerr_equal_samples"], rows["B.2"]["relerr_equal_samples"],
                             f"{best} {fmt(rows[best]['relerr_equal_time'])}", gain_text(rows[m], best, m),
                             1.0 / rows[m]["recon_ratio_to_best_baseline"] if recon else None, primary.get("bound"),
                             rows[m]["step_ratio_to_B.2"], rows[m].get("train_step_ratio_to_direct")])
    lines += ["", "#### Overview", ""]
    lines += markdown_table(["scene", "method", f"floor ({spp} spp)", f"relerr ({spp} spp)", f"B.2 ({spp} spp)", "best baseline eq. time",
                     "gain (eq. time)", "recon: best baseline RMSE / method's", "recon bound (oracle)", "step / B.2 step",
                     "train step / direct train step"], overview)
    if results.get("skipped_scenes"):
        lines += ["", f"Default scenes not run: {', '.join(results['skipped_scenes'])}."]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------- plots
def plot_results(results: dict[str, Any], out: Path) -> list[Path]:
    """``gradient_<scene>.png``: gradient error against seconds per step (each method at equal
    samples and equal time, joined; the floor oracle as crosses, the floor at ``--spp`` dotted);
    ``reconstruction_<scene>.png``: texture RMSE against training wall time."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    colours = {m: plt.get_cmap("tab10")(i) for i, m in enumerate(METHODS)}
    written = []
    for name, scene in results["scenes"].items():
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for m in methods_in(scene["rows"])[0]:
            pts = sorted((r["charged_seconds_per_step"], r["relerr"], r["spp"]) for r in scene["gradient_runs"] if r["method"] == m)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=colours[m], label=m)
            for x, y, s in pts:
                ax.annotate(f"{s}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
        oracle = [(r["charged_seconds_per_step"], r["relerr"], r["spp"]) for r in scene["gradient_runs"] if r["method"] == ORACLE]
        ax.plot([p[0] for p in oracle], [p[1] for p in oracle], "kx", markersize=8, label=f"{ORACLE}; dotted: at {results['config']['spp']} spp")
        for x, y, s in oracle:
            ax.annotate(f"{s}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
        ax.axhline(scene["rows"][ORACLE]["floor"], color="k", linestyle=":", linewidth=1)
        ax.set(xscale="log", yscale="log", xlabel="seconds per step (ReSTIR: burn-in charged)", ylabel="gradient relative error (RMS)",
               title=f"{name}: gradient error vs cost (labels: spp)")
        ax.legend(fontsize=7)
        fig.tight_layout()
        path = out / f"gradient_{file_stem(name)}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
        modes = scene.get("reconstruction") or {}
        if modes:
            fig, axes = plt.subplots(1, len(modes), figsize=(6.5 * len(modes), 4.5), squeeze=False)
            for ax, (mode, runs) in zip(axes[0], modes.items()):
                for r in runs:
                    oracle = r["method"] == ORACLE  # its time not charged: drawn against the budget's ReSTIR's steps
                    ax.plot(r["elapsed"], r["param_error"], color="k" if oracle else colours[r["method"]], alpha=0.85,
                            linestyle=":" if oracle else "-",
                            label=(f"{r['method']} (time not charged)" if oracle else r["method"]) if r["seed"] == 0 else None)
                ax.set(yscale="log", xlabel="training wall time (s)", ylabel="texture RMSE",
                       title=f"{name}: reconstruction vs wall time ({mode} paths)")
                ax.legend(fontsize=7)
            fig.tight_layout()
            path = out / f"reconstruction_{file_stem(name)}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    return written


# ----------------------------------------------------------------------------------- main
