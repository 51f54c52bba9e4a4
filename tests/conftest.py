"""Shared fixtures: tiny scenes, built once per session so Dr.Jit's kernels are reused.

Guards that keep every test's outcome independent of the tests before it (any order, any worker):

* each test starts from RNG states fixed by its own id (torch, numpy, ``random``), whatever ran before;
* a test that changes a shared scene (a session- or module-scoped fixture) fails, naming the
  scene and the parameters it changed (the next test would otherwise inherit them), and the
  values a test's renders bound to a shared scene are unbound after it: a grad-enabled value left
  bound in one test's scene broke another file's forward-mode derivative ("edge ... lies outside
  of the current dr.isolate_grad() scope": Dr.Jit's virtual calls reach every live scene);
* after each test module the garbage collector frees its scenes: every virtual call Dr.Jit
  traces (a BSDF, emitter or shape evaluated through its registry) covers *every* live instance
  of that class in the process, so the scenes of earlier modules, kept alive by reference cycles,
  slowed later renders (a 16x16 render 2 ms alone, 17 ms with 60 stale scenes) and changed
  their kernels (a kernel compiled again after the warm-up: order-dependent failures).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP (see torchir/__init__.py)

import gc  # noqa: E402
import hashlib  # noqa: E402
import random  # noqa: E402
import re  # noqa: E402
import zlib  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

import torchir
from tests.helpers import RES

if torchir.backend.device() != "cpu":
    # On a GPU (scripts/gpu_check.sh) the tests' own tensors are made where the renderer's are;
    # torchir itself never relies on the default device (tests/core/test_device_audit.py).
    torch.set_default_device(torchir.backend.device())

# The longest files (worker seconds, measured with the slow tests left out), run first so that
# `-n 2 --dist loadfile` ends with short files on both workers instead of one worker finishing a
# long file alone. xdist's own reordering (by number of tests per file) is switched off for this
# in pytest_configure. pytest-randomly (installed with the dev extras) shuffles files and tests
# before this stable sort, so the other files, and the tests inside every file, run in a new order
# each run (``--randomly-seed=N`` repeats an order; ``-p no:randomly`` keeps the files' own).
LONGEST_FILES_FIRST = (
    "test_training_techniques.py", "test_restir.py", "test_shape_terms_fd.py", "test_training.py", "test_functions_pixels.py",
    "test_shape_gradients.py", "test_primary_forms.py", "test_restir_integrator.py", "test_mesh_gradients.py",
    "test_photo_to_answer.py", "test_shading_bands.py", "test_extremes.py", "test_bench_adaptive.py", "test_readme_commands.py",
    "test_training_ddp.py", "test_tune.py", "test_restir_grad_paths.py", "test_silhouettes.py",
)
SHARED_SCOPES = ("session", "package", "module", "class")
_LITERAL = re.compile(r"\b(half|float|double|i1|i8|i16|i32|i64) (-?0x[0-9A-Fa-f]+|-?[0-9][0-9.e+-]*)")


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config.option, "loadscopereorder"):  # pytest-xdist >= 3.6
        config.option.loadscopereorder = False


def pytest_collection_finish(session: pytest.Session) -> None:
    # The guards below run the cyclic collector between tests (each module's scenes, a frozen
    # recording's registry). A full collection walks every object alive: after the imports of
    # torch, Mitsuba and Lightning about 440 000, 0.26 s a collection. What the imports and the
    # collected test modules made lives for the whole session; gc.freeze() leaves it out of
    # every later collection, which then walks only what tests made.
    gc.collect()
    gc.freeze()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # TORCHIR_TESTS_FIRST=a.py,b.py: these files first, in that order (scripts/gpu_check.sh: what a
    # time-limited run on a GPU must not miss), then the longest files
    first = [name.strip() for name in os.environ.get("TORCHIR_TESTS_FIRST", "").split(",") if name.strip()]
    rank = {name: i for i, name in enumerate([*first, *(n for n in LONGEST_FILES_FIRST if n not in first)])}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the tests in a file keep their (shuffled) order
    if not torchir.backend.frozen_renders():  # TORCHIR_FREEZE=0 (docs/troubleshooting.md): nothing is frozen to check
        skip = pytest.mark.skip(reason="checks frozen render passes, which TORCHIR_FREEZE=0 turns off")
        for item in items:
            if item.get_closest_marker("frozen"):
                item.add_marker(skip)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem):
    """With ``TORCHIR_TEST_PROFILE=DIR``: one JSON line per test (setup, call and teardown) in
    DIR/<worker>.jsonl with its wall time and the Dr.Jit kernels it compiled, loaded from disk
    and ran, to see where the suite's time goes (``python3 scripts/test_profile.py DIR``)."""
    folder = os.environ.get("TORCHIR_TEST_PROFILE")
    if not folder:
        return (yield)
    import json
    import time

    import drjit as dr

    dr.sync_thread()
    dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    start = time.perf_counter()
    try:
        return (yield)
    finally:
        dr.sync_thread()
        row = {"test": item.nodeid, "wall_s": time.perf_counter() - start, "compiled": 0, "compile_s": 0.0,
               "disk_loads": 0, "launched": 0, "execution_s": 0.0}
        for entry in dr.kernel_history():
            row["launched"] += 1
            row["execution_s"] += float(entry.get("execution_time", 0.0)) * 1e-3
            if not entry.get("cache_hit", 0) and "ir" in entry:  # a frozen function's replays hold no IR
                seconds = (float(entry.get("codegen_time", 0.0)) + float(entry.get("backend_time", 0.0))) * 1e-3
                row["compiled"] += 1
                row["compile_s"] += seconds
                # the kernel's IR with its constants blanked: kernels that differ only in literals share it
                shape = _LITERAL.sub(r"\1 _", entry["ir"].getvalue().replace(str(entry.get("hash", "")), ""))
                row.setdefault("kernels", []).append([zlib.crc32(shape.encode()), round(seconds, 4)])
                if os.environ.get("TORCHIR_TEST_PROFILE_IR"):  # the IR itself, to see which literals differ
                    os.makedirs(os.path.join(folder, "ir"), exist_ok=True)
                    name = f"{zlib.crc32(shape.encode())}_{entry.get('hash', '')}.ll"
                    with open(os.path.join(folder, "ir", name), "w") as f:
                        f.write(entry["ir"].getvalue())
            elif entry.get("cache_disk", 0):
                row["disk_loads"] += 1
        os.makedirs(folder, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(os.path.join(folder, f"{worker}.jsonl"), "a") as f:
            f.write(json.dumps(row) + "\n")


@pytest.fixture(autouse=True)
def _seeded(request: pytest.FixtureRequest) -> None:
    """RNG states fixed by the test's id: its random draws do not depend on what ran before it.
    The id is taken with the file as ``tests/<file name>``, whatever folder of tests/ holds it, so
    that moving a file between folders keeps its tests' draws (file names are unique in tests/)."""
    file, sep, rest = request.node.nodeid.partition("::")
    seed = zlib.crc32(f"tests/{os.path.basename(file)}{sep}{rest}".encode())
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


@pytest.fixture(scope="module", autouse=True)
def _free_module_scenes():
    """Collect the module's garbage once it is done, so its scenes leave Dr.Jit's registry."""
    yield
    gc.collect()


def _shared_scenes(item: pytest.Item) -> dict[str, torchir.Scene]:
    """The scenes ``item`` gets from fixtures that outlive it (session, module or class scope)."""
    out = {}
    defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
    for name, value in getattr(item, "funcargs", {}).items():
        if isinstance(value, torchir.Scene) and name in defs and defs[name][-1].scope in SHARED_SCOPES:
            out[name] = value
    return out


def _fingerprint(scene: torchir.Scene) -> dict[str, str]:
    """A digest of each parameter's loaded value (what every render starts from), and of the
    scene's integrator."""
    out = {"<integrator>": str(scene.integrator)}
    for name in scene.params.keys():
        try:
            value = scene.get(name)
        except Exception:  # noqa: BLE001 (a parameter torch cannot hold: not a render's input)
            continue
        out[name] = hashlib.sha1(value.cpu().numpy().tobytes()).hexdigest()
    return out


_FINGERPRINTS: dict[int, tuple[torchir.Scene, dict[str, str]]] = {}


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Fail the test that changed a shared scene: the tests after it would inherit the change."""
    shared = _shared_scenes(item)
    for scene in shared.values():
        if id(scene) not in _FINGERPRINTS or _FINGERPRINTS[id(scene)][0] is not scene:
            _FINGERPRINTS[id(scene)] = (scene, _fingerprint(scene))
    try:
        result = yield
    finally:
        for scene in shared.values():
            if scene.bound_names:  # a render's values, grad-enabled ones included: not the next test's
                scene.bind({})
    for name, scene in shared.items():
        before = _FINGERPRINTS[id(scene)][1]
        after = _fingerprint(scene)
        if after != before:
            _FINGERPRINTS[id(scene)] = (scene, after)
            changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
            raise AssertionError(f"this test changed the shared scene {name!r} ({', '.join(changed)}); the tests after it "
                                 "would inherit the change: work on a copy (e.g. torchir.Scene.builtin(...) of its own)")
    return result


@pytest.fixture(scope="session", autouse=True)
def _variant() -> str:
    variant = torchir.backend.set_variant("auto")
    _share_cores()
    return variant


def _share_cores() -> None:
    """Under ``pytest -n N``, each worker's torch gets its share of the cores: N workers each with
    an OpenMP team as wide as the machine kept their threads waiting on one another (six render
    test files on 2 cores, ``-n 2``: 85 s with torch's default threads, 62 s with one each).
    Dr.Jit's pool keeps its size: at one thread Mitsuba's EXR writer waits forever (see
    torchir.imageio.write_image), and resizing it while kernels run crashed a worker."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


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
    random failure in CI). Collect that garbage first, and keep the collector paused. Pending
    Dr.Jit work of earlier tests (unevaluated variables that hold a scene's objects) is evaluated
    between two collections, so that it releases what it holds before the count starts."""
    import drjit as dr

    gc.collect()
    dr.eval()
    dr.sync_thread()
    gc.collect()
    with torchir.backend.gc_paused():
        yield


@pytest.fixture()
def red(cbox) -> torch.Tensor:
    return cbox.get("red.reflectance.value").requires_grad_()


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[str, dict[str, object]]:
    """The meshes as exporters write them (OBJ and PLY files of ``torchir.bench.exported_meshes``)."""
    from torchir.bench.exported_meshes import write_all

    return write_all(tmp_path_factory.mktemp("exported"))
