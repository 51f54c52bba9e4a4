"""The ``torchir bench`` report: every suite's tables and plots in one Markdown and HTML file."""
from __future__ import annotations

import datetime
import html
import os
import platform
import re
from pathlib import Path


def _suite_section(run: dict, out: Path) -> list[str]:
    folder: Path = run["folder"]
    status = "ok" if run["exit_code"] == 0 else f"FAILED (exit code {run['exit_code']})"
    lines = [f"## {run['suite']}", "", f"{status}; {run['seconds']:.0f} s wall time; outputs in `{folder.relative_to(out)}/`.", ""]
    summary = folder / "summary.md"
    if summary.is_file():
        lines += [summary.read_text().strip(), ""]
    else:
        tables = _markdown_blocks(folder / "log.txt")
        lines += [tables, ""] if tables else ["(the suite wrote no summary.md and printed no tables)", ""]
    for png in sorted(folder.glob("*.png")):
        lines += [f"![{run['suite']}: {png.stem}]({png.relative_to(out).as_posix()})", ""]
    return lines


def _markdown_blocks(log: Path) -> str:
    """Markdown headings and tables a suite printed (its log), in order."""
    if not log.is_file():
        return ""
    kept, previous_table = [], False
    for line in log.read_text().splitlines():
        is_table = line.startswith("|")
        if is_table or line.startswith("#"):
            if line.startswith("#") or (is_table and not previous_table and kept):
                kept.append("")
            kept.append("###" + line.lstrip("#") if line.startswith("#") else line)
        previous_table = is_table
    return "\n".join(kept).strip()


def _extremes_section() -> list[str]:
    from ..extremes import run

    rows = run()
    lines = [
        "## Extremes matrix",
        "",
        f"{sum(ok for *_, ok in rows)}/{len(rows)} cases behave as expected (finite output, or the named clear error).",
        "",
        "| piece | condition | expected | outcome | ok |",
        "|---|---|---|---|---|",
    ]
    for piece, condition, expected, outcome, ok in rows:
        lines.append(f"| {piece} | {condition} | {expected} | {outcome.replace('|', '/')} | {'yes' if ok else 'NO'} |")
    return [*lines, ""]


def write_report(out: Path, runs: list[dict], extremes: bool = True) -> Path:
    """Write ``out/report.md`` and ``out/report.html``; returns the Markdown path."""
    from .. import backend

    lines = [
        "# torchir bench report",
        "",
        f"{datetime.datetime.now().isoformat(timespec='seconds')}; {backend.describe()}; {os.cpu_count()} CPUs; "
        f"Python {platform.python_version()}; mode {'quick' if runs and runs[0]['quick'] else 'full'}.",
        "",
        "| suite | status | wall time (s) |",
        "|---|---|---|",
        *[f"| {r['suite']} | {'ok' if r['exit_code'] == 0 else 'failed'} | {r['seconds']:.0f} |" for r in runs],
        "",
    ]
    from .claims import claims_table

    claims = claims_table(out)
    if claims:
        lines += ["## The papers' claims beside torchir's measurements", "", claims, ""]
    for run in runs:
        lines += _suite_section(run, out)
    if extremes:
        lines += _extremes_section()
    markdown = "\n".join(lines) + "\n"
    path = out / "report.md"
    path.write_text(markdown)
    path.with_suffix(".html").write_text(to_html(markdown))
    return path


def to_html(markdown: str) -> str:
    """A small Markdown-to-HTML conversion for the report (headings, tables, code, images)."""
    body, table, code = [], [], False

    def flush_table() -> None:
        if table:
            rows = [r for r in table if not re.fullmatch(r"\|[\s\-|:]+\|", r)]
            cells = [[html.escape(c.strip()) for c in r.strip("|").split("|")] for r in rows]
            head = "".join(f"<th>{c}</th>" for c in cells[0])
            rest = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
            body.append(f"<table><tr>{head}</tr>{rest}</table>")
            table.clear()

    for line in markdown.splitlines():
        if line.startswith("```"):
            flush_table()
            body.append("</pre>" if code else "<pre>")
            code = not code
        elif code:
            body.append(html.escape(line))
        elif line.startswith("|"):
            table.append(line)
        else:
            flush_table()
            image = re.fullmatch(r"!\[(.*)\]\((.*)\)", line)
            heading = re.match(r"(#+) (.*)", line)
            if image:
                body.append(f'<p><img alt="{html.escape(image[1])}" src="{html.escape(image[2])}" style="max-width:100%"></p>')
            elif heading:
                level = len(heading[1])
                body.append(f"<h{level}>{html.escape(heading[2])}</h{level}>")
            elif line.strip():
                text = re.sub(r"`([^`]*)`", r"<code>\1</code>", html.escape(line))
                body.append(f"<p>{text}</p>")
    flush_table()
    style = "body{font-family:sans-serif;max-width:1100px;margin:2em auto}table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}pre{background:#f6f6f6;padding:6px}"
    return f"<!doctype html><html><head><meta charset='utf-8'><title>torchir bench</title><style>{style}</style></head><body>{''.join(body)}</body></html>\n"
