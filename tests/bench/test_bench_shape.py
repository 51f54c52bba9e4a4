"""The shape suites' bookkeeping: the hand-welded baseline mesh, the phases compared, the config."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
import yaml

from torchir.bench import mesh_step, shape_tutorial
from torchir.bench.exported_meshes import uv_sphere, write_ply


def test_welded_baseline_has_one_vertex_per_position_and_the_same_triangles(tmp_path):
    import mitsuba as mi

    path = tmp_path / "sphere.ply"
    write_ply(uv_sphere(segments=12, rings=6), path)
    loaded = mi.load_dict({"type": "ply", "filename": str(path)})
    p = np.array(loaded.vertex_positions_buffer()).reshape(-1, 3)
    f = np.array(loaded.faces_buffer(), np.int64).reshape(-1, 3)
    welded, index = mesh_step.welded_mesh(path)
    q = np.array(welded.vertex_positions_buffer()).reshape(-1, 3)
    g = np.array(welded.faces_buffer(), np.int64).reshape(-1, 3)
    assert len(np.unique(p, axis=0)) == len(q) < len(p)  # the seam and the poles were repeated
    assert len(np.unique(q, axis=0)) == len(q)
    np.testing.assert_array_equal(q[index], p)  # each file vertex's welded index holds its position
    np.testing.assert_array_equal(q[g], p[f])  # every triangle at the same corners, in the same order


def _args(phase1: int = 3, phase2: int = 2) -> argparse.Namespace:
    return argparse.Namespace(phase1=phase1, phase2=phase2, resolution=16, spp=2)


def test_compare_takes_the_iteration_before_the_remesh_and_the_end():
    views = shape_tutorial.VIEWS
    steps = range(0, 5 * views + 1, views)
    mitsuba = {"chamfer": {s: 1.0 + s for s in steps}, "seconds_per_step": [0.5] * 40}
    torchir = {"chamfer": {s: 2.0 * (1.0 + s) for s in steps}, "seconds_per_step": [0.6] * 40}
    (row,) = shape_tutorial.compare([{"seed": 0, "mitsuba": mitsuba, "torchir": torchir}], _args())
    assert row["steps_before"] == 2 * views and row["steps_end"] == 5 * views
    assert row["mitsuba_before"] == 1.0 + 2 * views and row["ratio_before"] == pytest.approx(2.0)
    assert row["mitsuba_end"] == 1.0 + 5 * views and row["ratio_end"] == pytest.approx(2.0)
    assert row["time_ratio"] == pytest.approx(1.2)
    assert "| 0 |" in shape_tutorial.summary({"settings": {"assets": "x", "resolution": 16, "spp": 2, "phase1": 3, "phase2": 2,
                                                           "start_chamfer": 0.1, "floor": 0.001}, "rows": [row]})


def test_the_yaml_holds_the_tutorial_protocol(tmp_path):
    assets = shape_tutorial.stand_in_assets(tmp_path)
    targets = [tmp_path / f"target_{i}.exr" for i in range(shape_tutorial.VIEWS)]
    config = yaml.safe_load(shape_tutorial.write_config(assets, targets, _args(), tmp_path, seed=3).read_text())
    model = config["model"]
    assert model["parameters"]["shape.vertex_positions"]["parametrization"] == {"type": "large_steps", "lambda": shape_tutorial.LAMBDA}
    assert model["optimizer"] == "adam_uniform" and model["loss"] == "l1"
    assert model["remesh"] == {"at": [3 * shape_tutorial.VIEWS]}
    assert model["sensors"]["type"] == "fibonacci" and model["sensors"]["resolution"] == 16
    assert config["trainer"]["max_steps"] == 5 * shape_tutorial.VIEWS and config["data"]["views_per_step"] == 1
    assert (tmp_path / "scene.xml").read_text().count('name="sppi" value="0"') == 1


def test_missing_tutorial_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="ico_10k.ply"):
        shape_tutorial.tutorial_assets(tmp_path)
