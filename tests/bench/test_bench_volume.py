"""The volume tutorial suite's bookkeeping: the truth sampled in the fit's frame (the tutorial's
grid is rotated), the phases compared, and the YAML protocol."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
import yaml

from torchir.bench import volume_tutorial as vt


def test_the_truth_is_sampled_at_the_fit_s_voxel_centres_in_the_tutorial_s_rotated_frame(tmp_path):
    """The notebook places volume.vol with rotate(x, -90) . scale(2) . translate(-0.5): the world
    point (x, y, z) reads the grid at local ((x + 1) / 2, (1 - z) / 2, (y + 1) / 2), so on a grid of
    the truth's own size voxel (k, j, i) of the fit holds the truth's voxel (j, n - 1 - k, i)."""
    import mitsuba as mi

    import torchir

    torchir.backend.variant()
    n = 6
    grid = np.random.default_rng(0).random((n, n, n, 1)).astype(np.float32)
    path = tmp_path / "truth.vol"
    mi.VolumeGrid(grid).write(str(path))
    rotated = mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(2).translate(-0.5)
    expected = np.stack([grid[:, n - 1 - k] for k in range(n)])  # expected[k, j, i] = grid[j, n-1-k, i]
    np.testing.assert_allclose(vt.truth_on_grid(vt.Assets(path, rotated, "rotated"), n), expected, atol=1e-5)
    np.testing.assert_allclose(vt.truth_on_grid(vt.Assets(path, vt.fit_to_world(), "fit frame"), n), grid, atol=1e-5)
    error = vt.GridError(vt.Assets(path, vt.fit_to_world(), "fit frame"))
    assert error(grid) == pytest.approx(0.0, abs=1e-6)
    assert error(grid + 0.25) == pytest.approx(0.25, rel=1e-4)


def _args(phase1: int = 3, phase2: int = 2) -> argparse.Namespace:
    return argparse.Namespace(phase1=phase1, phase2=phase2, resolution=16, spp=2, spp_factor=8, coarse=4, fine=8)


def test_compare_takes_the_errors_at_the_resize_and_the_end_and_each_phase_s_step_times():
    views = vt.VIEWS
    mitsuba = {"l1_before": 0.02, "l1_end": 0.01, "seconds_per_step": [9.0] * views + [1.0] * (2 * views) + [9.0] * views + [4.0] * views}
    torchir = {"l1_before": 0.03, "l1_end": 0.011, "seconds_per_step": [9.0] * views + [0.5] * (2 * views) + [9.0] * views + [5.0] * views}
    (row,) = vt.compare([{"seed": 0, "mitsuba": mitsuba, "torchir": torchir}], _args())
    assert row["ratio_before"] == pytest.approx(1.5) and row["ratio_end"] == pytest.approx(1.1)
    assert (row["mitsuba_s_coarse"], row["torchir_s_coarse"], row["time_ratio_coarse"]) == (1.0, 0.5, 0.5)
    assert (row["mitsuba_s_fine"], row["torchir_s_fine"], row["time_ratio_fine"]) == (4.0, 5.0, 1.25)
    settings = {"assets": "x", "resolution": 16, "spp": 2, "spp_factor": 8, "coarse": 4, "fine": 8, "phase1": 3, "phase2": 2,
                "step_iterations": 3, "start_l1": 0.05}
    steps = {"mitsuba": {"step_s": 0.2, "kernels_after_warmup": 0}, "torchir": {"step_s": 0.3, "kernels_after_warmup": 1}}
    text = vt.summary({"settings": settings, "rows": [row], "steps": steps})
    assert "| 0 | 0.02 | 0.03 | 1.5 |" in text and "| torchir | 300 | 1.5 | 1 |" in text


def test_the_yaml_holds_the_tutorial_protocol(tmp_path):
    targets = [tmp_path / f"target_{i}.exr" for i in range(vt.VIEWS)]
    config = yaml.safe_load(vt.write_config(targets, _args(), tmp_path, seed=3, steps=25, name="run").read_text())
    model, resize = config["model"], 3 * vt.VIEWS
    entry = model["parameters"][vt.KEY]
    assert entry == {"init": "scene", "bounds": [1e-6, 1.0], "lr": vt.LR, "resolution": {4: 0, 8: resize}}
    assert model["spp"] == {2: 0, 16: resize} and model["loss"] == "l2" and model["optimizer"] == "adam"
    assert model["sensors"] == {"type": "orbit", "count": 5, "distance": 4.0, "elevation": 0.0, "fov": 45.0, "start": -90.0,
                                "arc": 180.0, "filter": "tent", "sample_border": False, "resolution": 16}
    assert config["trainer"]["max_steps"] == 25 and config["data"]["views_per_step"] == 1
    xml = (tmp_path / "scene.xml").read_text()
    assert 'id="object"' in xml and 'name="interior"' in xml and 'name="sigma_t"' in xml


def test_missing_tutorial_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="volume.vol"):
        vt.tutorial_assets(tmp_path)
