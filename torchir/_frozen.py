"""``freeze``: ``dr.freeze`` whose calls keep every live scene's buffers as they were (``replay_guard``).

A frozen function traverses every object in Dr.Jit's registry (the shapes, BSDFs and emitters of
*every* live scene, not only the one it renders) and, after the call, assigns the traversed
variables back to them. With Dr.Jit 1.5 that assignment sometimes hands a mesh a *new* variable
that aliases the memory of its old one without owning it; the mesh then drops the old variable,
the memory returns to the allocator, and the next allocation overwrites the mesh's vertices
(seen in a test-order run: a session scene's ``large-box.vertex_positions`` changed under a later
test; replayed in one process, the index changed 598 -> 600 with the same data pointer during a
frozen primal pass, and the box's values changed when the next scene was loaded).

torchir's render passes never write a scene's parameters inside a frozen call (binding happens
outside), so a buffer whose variable changed there is that artefact: the guard keeps a reference
to each live scene's buffers (vertex and index buffers, textures) for the duration of the call
and puts back the ones whose variable changed. The reference also keeps the memory owned
while the call runs. Cost: one index read per buffer of every live :class:`~torchir.Scene`.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import drjit as dr

from .scene import live_scenes

__all__ = ["freeze", "GuardedFrozen", "replay_guard", "repairs"]

_REPAIRS = [0]


def repairs() -> int:
    """How many buffers the guard put back since the process started."""
    return _REPAIRS[0]


def _index(value: Any) -> int:
    return value.array.index if dr.is_tensor_v(value) else value.index


def _value(params: Any, entry: tuple) -> Any:
    handle, value_type, node, _flags = entry
    return handle if value_type is None else params.get_property(handle, value_type, node)


def _put(params: Any, entry: tuple, value: Any) -> None:
    """Set the member behind ``entry`` without marking it dirty (the twin of :func:`_value`)."""
    handle, value_type, _node, _flags = entry
    if value_type is None:
        params.set_property(handle, value)
    else:
        params.set_property(handle, value_type, value)


def _buffers(params: Any) -> Iterator[tuple[tuple, Any]]:
    """``(property entry, live value)`` of each Dr.Jit buffer (an array wider than 1 or a tensor,
    not a literal or a transform) among ``params``."""
    for entry in params.properties.values():
        value = _value(params, entry)
        if not dr.is_jit_v(value):
            continue
        if dr.is_tensor_v(value):
            if dr.width(value.array) > 1:
                yield entry, value
        elif dr.depth_v(value) == 1 and dr.width(value) > 1:
            yield entry, value


@contextlib.contextmanager
def replay_guard() -> Iterator[None]:
    """Run a frozen call with every live scene's buffers held, and put back any it re-assigned."""
    held = [(scene.params, entry, type(value)(value), _index(value))
            for scene in live_scenes() for entry, value in _buffers(scene.params)]
    try:
        yield
    finally:
        for params, entry, original, index in held:
            if _index(_value(params, entry)) != index:
                _put(params, entry, original)
                _REPAIRS[0] += 1


class GuardedFrozen:
    """A ``dr.freeze``-d function whose every call runs inside :func:`replay_guard`; other
    attributes (``n_recordings``, ...) are the frozen function's."""

    def __init__(self, function: Any, **options: Any) -> None:
        self.frozen = dr.freeze(function, **options)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        with replay_guard():
            return self.frozen(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.frozen, name)


def freeze(function: Any, **options: Any) -> GuardedFrozen:
    """``dr.freeze(function, **options)``, guarded (see the module docstring)."""
    return GuardedFrozen(function, **options)
