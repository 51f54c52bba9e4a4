"""torchir: physics-based inverse rendering from PyTorch.

Mitsuba 3 renders are torch autograd Functions (:mod:`torchir.functions`); scenes load and bind
parameters through :class:`torchir.Scene`; :mod:`torchir.testing` checks render gradients.
"""
import os as _os
import sys as _sys

if "torch" not in _sys.modules:
    # Dr.Jit's LLVM thread pool and torch's OpenMP team share the CPU cores. With OpenMP's
    # default busy-waiting, threads of one pool spin on the cores the other needs after every
    # kernel: measured on 2 cores, a 5%-pixel step took 80 ms instead of 17 ms, a full 256^2
    # step 180 ms instead of 88 ms. OpenMP reads this when torch loads, so it only takes effect
    # when torchir is imported first (the CLI is); set OMP_WAIT_POLICY yourself otherwise.
    _os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from . import backend, scenes
from .scene import ParameterInfo, Scene

__version__ = "0.1.0"
__all__ = ["backend", "scenes", "Scene", "ParameterInfo", "functions", "testing", "derived", "rigs", "volumes", "__version__"]


_LAZY = ("functions", "testing", "derived", "modules", "samplers", "imageio", "training", "welding", "extremes",
         "integrators", "bench", "geometry", "rigs", "volumes")


def __getattr__(name: str):
    # the subpackages import Dr.Jit-side modules, torch.nn or Lightning: load each on first use, so
    # that ``torchir.derived.rigid_transform(...)`` works after a bare ``import torchir``
    if name in _LAZY:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchir' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
