"""Shared fixtures: tiny scenes, built once per session so Dr.Jit's kernels are reused."""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP (see torchir/__init__.py)

import pytest  # noqa: E402
import torch  # noqa: E402

import torchir

RES = 16  # every render test uses 16x16 so the kernels compile once

# The longest files (worker seconds, measured), run first so that `-n 2 --dist loadfile` ends
# with short files on both workers instead of one worker finishing a long file alone. xdist's
# own reordering (by number of tests per file) is switched off for this in pytest_configure.
LONGEST_FILES_FIRST = (
    "test_restir.py", "test_training_ddp.py", "test_restir_integrator.py", "test_extremes.py",
    "test_bench_restir.py", "test_photo_to_answer.py", "test_functions_pixels.py", "test_training.py",
    "test_training_techniques.py", "test_bench_restir_shadow.py", "test_scenes_restir.py", "test_primary_forms.py",
)


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config.option, "loadscopereorder"):  # pytest-xdist >= 3.6
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file keeps its order


@pytest.fixture(scope="session", autouse=True)
def _variant() -> str:
    return torchir.backend.set_variant("auto")


@pytest.fixture(scope="session")
def cbox() -> torchir.Scene:
    return torchir.Scene.builtin("cbox", resolution=RES)


@pytest.fixture(scope="session")
def painting() -> torchir.Scene:
    return torchir.Scene.builtin("painting", resolution=RES, texture=8, hidden_lights=2)


@pytest.fixture()
def settled_registry():
    """For tests that count a frozen function's recordings: Dr.Jit keys a recording on every
    instance in its registry (all scenes' shapes, BSDFs, emitters), so a scene of an earlier
    test freed by the cyclic collector between two calls forces one new recording (seen as a
    random failure in CI). Collect that garbage first, and keep the collector paused."""
    import gc

    gc.collect()
    with torchir.backend.gc_paused():
        yield


@pytest.fixture()
def red(cbox) -> torch.Tensor:
    return cbox.get("red.reflectance.value").requires_grad_()
