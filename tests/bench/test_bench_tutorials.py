"""scripts/bench_tutorials.py: torchir from YAML vs a plain Mitsuba loop on the example tasks."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bench_tutorials.py"
ROOM = ROOT / "configs" / "examples" / "room"

pytestmark = pytest.mark.skipif(not (ROOM / "targets" / "red.png").is_file(),
                                reason="run scripts/make_example_scene.py first")


def _bench():
    spec = importlib.util.spec_from_file_location("bench_tutorials", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_tutorials", module)  # dataclasses look their module up there
    spec.loader.exec_module(sys.modules["bench_tutorials"])
    return sys.modules["bench_tutorials"]


def _run(out: Path, *args: str, timeout: float) -> dict:
    # a subprocess: the benchmark owns its Dr.Jit state and kernel caches, as on the command line
    subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), *args], check=True, timeout=timeout, cwd=ROOT,
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    return json.loads((out / "results.json").read_text())


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_quick_red_wall_both_methods_reduce_the_error(tmp_path):
    report = _run(tmp_path, "--quick", "--tasks", "red_wall", "--steps", "12", "--no-formats", timeout=120)
    for name in ("summary.md", "results.json", "curves.png"):
        assert (tmp_path / name).is_file(), name
    entry = report["summary"]["red_wall"]
    for method in ("torchir", "mitsuba"):
        m = entry[method]
        assert m["final_error"] < 0.5 * m["initial_error"], (method, m)  # 0.28 -> ~0.07 after 12 steps
        assert m["seconds_per_step"] > 0
    for key in ("error_ratio", "time_ratio", "error_goal_met", "time_goal_met"):
        assert key in entry
    assert np.isfinite(entry["error_ratio"]) and np.isfinite(entry["time_ratio"])
    assert {r["method"] for r in report["runs"]} == {"torchir", "mitsuba"}
    assert all(len(r["step_error"]) == 12 for r in report["runs"])


def test_mitsuba_pose_transform_matches_torchir_rigid_transform():
    """The baseline's Transform4f (translate, rotate about y around the bbox centre) moves the
    blob's vertices exactly as torchir's derived blob.translation / blob.rotation do."""
    import mitsuba as mi

    import torchir
    from torchir.derived import rigid_transform

    bench = _bench()
    variant = torchir.backend.variant()
    torchir.backend.set_variant("llvm_ad_rgb")  # the benchmark's backend; the session's comes back after
    try:
        t, angle = [0.08, 0.0, -0.05], 15.0
        scene = torchir.Scene.from_file(ROOM / "scene.xml")
        rigid_transform(scene, "blob", rotation_axis=[0, 1, 0])
        # on the host, where an LLVM scene's values are (whatever the session's default device)
        expected = scene.expand_derived({"blob.translation": torch.tensor(t, device="cpu"), "blob.rotation": torch.tensor([angle], device="cpu")})
        params = mi.traverse(bench.load_mitsuba_scene(ROOM / "scene.xml"))
        pose = bench.RigidPose(params, "blob", "blob", [0, 1, 0])
        pose.apply(params, {"blob.translation": mi.Vector3f(*t), "blob.rotation": mi.Float(angle)})
        moved = np.asarray(params["blob.vertex_positions"].numpy())  # host: a Dr.Jit array
        np.testing.assert_allclose(moved, expected["blob.vertex_positions"].cpu().numpy().ravel(), atol=1e-5)
    finally:
        torchir.backend.set_variant(variant)


def test_float_bitmaps_adds_the_format_once():
    bench = _bench()
    xml = '<scene version="3.0.0"><texture type="bitmap" name="a"/><texture type="bitmap" name="b">' \
          '<string name="format" value="fp16"/></texture></scene>'
    out = bench.float_bitmaps(xml)
    assert out.count('value="variant"') == 1 and 'value="fp16"' in out


@pytest.mark.slow
def test_quick_mode_all_tasks(tmp_path):
    report = _run(tmp_path, "--quick", timeout=300)
    assert set(report["summary"]) == {"red_wall", "texture", "light", "pose"}
    for entry in report["summary"].values():
        assert entry["torchir"]["final_error"] < entry["torchir"]["initial_error"]
        assert entry["mitsuba"]["final_error"] < entry["mitsuba"]["initial_error"]


def _result(bench, method: str, task: str, seed: int, final: float, warm: float, step: float, target: str = "png"):
    """A finished fit: three warm-up steps of ``warm`` seconds, then three of ``step``."""
    return bench.RunResult(method=method, task=task, seed=seed, target=target, steps=6, step_seconds=[warm] * 3 + [step] * 3,
                           step_error=[0.5, 0.4, 0.3, 0.2, 0.2, final], final={}, final_error=final,
                           per_param_error={"k": final}, wall_seconds=10.0)


def test_compare_reads_the_ratios_and_goals_of_the_slow_runs_from_known_fits():
    """The numbers the slow runs above report (summary.md's ratio columns and goal verdicts),
    from fits with known errors and step times: error ratio = torchir's mean final error /
    Mitsuba's, time ratio = mean step time after the warm-up steps, torchir's / Mitsuba's, an
    error goal met at ratio <= 1.10 or within 2 s.e. of the seeds' spread; other targets (JPEG)
    left out."""
    bench = _bench()
    assert bench.WARMUP == 3 and bench.ERROR_GOAL == bench.TIME_GOAL == 1.10
    runs = [
        _result(bench, "torchir", "red_wall", 0, 0.12, 5.0, 0.2), _result(bench, "torchir", "red_wall", 1, 0.14, 5.0, 0.2),
        _result(bench, "mitsuba", "red_wall", 0, 0.10, 1.0, 0.1), _result(bench, "mitsuba", "red_wall", 1, 0.10, 1.0, 0.1),
        _result(bench, "torchir", "red_wall", 0, 9.0, 5.0, 9.0, target="jpg"),  # another target: not compared
        _result(bench, "torchir", "light", 0, 0.2, 0.5, 0.1), _result(bench, "torchir", "light", 1, 0.3, 0.5, 0.1),
        _result(bench, "mitsuba", "light", 0, 0.2, 0.5, 0.1), _result(bench, "mitsuba", "light", 1, 0.2, 0.5, 0.104),
    ]
    out = bench.compare(runs)
    red, light = out["red_wall"], out["light"]
    assert red["torchir"]["final_error"] == pytest.approx(0.13) and red["torchir"]["seconds_per_step"] == pytest.approx(0.2)
    assert red["torchir"]["initial_error"] == 0.5 and red["torchir"]["seeds"] == [0, 1]
    assert red["error_ratio"] == pytest.approx(1.3) and red["time_ratio"] == pytest.approx(2.0)
    # s.e. of the difference: sqrt((0.01414² + 0²) / 2) = 0.01; 0.03 apart is beyond 2 s.e.
    assert not red["within_noise"] and not red["error_goal_met"] and not red["time_goal_met"]
    # light: 0.25 against 0.2 (ratio 1.25), s.e. sqrt(0.0707² / 2) = 0.05: within noise
    assert light["error_ratio"] == pytest.approx(1.25) and light["within_noise"] and light["error_goal_met"]
    assert light["time_ratio"] == pytest.approx(0.1 / 0.102) and light["time_goal_met"]
    table = bench.main_table(out)
    assert "| 1.300, outside noise: NOT met |" in table and "| 2.000: NOT met |" in table
    assert "| 1.250, within noise: MET |" in table and "| 0.980: MET |" in table


def test_errors_are_the_rmse_over_every_entry_with_a_truth():
    bench = _bench()
    specs = [bench.ParamSpec("a", 0.5, 0.1, "none", None, np.array([1.0, 2.0])),
             bench.ParamSpec("b", 0.5, 0.1, "none", None, np.array([0.0])),
             bench.ParamSpec("c", 0.5, 0.1, "none", None, None)]  # no truth: not scored
    total, per = bench.errors({"a": np.array([1.5, 2.0]), "b": np.array([-1.0]), "c": np.array([7.0])}, specs)
    assert total == pytest.approx(np.sqrt((0.25 + 0.0 + 1.0) / 3))
    assert per == {"a": pytest.approx(np.sqrt(0.125)), "b": pytest.approx(1.0)}
