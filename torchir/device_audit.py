"""``device_audit``: what in a piece of code would leave the GPU, found on any machine.

On a GPU the images, parameters and gradients of a training step live on the device; two
kinds of code break that, and both run silently on a CPU, where every tensor is on the host:

* a torch factory (``torch.zeros``, ``torch.tensor``, ``torch.rand``, ...) called without a
  ``device``: it follows torch's *default* device (the CPU for most users), so its tensor meets
  CUDA images as a device mismatch or a copy;
* a host transfer: ``Tensor.cpu()/.numpy()/.tolist()/.item()``, ``float(t)``, ``bool(t)``,
  ``.to("cpu")`` (seen where the renderer's device is not the CPU), and Dr.Jit's ``.numpy()``,
  ``np.array(x)`` and ``bool(x)``, each a copy (and a wait) on a GPU.

Host bookkeeping by intent is told apart on any machine by how it was made: a tensor from a
factory given ``device="cpu"`` (the string; ``x.device`` is the render device's stand-in) or moved
with ``.to("cpu")``, and whatever is computed from such tensors alone, is read freely.

Inside ``with device_audit() as audit:`` every such call is recorded with the line of the audited
package that made it (``site``) and the line that ran it (``origin``: a library's, when torchir
called into Lightning or kornia), and for transfers the number of elements moved. Dr.Jit's
``float(x)`` is not seen (nanobind's number slots cannot be wrapped).

Example:
    >>> target = render(scene, {}, spp=4, seed=1)
    >>> with device_audit() as audit:
    ...     loss = (render(scene, {"red.reflectance.value": red}, spp=4, seed=0) - target).square().mean()
    ...     loss.backward()
    >>> audit.factories(), audit.transfers(min_elements=2)
    ([], [])
    >>> print(audit)  # a scalar read: the check that the values are finite
        1 x Tensor.__bool__ (1 elements) at torchir/scene.py:... check_values
"""
from __future__ import annotations

import math
import os
import sys
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

__all__ = ["device_audit", "DeviceAudit", "Finding"]

FACTORIES = frozenset({
    "zeros", "ones", "empty", "full", "arange", "linspace", "logspace", "tensor", "as_tensor", "eye",
    "rand", "randn", "randint", "randperm", "scalar_tensor", "empty_strided", "tril_indices", "triu_indices",
})
TRANSFERS = frozenset({"numpy", "cpu", "tolist", "item", "__float__", "__int__", "__bool__", "__index__"})
_DRJIT_TRANSFERS = ("numpy", "__array__", "__bool__")
_HERE = os.path.abspath(__file__)
_TORCH = os.path.dirname(os.path.abspath(torch.__file__))
_PACKAGE = os.path.dirname(_HERE)


@dataclass(frozen=True)
class Finding:
    """One kind of call at one place: ``kind`` "factory" or "transfer", ``call`` (e.g.
    ``torch.zeros``, ``Tensor.cpu``, ``drjit.numpy``), ``site`` (audited code, ``file:line
    function``), ``origin`` (the line that made the call, ``site`` when they are the same),
    ``count`` calls and, for transfers, the most ``elements`` one moved."""

    kind: str
    call: str
    site: str
    origin: str
    count: int
    elements: int

    def __str__(self) -> str:
        where = self.site if self.origin == self.site else f"{self.origin} <- {self.site}"
        size = f" ({self.elements} elements)" if self.kind == "transfer" else ""
        return f"{self.count:5d} x {self.call}{size} at {where}"


@dataclass
class DeviceAudit:
    """The calls :func:`device_audit` recorded, grouped by (kind, call, site, origin)."""

    roots: tuple[str, ...]
    _seen: dict[tuple[str, str, str, str], list[int]] = field(default_factory=dict)

    def record(self, kind: str, call: str, elements: int) -> None:
        sites = self._sites()
        if sites is None:
            return
        entry = self._seen.setdefault((kind, call, *sites), [0, 0])
        entry[0] += 1
        entry[1] = max(entry[1], elements)

    def _sites(self) -> tuple[str, str] | None:
        frame, origin = sys._getframe(3), None
        while frame is not None:
            path = frame.f_code.co_filename
            here = f"{_short(path)}:{frame.f_lineno} {frame.f_code.co_name}"
            if origin is None and not path.startswith(_TORCH) and path != _HERE:
                origin = here
            if path != _HERE and any(path.startswith(root) for root in self.roots):
                return here, origin or here
            frame = frame.f_back
        return None

    def findings(self, kind: str | None = None) -> list[Finding]:
        out = [Finding(k, call, site, origin, n, size) for (k, call, site, origin), (n, size) in self._seen.items()
               if kind is None or k == kind]
        return sorted(out, key=lambda f: (f.kind, f.site, f.call))

    def factories(self) -> list[Finding]:
        """Factory calls without a ``device`` made by the audited code itself (not by a library it called)."""
        return [f for f in self.findings("factory") if f.origin == f.site]

    def transfers(self, min_elements: int = 1, own: bool = True) -> list[Finding]:
        """Host transfers of at least ``min_elements`` (``min_elements=2`` leaves out scalar reads);
        ``own=False`` also lists those made inside libraries the audited code called."""
        return [f for f in self.findings("transfer") if f.elements >= min_elements and (f.origin == f.site or not own)]

    def __str__(self) -> str:
        lines = [str(f) for f in self.findings()]
        return "\n".join(lines) if lines else "no factory without a device, no host transfer"


