"""Dr.Jit-side integrators written in Python (Mitsuba ``RBIntegrator`` subclasses).

``ReSTIRDirectIntegrator`` (registered with Mitsuba as ``restir_di``): ReSTIR direct
illumination with reservoir reuse across gradient steps (Wang et al. 2023). Imported lazily:
the module needs a Mitsuba variant (call :func:`torchir.backend.variant` first).
"""
from __future__ import annotations

from typing import Any

__all__ = ["ReSTIRDirectIntegrator", "register"]


def register() -> None:
    """Register ``restir_di`` with Mitsuba (``{'type': 'restir_di', ...}`` in scene dicts)."""
    import mitsuba as mi

    from .restir_di import ReSTIRDirectIntegrator

    mi.register_integrator("restir_di", lambda props: ReSTIRDirectIntegrator(props))


def __getattr__(name: str) -> Any:
    if name == "ReSTIRDirectIntegrator":
        from .restir_di import ReSTIRDirectIntegrator

        return ReSTIRDirectIntegrator
    raise AttributeError(name)
