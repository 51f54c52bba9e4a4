"""What the package, the README, the docs and the configs refer to is in the repository.

Internal numbering (the papers' index numbers, design-note equation codes, issue numbers) means
nothing to a reader of the repository: papers are cited by authors, year and their own
equation numbers, and every script a page names exists.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TEXTS = sorted([*ROOT.glob("torchir/**/*.py"), ROOT / "README.md", *ROOT.glob("docs/*.md"), *ROOT.glob("configs/*.yaml"),
                *ROOT.glob("scripts/*.sh")])
INTERNAL = re.compile(
    r"paper 00\d"  # the papers' index numbers
    r"|spec §|spec [A-Z]\d|\(R\d{1,2}\)|\bR\d{1,2}[,-]R?\d|Alg\. [AP]\d"  # design-note codes
    r"|\bissue \d+|\.\./shared|stage v\d|\[proto\]"
)
SCRIPT = re.compile(r"\b(?:scripts|tests)/[\w./-]+\.(?:py|sh)\b")  # a script or test file a text names


def _hits(pattern: re.Pattern, path: Path) -> list[str]:
    return [f"{path.relative_to(ROOT)}:{n}: {line.strip()}" for n, line in enumerate(path.read_text().splitlines(), 1)
            if pattern.search(line)]


def test_the_texts_exist():
    assert len(TEXTS) > 50 and ROOT / "README.md" in TEXTS


@pytest.mark.parametrize("path", TEXTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_internal_reference_codes(path):
    assert _hits(INTERNAL, path) == []


@pytest.mark.parametrize("path", TEXTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_named_scripts_and_tests_exist(path):
    missing = [name for name in {m.group(0) for m in SCRIPT.finditer(path.read_text())} if not (ROOT / name).exists()]
    assert missing == []


@pytest.mark.parametrize("text", ["paper 004 R20", "(R9)", "spec §3.6", "spec D2", "Alg. P4", "issue 39", "../shared/spec"])
def test_the_pattern_catches_each_kind(text):
    assert INTERNAL.search(text)


@pytest.mark.parametrize("text", ["Wang et al. 2023, Eq. 21", "B.2 baseline", "R, G, B", "Alg. 4", "spec = parse(x)"])
def test_the_pattern_passes_citations_and_code(text):
    assert not INTERNAL.search(text)


def test_the_docs_build_without_warnings(tmp_path):
    """The site (docs/*.md and the API pages autodoc makes from the docstrings) builds from
    scratch with warnings as errors, as ``bash scripts/build_docs.sh -E -W`` does."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "sphinx", "-b", "html", "-E", "-W", "--keep-going", "-q",
                           str(ROOT / "docs"), str(tmp_path / "html")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
    assert (tmp_path / "html" / "api.html").stat().st_size > 50_000  # the reference pages were generated
