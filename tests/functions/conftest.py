"""Fixtures of the ``torchir.functions`` tests: the "wall" scene (tests.helpers.wall_dict), an
8x8 Cornell box, and warnings raised as errors."""
from __future__ import annotations

import warnings

import pytest

import torchir
from tests.helpers import wall_dict


@pytest.fixture(scope="module")
def wall() -> torchir.Scene:
    return torchir.Scene.from_dict(wall_dict())


@pytest.fixture(scope="module")
def cbox8() -> torchir.Scene:
    return torchir.Scene.builtin("cbox", resolution=8)


@pytest.fixture()
def strict_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield
