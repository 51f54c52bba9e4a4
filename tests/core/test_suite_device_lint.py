"""The test suite's own code runs on a GPU too (scripts/gpu_check.sh): there tests/conftest.py
makes the renderer's device torch's default, renders are CUDA tensors, and two habits of
CPU-only code fail for reasons of the tests themselves:

* ``torch.Generator()`` is a CPU generator: ``torch.rand(..., generator=g)`` on a CUDA default
  device raises. Use ``torch.Generator(device=DEVICE)`` (``tests.helpers.DEVICE``; the same
  stream as ``torch.Generator()`` on the CPU), or ``device="cpu"`` where the draws are meant
  for the host;
* ``tensor.numpy()`` raises for a CUDA tensor: ``tensor.cpu().numpy()`` (no copy on the CPU).
  A Dr.Jit array's ``.numpy()`` copies from the GPU by itself: mark such a line ``# host:``.

A regex over the source, line by line: a ``.cpu()`` on an earlier line of a chained expression
is not seen (move it onto the line of the ``.numpy()``).
"""
from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
EMPTY_GENERATOR = re.compile(r"torch\.Generator\(\s*\)")
NUMPY = re.compile(r"\.numpy\(\)")
ON_THE_HOST = (".cpu()", ".cpu().detach()")
OPT_OUT = "# host:"


def device_findings(text: str) -> list[tuple[int, str]]:
    """``(line number, what)`` for each line of ``text`` that would fail with CUDA tensors."""
    out = []
    for number, line in enumerate(text.splitlines(), 1):
        if OPT_OUT in line:
            continue
        if EMPTY_GENERATOR.search(line):
            out.append((number, "torch.Generator() is a CPU generator: torch.Generator(device=DEVICE)"))
        if any(not line[: m.start()].endswith(ON_THE_HOST) for m in NUMPY.finditer(line)):
            out.append((number, ".numpy() without .cpu() before it (a Dr.Jit array's: mark the line '# host:')"))
    return out


def test_the_lint_finds_both_habits_and_respects_the_opt_out():
    text = "\n".join([
        "g = torch.Generator().manual_seed(0)",
        "g = torch.Generator( )",
        "g = torch.Generator(device=DEVICE).manual_seed(0)",
        "a = image.numpy()",
        "a = image.detach().numpy()",
        "a = image.cpu().numpy(), image.numpy()",
        "a = image.cpu().numpy()",
        "a = image.detach().cpu().numpy()",
        "a = image.cpu().detach().numpy()",
        "a = mi.Float(1.0).numpy()  # host: a Dr.Jit array",
        "a = np.asarray(x)",
    ])
    assert [number for number, _ in device_findings(text)] == [1, 2, 4, 5, 6]


def test_no_cpu_generator_or_device_numpy_in_the_tests():
    this = Path(__file__).resolve()
    found = []
    for path in sorted(TESTS.rglob("*.py")):
        if path.resolve() == this:
            continue
        for number, what in device_findings(path.read_text(encoding="utf-8")):
            found.append(f"{path.relative_to(TESTS.parent)}:{number}: {what}")
    assert not found, "test code that fails on a GPU (see this file's docstring):\n" + "\n".join(found)


def test_no_cpu_generator_or_device_numpy_in_torchir():
    # torchir's own code (the benchmarks included: scripts/gpu_check.sh runs them on the GPU);
    # the runtime check of its steps is tests/core/test_device_audit.py
    package = TESTS.parent / "torchir"
    found = []
    for path in sorted(package.rglob("*.py")):
        if path.name == "device_audit.py":  # names the calls it records in its docstring
            continue
        for number, what in device_findings(path.read_text(encoding="utf-8")):
            found.append(f"{path.relative_to(package.parent)}:{number}: {what}")
    assert not found, "torchir code that fails on a GPU:\n" + "\n".join(found)


def test_files_named_in_torchir_tests_first_run_first():
    # scripts/gpu_check.sh names the files a time-limited GPU run must not miss
    import os
    import subprocess
    import sys

    files = ["tests/modules/test_losses.py", "tests/core/test_jpeg.py", "tests/core/test_extremes.py"]
    env = {**os.environ, "TORCHIR_TESTS_FIRST": "test_jpeg.py,test_losses.py"}
    out = subprocess.run([sys.executable, "-m", "pytest", "--co", "-q", "-p", "no:randomly", "-p", "no:cacheprovider", *files],
                         cwd=TESTS.parent, env=env, capture_output=True, text=True, timeout=300)
    order = [line.split("::")[0] for line in out.stdout.splitlines() if "::" in line]
    assert out.returncode == 0, out.stderr[-2000:]
    seen = list(dict.fromkeys(order))
    # named files first, in the order named, then the longest files (test_extremes.py is one)
    assert seen == ["tests/core/test_jpeg.py", "tests/modules/test_losses.py", "tests/core/test_extremes.py"], seen
