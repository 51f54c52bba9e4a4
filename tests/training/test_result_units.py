"""The units of ``result.yaml`` (torchir.training.results), checked on a real run against Mitsuba.

``result.yaml`` documents each value "in the scene's own units": a rigid pose's rotation in
degrees (three Euler angles, ``R = Rz Ry Rx``), its translation in scene units, its scale
unitless; colours as linear values (an irradiance, a texture's EXR file), not sRGB codes; the
parameter error the pooled RMSE of those numbers against the truth. A run that wrote radians,
a latent (``log`` of the value), sRGB-encoded texels or another error would still write a
plausible file; what tells is an outside computation from the written numbers read in their
documented units: the scene built from them by Mitsuba alone (``rotate`` in degrees, the
texture from the EXR as Mitsuba reads it) must render, with the run's preview seed and spp,
the very image the run wrote as ``images/final_v0.exr``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from torchir import cli

# prb, not a projective integrator: no edge of the plane is in view, so the interior term is the
# whole pose derivative, and torchir's warning that prb misses boundary terms does not apply
pytestmark = pytest.mark.filterwarnings("ignore:'plane.to_world' moves visibility edges:UserWarning")

PIVOT = (0.05, 0.0, 0.0)  # where the plane's load-time to_world puts its origin ("center")
PREVIEW_SPP = 8
PREVIEW_SEED = 2**32 - 7  # InverseRenderingModule.preview's
TEXTURE = np.array([[[0.2, 0.5, 0.8], [0.9, 0.3, 0.1], [0.4, 0.7, 0.2], [0.1, 0.2, 0.6]],
                    [[0.6, 0.1, 0.3], [0.3, 0.8, 0.5], [0.8, 0.6, 0.9], [0.5, 0.4, 0.2]],
                    [[0.7, 0.9, 0.2], [0.2, 0.4, 0.7], [0.3, 0.2, 0.4], [0.9, 0.7, 0.5]],
                    [[0.4, 0.3, 0.9], [0.6, 0.5, 0.3], [0.1, 0.9, 0.8], [0.7, 0.1, 0.4]]])  # (H, W, 3), no symmetry

# A Python scene factory (model.scene: file.py:function): a textured square that fills the view
# whatever its small pose (no silhouette moves), lit head-on by a directional light.
FACTORY = '''
import mitsuba as mi
import numpy as np


def plane(resolution=16, to_world=None, irradiance=3.0, texture=None):
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 30, "to_world": T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "plane": {"type": "rectangle", "to_world": T().translate(%r) @ T().scale(1.2) if to_world is None else to_world,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "raw": True, "filter_type": "bilinear",
                                                              "data": mi.TensorXf(np.asarray(%r if texture is None else texture,
                                                                                             dtype=np.float32))}}},
        "sun": {"type": "directional", "direction": [0.1, -0.2, -1.0], "irradiance": {"type": "rgb", "value": irradiance}},
    }
''' % (list(PIVOT), TEXTURE.tolist())

CONFIG = """
seed_everything: 0
model:
  scene: scenes.py:plane
  derived:
    plane: {type: rigid, shape: plane}
  parameters:
    plane.translation: {init: [0.04, -0.03, 0.05], lr: 0.01, truth: [0.0, 0.0, 0.0]}
    plane.rotation: {init: [4.0, -3.0, 8.0], lr: 1.0, truth: [0.0, 0.0, 0.0]}
    plane.scale: {init: [1.1], lr: 0.01, truth: [1.0]}
    sun.irradiance.value: {init: [2.0, 2.5, 3.5], transform: log, lr: 0.05, truth: [3.0, 3.0, 3.0]}
    plane.bsdf.reflectance.data: {init: scene, lr: 0.05}
  spp: 2
  preview_spp: %d
data:
  target_spp: 8
trainer:
  max_steps: 3
  enable_progress_bar: false
  enable_model_summary: false
  logger:
    - class_path: lightning.pytorch.loggers.CSVLogger
      init_args: {save_dir: results, name: units}
""" % PREVIEW_SPP


def _mitsuba_pose(translation, angles, scale):
    """Mitsuba's transform of the pose as documented: rotate (degrees, x then y then z) and scale
    about the pivot, then translate (scene units)."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    x, y, z = angles
    return (T().translate([p + t for p, t in zip(PIVOT, translation)])
            @ T().rotate([0, 0, 1], z) @ T().rotate([0, 1, 0], y) @ T().rotate([1, 0, 0], x)
            @ T().scale(scale) @ T().translate([-p for p in PIVOT]))


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A three-step ``torchir fit`` from YAML on the factory's scene: its run folder."""
    folder = tmp_path_factory.mktemp("units")
    (folder / "scenes.py").write_text(FACTORY)
    (folder / "units.yaml").write_text(CONFIG)
    assert cli.main(["fit", "--config", str(folder / "units.yaml"),
                     "--trainer.logger.init_args.save_dir", str(folder / "results")]) == 0
    return folder / "results" / "units" / "version_0"


