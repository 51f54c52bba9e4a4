"""The documentation's page of measured results, generated from the benchmarks' own output.

A run kept for the docs is a suite's output folder copied under ``docs/results/<name>/``
(``results.json``, ``summary.md``, plots). :func:`results_page` turns the folders into one
Markdown page: per run, where and how it was measured (the ``environment`` record in its
``results.json``: command, commit, machine, versions), its tables, and its plots. Where the
suite defines ``summary(results) -> str``, the tables are rebuilt from ``results.json`` by that
function (so the page is the JSON's, whatever ``summary.md`` says); otherwise ``summary.md``,
which the suite wrote from the same results, is included. The docs build writes the page
(``docs/conf.py``), as does ``python -m torchir.bench.pages``; it is kept in the repository (a
test checks it is current), so each figure lives in one place: the run's JSON.
"""
from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

from . import SUITES

__all__ = ["results_page", "measured_on"]

TITLE = "# Measured results"
INTRO = ("Generated (by the docs build, or `python -m torchir.bench.pages`) from the benchmark runs kept under "
         "`docs/results/` (each a suite's output folder: `results.json`, `summary.md`, plots). To add or refresh one: "
         "`torchir bench SUITE [options] --out /tmp/run`, then copy `/tmp/run/SUITE` to `docs/results/NAME/`.")


def measured_on(environment: dict[str, Any]) -> str:
    """One line: the command, commit and date of a run, and the machine and versions it ran on."""
    parts = []
    if environment.get("command"):
        parts.append(f"`{environment['command']}`")
    if environment.get("commit"):
        parts.append(f"commit {environment['commit'][:7]}")
    if environment.get("date"):
        parts.append(environment["date"])
    machine = [environment.get(k) for k in ("torchir_backend", "platform")]
    if environment.get("cpu_count"):
        machine.append(f"{environment['cpu_count']} CPUs")
    parts.append(", ".join(str(m) for m in machine if m))
    return "Measured: " + "; ".join(p for p in parts if p) + "."


def _suite_of(folder: Path, results: dict[str, Any]) -> str | None:
    name = results.get("environment", {}).get("suite") or folder.name.split("-")[0]
    return name if name in SUITES else None


def _tables(folder: Path, results: dict[str, Any]) -> str:
    suite = _suite_of(folder, results)
    if suite is not None:
        summary = getattr(importlib.import_module(SUITES[suite]), "summary", None)
        if callable(summary):
            return summary(results).strip()
    path = folder / "summary.md"
    return path.read_text().strip() if path.exists() else "(this run kept no tables)"


def _demote(markdown: str) -> str:
    """Headings one level down (a run's ``##`` sits under the page's ``##`` of the run)."""
    return "\n".join("#" + line if line.startswith("#") else line for line in markdown.splitlines())


def results_page(root: Path, link_base: str = "results") -> str:
    """The Markdown page of every run folder under ``root`` (sorted by name); plots are linked
    as ``link_base/<run>/<file>``."""
    lines = [TITLE, "", INTRO, ""]
    folders = sorted(p for p in root.iterdir() if (p / "results.json").exists()) if root.exists() else []
    if not folders:
        lines += ["No runs are kept yet.", ""]
    for folder in folders:
        results = json.loads((folder / "results.json").read_text())
        lines += [f"## {folder.name}", "", measured_on(results.get("environment", {})), "",
                  _demote(_tables(folder, results)), ""]
        for picture in sorted(folder.glob("*.png")):
            lines += [f"![{picture.stem}]({link_base}/{folder.name}/{picture.name})", ""]
    return "\n".join(lines)


def main() -> None:
    """``python -m torchir.bench.pages``: write docs/measured.md from docs/results/ (the docs build
    does the same; the file is kept in the repository so that links to it always resolve)."""
    docs = Path(__file__).resolve().parents[2] / "docs"
    (docs / "measured.md").write_text(results_page(docs / "results"))
    print(f"wrote {docs / 'measured.md'}")


if __name__ == "__main__":
    main()
