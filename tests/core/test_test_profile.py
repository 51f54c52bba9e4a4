"""scripts/test_profile.py: the suite's time per file, and kernels repeated for a literal."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "test_profile.py"


def _module():
    spec = importlib.util.spec_from_file_location("test_profile", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_report_counts_a_kernel_shape_compiled_again_as_a_literal_repeat(tmp_path):
    rows = [
        {"test": "tests/test_a.py::one", "wall_s": 5.0, "compile_s": 3.0, "execution_s": 0.5, "kernels": [[11, 2.0], [12, 1.0]]},
        {"test": "tests/test_a.py::two", "wall_s": 2.0, "compile_s": 2.0, "execution_s": 0.0, "kernels": [[11, 2.0]]},
        {"test": "tests/test_b.py::three", "wall_s": 1.0, "compile_s": 0.0, "execution_s": 0.25},
    ]
    (tmp_path / "gw0.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    report = _module().main([str(tmp_path)])
    assert "3 tests: 8 worker-s, compiling 5 s (literal repeats 2 s), executing kernels 1 s" in report
    a, b = (line.split() for line in report.splitlines() if line.startswith(("tests/test_a.py ", "tests/test_b.py ")))
    assert a[1:] == ["7.0", "5.0", "2.0", "0.5"] and b[1:] == ["1.0", "0.0", "0.0", "0.2"]
