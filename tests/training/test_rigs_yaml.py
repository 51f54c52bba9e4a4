"""``model.sensors`` in YAML: a sensor rig (torchir.rigs) replaces the scene's sensors, sized by
its own ``resolution`` or by ``model.resolution``; a ``torchir fit`` run over a rig; the
config errors (unknown type or key, two resolutions that disagree)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from torchir import cli, rigs
from torchir.imageio import read_image
from torchir.training import InverseRenderingModule

from tests.helpers import ROOT, _run_dir

PARAMS = {"object.bsdf.reflectance.data": {"init": 0.5}}


def test_model_resolution_sizes_the_rig_and_the_rig_replaces_the_scene_sensors():
    """``model.sensors: {type: fibonacci, ...}`` without its own resolution takes
    ``model.resolution`` (8x12 here, not the built-in's own size) and gives the scene the rig's
    cameras in its order; an orbit with its own resolution keeps it."""
    module = InverseRenderingModule("multiview", resolution=[8, 12], parameters=PARAMS,
                                    sensors={"type": "fibonacci", "count": 5, "distance": 5, "fov": 45})
    expected = rigs.fibonacci(5, 5, 45, (8, 12))
    assert module.scene.sensor_count == 5
    for i in range(5):
        assert module.scene.sensor_resolution(i) == (8, 12)
        np.testing.assert_allclose(np.array(module.scene.sensor(i).world_transform().matrix).reshape(4, 4),
                                   np.array(expected[i]["to_world"].matrix).reshape(4, 4), atol=1e-5)
    orbit = InverseRenderingModule("multiview", parameters=PARAMS,
                                   sensors={"type": "orbit", "count": 2, "distance": 4, "elevation": 20, "fov": 40, "resolution": 6})
    assert orbit.scene.sensor_count == 2 and orbit.scene.sensor_resolution(1) == (6, 6)


def test_bad_rigs_in_the_config_are_clear_errors():
    """An unknown rig type or key, or ``model.resolution`` and the rig's resolution disagreeing,
    is a ValueError naming ``model.sensors``."""
    for sensors, message in (({"type": "ring", "count": 2}, r"model.sensors.type must be one of"),
                             ({"type": "orbit", "count": 2, "distance": 4, "fov": 40, "height": 1}, r"unknown key\(s\) \['height'\]"),
                             ({"type": "orbit", "count": 2, "distance": 4, "elevation": 0, "fov": 40, "resolution": 16},
                              r"model.resolution \(8\) and model.sensors.resolution \(16\) differ")):
        with pytest.raises(ValueError, match=message):
            InverseRenderingModule("multiview", resolution=8, parameters=PARAMS, sensors=sensors)


def test_a_yaml_run_over_a_fibonacci_rig(tmp_path):
    """``torchir fit`` on configs/multiview.yaml with ``--model.sensors`` a 3-camera Fibonacci rig
    and ``--model.resolution 8``: 2 steps over the rig's 3 views, whose 8² targets it writes;
    the saved config keeps the rig."""
    code = cli.main(["fit", "--config", str(ROOT / "configs" / "multiview.yaml"),
                     "--model.sensors", "{type: fibonacci, count: 3, distance: 3, fov: 40}", "--model.resolution", "8",
                     "--model.preview_spp", "2", "--data.views_per_step", "3", "--trainer.max_steps", "2",
                     "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
                     "--trainer.logger.init_args.save_dir", str(tmp_path)])
    assert code == 0
    run = _run_dir(tmp_path, "multiview")
    assert yaml.safe_load((run / "result.yaml").read_text())["step"] == 2
    assert yaml.safe_load((run / "hparams.yaml").read_text())["sensors"] == {"type": "fibonacci", "count": 3, "distance": 3, "fov": 40}
    targets = sorted(p.name for p in (run / "images").glob("target_v*.png"))
    assert targets == ["target_v0.png", "target_v1.png", "target_v2.png"]
    assert read_image(run / "images" / "target_v2.exr").shape == (3, 8, 8)