def _short(path: str) -> str:
    for marker in ("site-packages" + os.sep, os.path.dirname(_PACKAGE) + os.sep):
        if marker in path:
            return path.split(marker, 1)[1]
    return path


def _elements(value: object) -> int:
    """Entries of a Dr.Jit array or tensor (its ``len`` would count a matrix's rows, a tensor's first axis)."""
    shape = getattr(value, "shape", None)
    return math.prod(shape) if shape is not None else 1


def _to_host(args: tuple, kwargs: dict, render_device: str) -> bool:
    """``.to(...)`` towards the CPU, unless the CPU is where the renderer's tensors live (then
    ``.to(device)`` is the code's move *to* the render device: no transfer where that is a GPU)."""
    if render_device == "cpu":
        return False
    targets = [*args[1:], kwargs.get("device")]
    return any(isinstance(t, (str, torch.device)) and torch.device(t).type == "cpu" for t in targets if t is not None)


def _render_device() -> str:
    try:
        from . import backend
    except ImportError:  # pragma: no cover
        return "cpu"
    return backend.device()


def _tensors(tree: object) -> list[torch.Tensor]:
    return [leaf for leaf in tree_flatten(tree)[0] if isinstance(leaf, torch.Tensor)]


class _TorchCalls(TorchFunctionMode):
    """Records factories without a device and host transfers. Tensors made with an explicit
    ``device="cpu"``, and what is computed from them alone, are host bookkeeping by intent (a
    CPU generator's draws, a batch's view indices): reading them is no transfer on a GPU."""

    def __init__(self, audit: DeviceAudit) -> None:
        super().__init__()
        self.audit = audit
        self.host: dict[int, weakref.ref] = {}
        self.render_device = _render_device()

    def _is_host(self, tensor: torch.Tensor) -> bool:
        ref = self.host.get(id(tensor))
        return ref is not None and ref() is tensor

    def _mark_host(self, result: object) -> None:
        for tensor in _tensors(result):
            key = id(tensor)
            self.host[key] = weakref.ref(tensor, lambda _, key=key: self.host.pop(key, None))

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        inputs = _tensors((args, kwargs))
        from_host = bool(inputs) and all(self._is_host(t) for t in inputs)
        if name in FACTORIES:
            device = kwargs.get("device")
            if device is None:
                self.audit.record("factory", f"torch.{name}", 0)
            result = func(*args, **kwargs)
            if _says_host(device):
                self._mark_host(result)
            return result
        if not from_host and (name in TRANSFERS or (name == "to" and _to_host(args, kwargs, self.render_device))):
            source = args[0] if args and isinstance(args[0], torch.Tensor) else None
            self.audit.record("transfer", f"Tensor.{name}", source.numel() if source is not None else 1)
        result = func(*args, **kwargs)
        moved = _moved_to(name, args, kwargs)
        if _says_host(moved) or (from_host and moved is None):
            self._mark_host(result)
        elif moved is not None and args and result is args[0] and self._is_host(result):
            # on the CPU, .to(x.device) of a host tensor returns the tensor itself: hand back an
            # alias, so that the moved tensor is read as a device tensor and the original stays host
            # (inside the handler the mode is off: this call is not recorded)
            result = result.view_as(result)
        return result


def _says_host(device: object) -> bool:
    """A device written as the string "cpu": host by intent. A ``torch.device`` (``x.device``)
    is not: on a CPU machine it cannot tell the host from the render device."""
    return isinstance(device, str) and device == "cpu"


def _moved_to(name: str, args: tuple, kwargs: dict) -> object:
    """The device a ``.to(...)``/``.cuda()`` call moves to (None: no move, e.g. a dtype change)."""
    if name == "cuda":
        return "cuda"
    if name != "to":
        return None
    for candidate in (*args[1:], kwargs.get("device")):
        if isinstance(candidate, (str, torch.device)):
            return candidate
        if isinstance(candidate, torch.Tensor):  # .to(other): other's device
            return candidate.device
    return None


@contextmanager
def _drjit_calls(audit: DeviceAudit) -> Iterator[None]:
    try:
        import drjit as dr
    except ImportError:  # pragma: no cover - torchir needs Dr.Jit, but the audit itself does not
        yield
        return
    originals = {name: dr.ArrayBase.__dict__[name] for name in _DRJIT_TRANSFERS if name in dr.ArrayBase.__dict__}

    def wrap(name: str, method):
        def recorded(self, *args, **kwargs):
            audit.record("transfer", f"drjit.{name}", _elements(self))
            return method(self, *args, **kwargs)

        return recorded

    for name, method in originals.items():
        setattr(dr.ArrayBase, name, wrap(name, method))
    try:
        yield
    finally:
        for name, method in originals.items():
            setattr(dr.ArrayBase, name, method)


@contextmanager
def device_audit(roots: Sequence[str] = (_PACKAGE,)) -> Iterator[DeviceAudit]:
    """Record, while the block runs, torch factory calls without a device and host transfers
    (torch and Dr.Jit) made from code under ``roots`` (folders; default: the torchir package).

    Yields:
        :class:`DeviceAudit`: ``factories()``, ``transfers(min_elements)``, ``findings()``, ``str()``.
    """
    audit = DeviceAudit(tuple(os.path.abspath(r) + os.sep for r in roots))
    with _drjit_calls(audit), _TorchCalls(audit):
        yield audit
