"""Mitsuba variant choice and the LLVM check: the one place that touches ``mi.set_variant``.

``auto`` picks ``cuda_ad_rgb`` when Dr.Jit's CUDA backend works, else ``llvm_ad_rgb``. The
environment variable ``TORCHIR_VARIANT`` overrides ``auto``. Dr.Jit 1.5's LLVM backend needs
LLVM >= 16: with an older LLVM the first kernel *aborts the process*, so the version is checked
before any kernel runs and a :class:`LLVMError` says how to fix it.

Example:
    >>> import torchir
    >>> torchir.backend.set_variant("auto")  # cuda_ad_rgb where CUDA is there
    '..._ad_rgb'
"""
from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

ENV_VARIANT = "TORCHIR_VARIANT"
ENV_FREEZE = "TORCHIR_FREEZE"  # "0" turns frozen render passes off
MIN_LLVM_VERSION = (16, 0, 0)

_FIX_LLVM = (
    "Fix: install LLVM >= 16, e.g. `apt-get install libllvm19` on Debian/Ubuntu (torchir's "
    "`scripts/install.sh` does this), or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 16. "
    "On a machine with an NVIDIA GPU, `set_variant('cuda_ad_rgb')` avoids LLVM altogether."
)

_variant: str | None = None
_freeze = os.environ.get(ENV_FREEZE, "1").strip() != "0"


class LLVMError(RuntimeError):
    """Dr.Jit's LLVM backend is missing or too old to run torchir's kernels."""


def llvm_version() -> tuple[int, int, int] | None:
    """The LLVM version Dr.Jit loaded, or ``None`` when it found no LLVM library."""
    version = tuple(int(v) for v in dr.detail.llvm_version())
    return None if version[0] < 0 else version  # Dr.Jit reports (-1, -1, -1) when none loads


def check_llvm() -> tuple[int, int, int]:
    """Raise :class:`LLVMError` unless Dr.Jit has LLVM >= 16; return the version otherwise."""
    version = llvm_version()
    if version is None:
        raise LLVMError(f"Dr.Jit could not load an LLVM library, so it cannot run on the CPU. {_FIX_LLVM}")
    if version < MIN_LLVM_VERSION:
        found = ".".join(map(str, version))
        raise LLVMError(
            f"Dr.Jit found LLVM {found}, but Dr.Jit 1.5 needs LLVM >= 16 (older versions abort with "
            f"'LLVM ERROR: Cannot select ... fminimum'). {_FIX_LLVM}"
        )
    return version


def _auto_variant() -> str:
    requested = os.environ.get(ENV_VARIANT, "").strip()
    if requested and requested != "auto":
        return requested
    return "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"


def set_variant(name: str = "auto") -> str:
    """Select the Mitsuba variant torchir renders with; returns the variant set.

    Args:
        name: ``"auto"`` (``$TORCHIR_VARIANT`` if set, else CUDA when it works, else LLVM) or an
            explicit differentiable variant such as ``"llvm_ad_rgb"`` or ``"cuda_ad_rgb"``.

    Raises:
        ValueError: the variant is unknown or not differentiable (torchir needs ``*_ad_*``).
        LLVMError: an LLVM variant was asked for and LLVM >= 16 is not available.
    """
    global _variant
    chosen = _auto_variant() if name == "auto" else name
    if chosen not in mi.variants():
        raise ValueError(f"unknown Mitsuba variant {chosen!r}; available: {', '.join(mi.variants())}")
    if "_ad_" not in chosen:
        raise ValueError(f"variant {chosen!r} is not differentiable; torchir needs an '*_ad_*' variant")
    if chosen.startswith("llvm"):
        check_llvm()
    elif chosen.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise RuntimeError(f"variant {chosen!r} needs a working CUDA driver and GPU; none was found")
    mi.set_variant(chosen)
    _variant = chosen
    return chosen


def variant() -> str:
    """The active variant; selects ``auto`` on first use."""
    if _variant is None or mi.variant() != _variant:
        return set_variant("auto" if _variant is None else _variant)
    return _variant


def set_frozen_renders(enabled: bool) -> None:
    """Run render passes as Dr.Jit frozen functions (``dr.freeze``; on by default).

    A frozen pass replays its recorded kernels without re-tracing Python, which removes most
    per-step overhead. Integrators that cannot be frozen (projective ones, custom Python
    integrators) always run unfrozen. ``TORCHIR_FREEZE=0`` turns it off at start-up.
    Affects scenes whose first render comes after the call.
    """
    global _freeze
    _freeze = bool(enabled)


def frozen_renders() -> bool:
    """Whether new scenes' render passes are frozen."""
    return _freeze


_RECORDINGS_PER_PASS = 8  # cached recordings of a frozen pass (one per sensor/spp configuration) ...
_RECORDINGS_PER_SENSOR = 2  # ... plus this many per sensor: each view is its own recording


