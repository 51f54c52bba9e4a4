"""torchir bench: suite dispatch, the report (Markdown + HTML) and the CLI entry."""
from __future__ import annotations

import json

import pytest

from torchir.bench import SUITES, run_suites
from torchir.bench.report import to_html, write_report
from torchir.cli import main


def test_unknown_suite_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="unknown bench suite"):
        run_suites(["nope"], quick=True, out=tmp_path)
    with pytest.raises(SystemExit):
        main(["bench", "nope"])


def test_every_suite_has_a_main():
    import importlib

    for module in SUITES.values():
        assert callable(importlib.import_module(module).main)


def test_report_collects_summaries_and_plots(tmp_path):
    folder = tmp_path / "demo"
    folder.mkdir()
    (folder / "summary.md").write_text("| method | error |\n|---|---|\n| a | 0.5 |\n")
    (folder / "results.json").write_text(json.dumps({"x": 1}))
    (folder / "plot.png").write_bytes(b"\x89PNG")
    runs = [{"suite": "demo", "folder": folder, "exit_code": 0, "seconds": 3.0, "quick": True},
            {"suite": "broken", "folder": tmp_path / "broken", "exit_code": 2, "seconds": 1.0, "quick": True}]
    path = write_report(tmp_path, runs, extremes=False)
    text = path.read_text()
    assert "| a | 0.5 |" in text and "![demo: plot](demo/plot.png)" in text
    assert "FAILED (exit code 2)" in text and "printed no tables" in text
    page = path.with_suffix(".html").read_text()
    assert "<td>0.5</td>" in page and '<img alt="demo: plot" src="demo/plot.png"' in page


def test_to_html_escapes_and_keeps_code():
    page = to_html("# T\n\n```\na < b\n```\n`x<y` text\n")
    assert "<h1>T</h1>" in page and "a &lt; b" in page and "<code>x&lt;y</code>" in page


def test_report_falls_back_to_the_tables_a_suite_printed(tmp_path):
    folder = tmp_path / "printed"
    folder.mkdir()
    (folder / "log.txt").write_text("progress 1/3\n## (a) variance\n| method | ratio |\n|---|---|\n| adaptive | 5.5x |\nwrote files\n")
    text = write_report(tmp_path, [{"suite": "printed", "folder": folder, "exit_code": 0, "seconds": 1.0, "quick": False}], extremes=False).read_text()
    assert "### (a) variance" in text and "| adaptive | 5.5x |" in text and "progress" not in text


def test_soak_table_flags_growth_and_recompilation():
    from torchir.bench.soak import table

    ok = {"technique": "plain", "steps": 10, "seconds_per_step": 0.1, "kernels_per_step": 7.0, "rss_after_warmup_mb": 500.0,
          "rss_final_mb": 501.0, "memory_growth": 0.002, "cache_misses_after_warmup": 0, "compiled_after_warmup": 0}
    leaky = {**ok, "technique": "leaky", "rss_final_mb": 600.0, "memory_growth": 0.2}
    recompiling = {**ok, "technique": "recompiling", "cache_misses_after_warmup": 3}
    rows = table([ok, leaky, recompiling, {"technique": "broken", "error": "boom"}]).splitlines()[2:]
    assert rows[0].endswith("| yes |") and rows[1].endswith("| NO |") and rows[2].endswith("| NO |")
    assert "failed: boom" in rows[3]


def test_claims_table_reads_results_and_marks_missing_figures(tmp_path):
    from torchir.bench.claims import claims_table

    (tmp_path / "adaptive").mkdir()
    rows = [{"method": "adaptive", "budget": 0.03, "ratio_vs_uniform_all": 6.5}]
    (tmp_path / "adaptive" / "results.json").write_text(json.dumps({"a": {"rows": rows}, "b": {"adaptive_time_ratio": 0.7}}))
    table = claims_table(tmp_path)
    assert "| 6.5x | yes |" in table and "| 0.7x | NO |" in table and "| not measured | - |" in table
    assert "denoiser" not in table  # suites that did not run are left out
