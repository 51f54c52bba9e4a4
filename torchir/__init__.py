"""torchir: physics-based inverse rendering from PyTorch.

Mitsuba 3 renders are torch autograd Functions (:mod:`torchir.functions`); scenes load and bind
parameters through :class:`torchir.Scene`; :mod:`torchir.testing` checks render gradients.
"""
from . import backend, scenes
from .scene import ParameterInfo, Scene

__version__ = "0.1.0"
__all__ = ["backend", "scenes", "Scene", "ParameterInfo", "functions", "testing", "__version__"]


def __getattr__(name: str):
    # functions/ and testing import Dr.Jit-side modules; load them on first use.
    if name in ("functions", "testing"):
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchir' has no attribute {name!r}")