def test_result_yaml_numbers_rebuild_the_final_image_in_mitsuba(run):
    """Mitsuba's own scene built from result.yaml's numbers in their documented units (pose in
    degrees / scene units / unitless, irradiance linear, texture the EXR's linear texels as
    Mitsuba reads them, (H, W, C)) renders the run's final image (same seed and spp).

    The written numbers carry 6 significant digits: a relative change of 5e-7 in the pose and
    the colours moves this smooth image (bilinear texture, no edge in view) by about as much
    (measured: 2.5e-6 at most), so ``rtol=1e-4`` holds with a wide margin. Measured, the largest
    relative change of a pixel when the numbers are read otherwise: the angles as radians 26%,
    in the other order 26%, the irradiance's latent (its log) 64%, the texels sRGB-encoded
    107%, the texture's rows flipped 178%, the translation doubled 5.7%, the scale's log 264%."""
    import mitsuba as mi

    result = yaml.safe_load((run / "result.yaml").read_text())
    p = result["parameters"]
    texture_entry = p["plane.bsdf.reflectance.data"]
    assert texture_entry["file"] == "parameters/plane.bsdf.reflectance.data.exr" and texture_entry["shape"] == [4, 4, 3]
    texture = np.array(mi.Bitmap(str(run / texture_entry["file"])), dtype=np.float32)
    assert texture.shape == (4, 4, 3)
    assert 0.05 < np.abs(texture - TEXTURE).max() < 0.5  # the run changed the texels a few steps' worth
    np.testing.assert_allclose(texture.reshape(-1, 3).mean(0), texture_entry["mean"], rtol=1e-5)

    namespace: dict = {}
    exec(FACTORY, namespace)  # the user's factory, called by Mitsuba's loader alone
    pose = _mitsuba_pose(p["plane.translation"], p["plane.rotation"], p["plane.scale"])
    world = pose @ mi.ScalarTransform4f().translate(list(PIVOT)) @ mi.ScalarTransform4f().scale(1.2)
    native = mi.load_dict(namespace["plane"](to_world=world, irradiance=p["sun.irradiance.value"], texture=texture))
    expected = np.array(mi.render(native, seed=PREVIEW_SEED, spp=PREVIEW_SPP), dtype=np.float64)
    final = np.array(mi.Bitmap(str(run / "images" / "final_v0.exr")), dtype=np.float64)
    assert final.shape == expected.shape == (16, 16, 3)
    np.testing.assert_allclose(final, expected, rtol=1e-4, atol=1e-6)
    # the numbers matter: the loaded scene (the pose and colours the run started from) renders otherwise
    start = np.array(mi.render(mi.load_dict(namespace["plane"]()), seed=PREVIEW_SEED, spp=PREVIEW_SPP))
    assert np.abs(start - final).max() > 0.05

    # the PNG beside it holds the sRGB codes of the same linear image (Pillow reads it)
    linear = np.clip(final, 0.0, 1.0)
    codes = np.rint(255 * np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055))
    with Image.open(run / "images" / "final_v0.png") as png:
        assert np.abs(np.array(png, dtype=np.float64) - codes).max() <= 1  # float32 vs float64 rounding at a half code


def test_param_error_is_the_pooled_rmse_of_the_written_numbers(run):
    """``param_error`` is the RMSE over every entry with a truth (translation, rotation in
    degrees, scale, irradiance: 10 numbers, pooled whatever their units), computed here from
    the written numbers and the config's truth; the texture, given no truth, is left out."""
    result = yaml.safe_load((run / "result.yaml").read_text())
    truth = {"plane.translation": [0.0, 0.0, 0.0], "plane.rotation": [0.0, 0.0, 0.0], "plane.scale": [1.0],
             "sun.irradiance.value": [3.0, 3.0, 3.0]}
    errors = np.concatenate([np.ravel(result["parameters"][k]) - np.array(v) for k, v in truth.items()])
    assert errors.size == 10
    assert result["param_error"] == pytest.approx(math.sqrt(float(np.mean(errors**2))), rel=2e-5)
    assert result["step"] == 3
