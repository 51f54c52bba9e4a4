"""Every ``>>>`` example in torchir's docstrings runs, with the shown output (doctest).

Examples that use a scene get ``scene`` (the 32² Cornell box), ``params`` (``{}``) and ``red``
(its red wall's albedo, grad-enabled), as the docstrings call them; each module runs with a fresh
namespace, so one example cannot lean on another's.
"""
from __future__ import annotations

import doctest
import importlib
import pathlib
import re

import torchir  # noqa: I001  (before torch)
import pytest
import torch

ROOT = pathlib.Path(torchir.__file__).parent
MODULES = sorted(
    ".".join(("torchir", *path.relative_to(ROOT).with_suffix("").parts)).removesuffix(".__init__")
    for path in ROOT.rglob("*.py") if re.search(r"^\s*>>> ", path.read_text(encoding="utf-8"), re.M)
)


def _namespace() -> dict:
    from torchir.functions import render, render_pixels

    scene = torchir.Scene.builtin("cbox", resolution=32)
    return {"torchir": torchir, "torch": torch, "render": render, "render_pixels": render_pixels, "scene": scene,
            "params": {}, "red": scene.get("red.reflectance.value").requires_grad_()}


def test_examples_are_found():
    assert len(MODULES) >= 15 and "torchir.integrators.restir_options" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    finder, runner = doctest.DocTestFinder(), doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = finder.find(module, name, globs={**vars(module), **_namespace()})
    examples = sum(len(t.examples) for t in tests)
    report = []
    for test in tests:
        runner.run(test, out=report.append)
    assert examples > 0
    assert runner.failures == 0, "".join(report)
