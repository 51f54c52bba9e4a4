"""Variant choice, the LLVM check (a clear error, never an abort) and import order."""
from __future__ import annotations

import glob
import os
import subprocess
import sys
import textwrap

import drjit as dr
import numpy as np
import pytest

from torchir import backend

RENDER_SNIPPET = """
import torchir
from torchir.functions import render
scene = torchir.Scene.builtin("cbox", resolution=8)
red = scene.get("red.reflectance.value").requires_grad_()
render(scene, {"red.reflectance.value": red}, spp=2, seed=1).mean().backward()
assert red.grad is not None and bool(red.grad.isfinite().all()) and float(red.grad.abs().sum()) > 0
print("OK")
"""


def _run(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.skipif(dr.has_backend(dr.JitBackend.CUDA), reason="CUDA available: auto picks cuda")
def test_auto_picks_llvm_without_cuda(monkeypatch):
    monkeypatch.delenv(backend.ENV_VARIANT, raising=False)
    assert backend.set_variant("auto") == "llvm_ad_rgb"
    assert backend.device() == "cpu"


def test_environment_variable_overrides_auto(monkeypatch):
    monkeypatch.setenv(backend.ENV_VARIANT, "llvm_ad_rgb")
    assert backend.set_variant("auto") == "llvm_ad_rgb"
    monkeypatch.setenv(backend.ENV_VARIANT, "scalar_rgb")
    with pytest.raises(ValueError, match="not differentiable"):
        backend.set_variant("auto")
    monkeypatch.delenv(backend.ENV_VARIANT)
    backend.set_variant("auto")


def test_unknown_variant_lists_choices():
    before = backend.variant()  # llvm_ad_rgb in CI, cuda_ad_rgb on a GPU
    with pytest.raises(ValueError, match="unknown Mitsuba variant 'llvm_ad_rbg'.*llvm_ad_rgb"):
        backend.set_variant("llvm_ad_rbg")
    assert backend.variant() == before  # the failed call changed nothing


def test_llvm_version_is_supported_here():
    assert backend.check_llvm() >= backend.MIN_LLVM_VERSION
    assert "llvm=" in backend.describe()


OLD_LLVM = sorted(glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM-1[45].so"))


@pytest.mark.skipif(not OLD_LLVM, reason="no LLVM < 16 on this machine to test with")
@pytest.mark.parametrize("library", OLD_LLVM)
def test_old_llvm_gives_clear_error_not_abort(library):
    result = _run(RENDER_SNIPPET, DRJIT_LIBLLVM_PATH=library)
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])  # an exception, not SIGABRT
    assert "torchir.backend.LLVMError" in result.stderr and "libllvm19" in result.stderr
    # LLVM 15 loads (and would abort at the first kernel); Dr.Jit itself refuses LLVM 14.
    expected = "needs LLVM >= 16" if "-15" in library else "could not load an LLVM library"
    assert expected in result.stderr


def test_missing_llvm_gives_clear_error():
    result = _run(RENDER_SNIPPET, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    assert "could not load an LLVM library" in result.stderr


@pytest.mark.parametrize("imports", ["import torch\nimport mitsuba\nimport drjit", "import mitsuba\nimport drjit\nimport torch"])
def test_import_order_does_not_matter(imports):
    result = _run(imports + "\n" + RENDER_SNIPPET)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().endswith("OK")


def test_count_kernels_sees_compilation_and_reuse():
    import mitsuba as mi

    x = mi.Float(1.0, 2.0, 3.0)
    marker = float(int.from_bytes(os.urandom(3), "little")) + 0.5  # a literal no kernel in this process has seen
    with backend.count_kernels() as first:
        dr.eval(dr.sin(x) * marker)
    with backend.count_kernels() as second:
        dr.eval(dr.sin(x) * marker)
    # the first launch is compiled, or loaded from Dr.Jit's disk cache (a run before this one drew
    # the same literal): either way it was not in memory (a disk load counted as a hit failed CI)
    assert first.launched == 1 and first.cache_misses == 1
    assert second.launched == 1 and second.cache_misses == 0 and second.compiled == 0


def test_count_kernels_counts_a_disk_cache_load_as_a_miss_not_a_compilation():
    import mitsuba as mi

    marker = float(int.from_bytes(os.urandom(3), "little")) + 0.25
    variant = mi.variant()
    code = (f"import drjit as dr, mitsuba as mi; mi.set_variant({variant!r}); "
            f"dr.eval(dr.sin(mi.Float(1.0, 2.0, 3.0)) * {marker!r})")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr  # the kernel is now in Dr.Jit's disk cache, not in this process
    x = mi.Float(1.0, 2.0, 3.0)
    with backend.count_kernels() as loaded:
        dr.eval(dr.sin(x) * marker)
    assert loaded.launched == 1 and loaded.cache_misses == 1 and loaded.compiled == 0, loaded


@pytest.mark.parametrize("preset", [None, "ACTIVE"])
def test_openmp_waits_passively_unless_the_user_says_otherwise(preset):
    # torch's OpenMP threads busy-wait by default and take the cores Dr.Jit's pool needs
    # (torchir/__init__.py); a user's own setting wins
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    code = "import os, torchir, torch; print(os.environ['OMP_WAIT_POLICY'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == (preset or "PASSIVE")


def test_gc_paused_nests_and_restores_the_collector(cbox):
    """Dr.Jit traces run with Python's cyclic collector paused (a scene freed mid-trace aborts
    the process, backend.gc_paused); a render leaves it as it found it, on or off."""
    import gc

    import torch

    from torchir.functions import render

    assert gc.isenabled()
    with backend.gc_paused():
        assert not gc.isenabled()
        with backend.gc_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()
    assert gc.isenabled()
    seen = []
    with pytest.raises(RuntimeError, match="inside"):
        with backend.gc_paused():
            seen.append(gc.isenabled())
            raise RuntimeError("inside")
    assert seen == [False] and gc.isenabled()
    red = cbox.get("red.reflectance.value").requires_grad_()
    render(cbox, {"red.reflectance.value": red}, spp=1, seed=0).sum().backward()
    assert gc.isenabled()
    gc.disable()
    try:
        render(cbox, {"red.reflectance.value": red}, spp=1, seed=1).sum().backward()
        assert not gc.isenabled()
    finally:
        gc.enable()
    assert torch.isfinite(red.grad).all()


@pytest.mark.parametrize("dtype", [np.uint32, np.bool_, np.float32])
def test_aligned_host_array_copies_onto_a_64_byte_boundary(dtype):
    """Fresh NumPy arrays start wherever the allocator puts them; Dr.Jit compiles their loads
    as aligned or not by that address, so the copy must always start on the boundary."""
    for n in (1, 7, 1000):
        values = (np.arange(3 * n) % 5).astype(dtype)[1::3]  # a strided, offset view
        out = backend.aligned_host_array(values)
        assert out.ctypes.data % 64 == 0 and out.flags.c_contiguous and out.dtype == values.dtype
        np.testing.assert_array_equal(out, values)
