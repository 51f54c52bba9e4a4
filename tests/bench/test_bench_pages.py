"""The docs' page of measured results (``torchir.bench.pages``): tables rebuilt from each kept
run's ``results.json`` where the suite can, its ``summary.md`` otherwise, with where and how the
run was measured."""
from __future__ import annotations

import json

from torchir.bench import environment
from torchir.bench.jpeg import summary
from torchir.bench.pages import measured_on, results_page

ENVIRONMENT = {"suite": "jpeg", "command": "python -m torchir.bench.jpeg --resolution 256", "commit": "0123456789abcdef",
               "date": "2026-11-29 03:00 UTC", "torchir_backend": "variant=llvm_ad_rgb", "platform": "Linux", "cpu_count": 2}
JPEG_RESULTS = {
    "answers": {"png": [[1.0, 2.0, 3.0], [1.2, 2.2, 3.2]], "exr": [[1.1, 2.1, 3.1], [1.3, 2.3, 3.3]],
                "q75 codec": [[1.05, 2.0, 3.3], [1.25, 2.2, 3.5]]},
    "truth": [1.0, 2.0, 3.0],
    "settings": {"resolution": 256, "steps": 400, "seeds": 2, "photo_spp": 1024, "spp": 8, "corrections": ["codec"]},
    "environment": ENVIRONMENT,
}


def _run(folder, results, summary_md=None, picture=False):
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps(results))
    if summary_md is not None:
        (folder / "summary.md").write_text(summary_md)
    if picture:
        (folder / "plot.png").write_bytes(b"\x89PNG")


def test_tables_come_from_the_json_where_the_suite_can_rebuild_them(tmp_path):
    _run(tmp_path / "jpeg-256", JPEG_RESULTS, summary_md="## stale tables\n", picture=True)
    page = results_page(tmp_path)
    assert "stale" not in page and "### JPEG targets" in page  # summary(results), one heading level down
    assert summary(JPEG_RESULTS).splitlines()[-1] in page  # the q75 row, from the answers
    # paired offsets from the PNG, mean over the two seeds: R (5 % + 4.17 %) / 2, B (10 % + 9.375 %) / 2
    assert "| q75 | codec | +4.58 %, +0.00 %, +9.69 % |" in page
    assert "## jpeg-256" in page and "![plot](results/jpeg-256/plot.png)" in page
    assert measured_on(ENVIRONMENT) in page


def test_other_suites_keep_the_summary_they_wrote(tmp_path):
    _run(tmp_path / "soak-long", {"environment": {"suite": "soak"}}, summary_md="## soak\n\n| step | MB |\n")
    _run(tmp_path / "notes", {"environment": {}})  # no suite, no summary
    page = results_page(tmp_path)
    assert "### soak\n\n| step | MB |" in page and "(this run kept no tables)" in page
    assert page.index("## notes") < page.index("## soak-long")  # runs sorted by name


def test_an_empty_folder_says_so(tmp_path):
    assert "No runs are kept yet." in results_page(tmp_path / "missing")


def test_measured_on_names_command_commit_date_and_machine():
    line = measured_on(ENVIRONMENT)
    assert line == ("Measured: `python -m torchir.bench.jpeg --resolution 256`; commit 0123456; 2026-11-29 03:00 UTC; "
                    "variant=llvm_ad_rgb, Linux, 2 CPUs.")
    assert measured_on({}) == "Measured: ."


def test_environment_records_the_command_and_the_commit():
    env = environment()
    assert env["command"].split()[0] and env["date"].endswith("UTC")
    assert env["commit"] is None or len(env["commit"].split("+")[0]) == 40


def test_the_docs_page_is_the_kept_runs_page():
    """docs/measured.md (kept in the repository, so links to it resolve in any test order) is
    what the kept runs make; after adding a run: ``python -m torchir.bench.pages``."""
    from pathlib import Path

    docs = Path(__file__).resolve().parents[2] / "docs"
    assert (docs / "measured.md").read_text() == results_page(docs / "results")
    assert any((docs / "results").glob("*/results.json"))  # at least one run is kept