def frozen_recordings(sensor_count: int) -> int:
    """Recordings a frozen pass of a scene with ``sensor_count`` sensors keeps (its LRU bound)
    and may make before Dr.Jit's "recorded N times" warning is due: a multi-view run renders
    every sensor each epoch, and an LRU smaller than the sensor count re-records every call
    (every render re-traced; measured: docs/rendering.md, "Measurements behind the design");
    Dr.Jit's own threshold (10) printed its warning every step for 8 sensors, whose recordings
    are all expected."""
    return _RECORDINGS_PER_PASS + _RECORDINGS_PER_SENSOR * max(1, sensor_count)


def device() -> str:
    """The torch device whose tensors the active variant exchanges without copies."""
    return "cuda" if variant().startswith("cuda") else "cpu"


def describe() -> str:
    """One line for logs: variant, LLVM version, Mitsuba and Dr.Jit versions."""
    llvm = llvm_version()
    llvm_text = ".".join(map(str, llvm)) if llvm else "none"
    return f"variant={variant()} llvm={llvm_text} mitsuba={mi.__version__} drjit={dr.__version__}"


@dataclass
class KernelStats:
    """What Dr.Jit launched inside a :class:`count_kernels` block."""

    launched: int = 0  # JIT kernels launched
    compiled: int = 0  # of those, compiled from scratch (neither in memory nor on disk)
    cache_misses: int = 0  # of those, not found in the in-memory kernel cache (compiled or loaded from disk)
    execution_time: float = 0.0  # seconds spent executing kernels (as Dr.Jit measures it)
    hashes: list[str] = field(default_factory=list)  # hashes of the compiled kernels


class count_kernels:
    """Context manager counting Dr.Jit kernel launches and compilations.

    Example:
        >>> with torchir.backend.count_kernels() as stats:
        ...     img = render(scene, params, spp=4, seed=1)
        >>> stats.launched > 0   # and stats.compiled == 0 once the kernels are cached
        True
    """

    def __enter__(self) -> KernelStats:
        self._previous = dr.flag(dr.JitFlag.KernelHistory)
        dr.sync_thread()
        dr.kernel_history()  # drain what came before
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        self.stats = KernelStats()
        return self.stats

    def __exit__(self, *exc) -> None:
        drain_kernel_history(self.stats)
        dr.set_flag(dr.JitFlag.KernelHistory, self._previous)


def drain_kernel_history(stats: KernelStats | None = None) -> KernelStats:
    """Wait for queued kernels, then move Dr.Jit's kernel history (recorded while
    ``JitFlag.KernelHistory`` is on) into ``stats`` (a new one by default)."""
    stats = KernelStats() if stats is None else stats
    dr.sync_thread()
    for entry in dr.kernel_history():
        if entry["type"] != dr.KernelType.JIT:
            continue
        stats.launched += 1
        stats.execution_time += float(entry.get("execution_time", 0.0)) * 1e-3
        # Dr.Jit marks a kernel loaded from its disk cache as a hit too (cache_hit and cache_disk)
        in_memory = entry.get("cache_hit", 0) and not entry.get("cache_disk", 0)
        if not in_memory:
            stats.cache_misses += 1
        if not entry.get("cache_hit", 0):
            stats.compiled += 1
            stats.hashes.append(str(entry.get("hash", "")))
    return stats


@contextmanager
def gc_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector while Dr.Jit traces or records.

    A Mitsuba scene that the collector frees in the middle of a trace (a frozen function's
    recording, a symbolic loop) releases its Embree handle through ``jit_enqueue_host_func``,
    which throws there, inside a C++ destructor: the process aborts (seen in the test suite
    as a random ``Aborted`` after a few hundred tests: gdb showed ``Scene::~Scene ->
    EmbreeAccel::release -> jitc_var_free -> jit_enqueue_host_func`` unwinding into
    ``std::terminate`` from a dict freed by the collector). Scenes in reference cycles (a
    Lightning module, a closure) are only ever freed by the collector, at whatever allocation
    triggers it; paused, it runs after the trace. Nesting is fine.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def aligned_host_array(values: np.ndarray, alignment: int = 64) -> np.ndarray:
    """A C-contiguous copy of ``values`` whose data starts on an ``alignment``-byte boundary.

    Dr.Jit maps a NumPy array without copying and compiles its loads as aligned or not by
    where the data happens to start, so arrays made afresh every step flip between two
    kernels (and re-record a frozen function). Map this copy instead: always aligned.
    """
    values = np.asarray(values)
    buffer = np.empty(values.nbytes + alignment, np.uint8)
    start = -buffer.ctypes.data % alignment
    out = buffer[start : start + values.nbytes].view(values.dtype).reshape(values.shape)
    out[...] = values
    return out


def jit_array(array_type: type, values: np.ndarray) -> Any:
    """``array_type(values)`` (a Dr.Jit array such as ``mi.UInt32``) made from an aligned host
    copy (:func:`aligned_host_array`): the kernels reading it are the same whatever NumPy's
    allocation, so a step that makes it afresh compiles nothing new."""
    return array_type(aligned_host_array(np.ascontiguousarray(values)))
