"""The README's main job at tiny scale, and the command line."""
from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import matplotlib.image

from torchir import cli

ROOT = Path(__file__).resolve().parents[1]


def _load_quickstart():
    spec = importlib.util.spec_from_file_location("quickstart", ROOT / "scripts" / "quickstart.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_quickstart_recovers_the_albedos(tmp_path):
    summary = _load_quickstart().main(["--resolution", "16", "--steps", "40", "--spp", "4", "--out", str(tmp_path)])
    assert summary["final_param_error"] < 0.25 * summary["initial_param_error"], summary
    for name in ("target", "initial", "final", "curves"):
        image = matplotlib.image.imread(tmp_path / f"{name}.png")
        assert image.ndim == 3 and image.shape[0] > 0
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert len(rows) == 40 and {"step", "loss", "param_error", "seconds"} <= set(rows[0])


def test_cli_info_lists_backend_and_scenes(capsys):
    assert cli.main(["info"]) == 0
    out = capsys.readouterr().out
    assert "variant=" in out and "cbox" in out and "painting" in out
