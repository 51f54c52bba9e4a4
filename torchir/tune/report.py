"""What ``torchir tune`` writes: one row per setting (its trials merged), the Markdown table,
and the Pareto plot of the window error (:func:`~torchir.tune.search.window_error`) against seconds per step."""
from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any, Optional

from ..bench._common import markdown_table
from .search import OPTIMISER_WINDOW, pareto_front, row_window_error
from .space import Setting

__all__ = ["setting_rows", "table", "plot_pareto"]

METRIC_NAMES = {"param_error": "param RMSE", "image_error": "image MSE"}


def setting_rows(trials: list[dict[str, Any]], settings: dict[str, Setting], budget_seconds: Optional[float],
                 chosen: Optional[Setting]) -> list[dict[str, Any]]:
    """One row per setting, in the order first measured: its longest gradient trial (seconds per
    step, gradient error, its persistent part, and the window error over :data:`OPTIMISER_WINDOW`
    steps of ``budget_seconds``, the config's own step), its training run (error decrease per
    second), whether it is on the Pareto front and whether it was chosen."""
    rows: dict[str, dict[str, Any]] = {}
    for trial in trials:
        key = trial["key"]
        row = rows.setdefault(key, {"setting": trial["setting"], "key": key, "gradient_scored": settings[key].gradient_scored,
                                    "status": trial.get("status"), "note": ""})
        if trial.get("status") != "ran":
            if not row.get("ran"):
                row.update(status=trial.get("status"), note=trial.get("error", ""))
            continue
        row["ran"], row["status"], row["note"] = True, "ran", ""
        if trial["kind"] == "gradient" and trial["steps"] >= row.get("steps", 0):
            row.update(steps=trial["steps"], seconds_per_step=trial["seconds_per_step"], gradient_error=trial["gradient_error"],
                       persistent_error=trial.get("persistent_error"), step_spread=trial.get("step_spread"))
        elif trial["kind"] == "training":
            row.update(decrease_per_second=trial["decrease_per_second"], metric=trial["metric"],
                       training_steps=trial["steps"])
            gaps = [b - a for a, b in zip(trial["times"], trial["times"][1:])]
            if "seconds_per_step" not in row and gaps:
                row["seconds_per_step"] = statistics.median(gaps)
    out = list(rows.values())
    for row in out:
        if "gradient_error" in row and budget_seconds:
            row["window_error"] = row_window_error(row, OPTIMISER_WINDOW * budget_seconds)
    scored = [r for r in out if "window_error" in r]
    for row, front in zip(scored, pareto_front([(r["seconds_per_step"], r["window_error"]) for r in scored])):
        row["pareto"] = front
    for row in out:
        row["chosen"] = chosen is not None and row["key"] == chosen.key
    return out


def table(rows: list[dict[str, Any]]) -> list[str]:
    """The Markdown table of :func:`setting_rows` (best window error first)."""
    metrics = {r["metric"] for r in rows if "metric" in r}
    metric = METRIC_NAMES.get(next(iter(metrics)), "error") if len(metrics) == 1 else "error"
    order = sorted(rows, key=lambda r: (r.get("window_error", math.inf), -(r.get("decrease_per_second") or -math.inf)))
    longest = max((r.get("steps", 0) for r in rows), default=0)
    body = []
    for r in order:
        screened = r.get("steps", longest) < longest
        mark = ", ".join(w for w, on in (("chosen", r["chosen"]), ("Pareto", r.get("pareto")), ("screened only", screened)) if on)
        if r["status"] != "ran":
            mark = f"{r['status']}: {r['note']}"
        elif not r["gradient_scored"]:
            mark = ", ".join(filter(None, [mark, "changes the loss: training score only"]))
        body.append([("**" + r["setting"] + "**") if r["chosen"] else r["setting"], r.get("seconds_per_step"), r.get("steps"),
                     r.get("gradient_error"), r.get("persistent_error"), r.get("window_error"), r.get("decrease_per_second"), mark])
    return markdown_table(["setting", "s/step", "gradient steps", "gradient error", "persistent", "window error",
                           f"{metric} decrease/s", "note"], body)


def plot_pareto(rows: list[dict[str, Any]], path: Path, title: str) -> Optional[Path]:
    """The window error against seconds per step, every scored setting, the Pareto
    front joined and the chosen setting starred; ``None`` when nothing was scored."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scored = [r for r in rows if "window_error" in r and r["window_error"] > 0]
    if not scored:
        return None
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.scatter([r["seconds_per_step"] for r in scored], [r["window_error"] for r in scored], color="tab:blue", s=24,
               alpha=0.7, label="setting")
    front = sorted((r for r in scored if r.get("pareto")), key=lambda r: r["seconds_per_step"])
    ax.plot([r["seconds_per_step"] for r in front], [r["window_error"] for r in front], "o-", color="tab:red",
            label="Pareto front")
    for r in front:
        ax.annotate(r["setting"], (r["seconds_per_step"], r["window_error"]), fontsize=7, xytext=(4, 4),
                    textcoords="offset points")
    for r in scored:
        if r["chosen"]:
            ax.scatter([r["seconds_per_step"]], [r["window_error"]], marker="*", s=260, color="gold",
                       edgecolors="black", zorder=5, label=f"chosen: {r['setting']}")
    ax.set(xscale="log", yscale="log", xlabel="seconds per step", ylabel="window error (gradient averaged over the optimiser's window)", title=title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
