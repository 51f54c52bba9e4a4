"""The reconstruction loop of docs/geometry.md runs as the page shows it (one step per view a
phase instead of twenty), in a fresh working directory, and writes the recovered mesh."""
from __future__ import annotations

import re
import warnings

from tests.helpers import ROOT
from torchir.geometry import read_mesh

PAGE = ROOT / "docs" / "geometry.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```$", text, flags=re.S | re.M)


def test_the_pages_loop_runs_and_writes_the_recovered_mesh(tmp_path, monkeypatch, capsys):
    blocks = python_blocks(PAGE.read_text())
    assert len(blocks) == 1 and "steps = 20\n" in blocks[0]
    monkeypatch.chdir(tmp_path)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*smooth-shaded.*")  # the page names it
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="gpytoolbox.*")  # its imports of scipy/numpy
        exec(compile(blocks[0].replace("steps = 20\n", "steps = 1\n"), str(PAGE), "exec"), {"__name__": "geometry_page"})
    assert "Chamfer² " in capsys.readouterr().out
    v, f = read_mesh(tmp_path / "recovered.ply", device="cpu")
    assert len(v) > 162 and f.shape[1] == 3  # remeshed to shorter edges: more vertices than the sphere's
