"""Scene loading, built-in scenes, parameter listing and reading, and their errors."""
from __future__ import annotations

import pytest
import torch

import torchir
from torchir.functions import render


def test_builtin_registry_lists_documented_scenes():
    scenes = torchir.scenes.available()
    assert {"cbox", "painting", "glossy_ball", "multiview"} <= set(scenes)
    for name, description in scenes.items():
        assert "max_depth" in description, f"{name} must say which integrator depth it needs"


@pytest.mark.parametrize("name", sorted(torchir.scenes.available()))
def test_every_builtin_loads_renders_and_uses_a_box_filter(name):
    scene = torchir.Scene.builtin(name, resolution=(6, 10))
    assert scene.resolution == (6, 10)
    for sensor in range(scene.sensor_count):
        assert "Box" in str(scene.sensor(sensor).film().rfilter())
    for key in torchir.scenes.get(name).parameters:
        assert key in scene.parameter_names(differentiable_only=True)
    img = render(scene, {}, spp=2, seed=0)
    assert img.shape == (3, 6, 10) and bool(img.isfinite().all()) and float(img.sum()) > 0


def test_multiview_has_one_sensor_per_view():
    scene = torchir.Scene.builtin("multiview", resolution=8, views=3)
    assert scene.sensor_count == 3
    views = [render(scene, {}, spp=2, seed=0, sensor=v) for v in range(3)]
    assert not torch.equal(views[0], views[1])


def test_get_returns_mitsuba_shaped_copies(cbox, painting):
    red = cbox.get("red.reflectance.value")
    assert red.shape == (3,) and red.dtype == torch.float32
    red += 1.0  # a copy: the scene is unchanged
    assert torch.allclose(cbox.get("red.reflectance.value") + 1.0, red)
    assert painting.get("canvas.bsdf.reflectance.data").shape == (8, 8, 3)
    ball = torchir.Scene.builtin("glossy_ball", resolution=8)
    assert ball.get("ball.bsdf.alpha").shape == (1,)
    assert cbox.get("small-box.vertex_positions").shape == (3 * 24,)
    assert cbox.info("red.reflectance.value").differentiable


def test_resolution_and_sensor_count(cbox):
    assert cbox.resolution == (16, 16) and cbox.sensor_count == 1
    with pytest.raises(IndexError, match="sensor 3 out of range: the scene has 1"):
        cbox.sensor(3)


def test_unknown_builtin_suggests_a_name():
    with pytest.raises(KeyError, match="Did you mean 'cbox'"):
        torchir.Scene.builtin("cbx")


def test_unknown_parameter_names_close_matches(cbox):
    with pytest.raises(KeyError, match="'red.reflectance.value'"):
        cbox.get("red.reflectance.valu")


@pytest.mark.parametrize("resolution", [0, (4, -1), "big", (1, 2, 3)])
def test_bad_resolution(resolution):
    with pytest.raises(ValueError, match="resolution"):
        torchir.Scene.builtin("cbox", resolution=resolution)


def test_from_file_missing_names_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.xml"):
        torchir.Scene.from_file(tmp_path / "nope.xml")


def test_from_file_and_from_dict(tmp_path):
    xml = tmp_path / "tiny.xml"
    xml.write_text(
        """<scene version="3.0.0">
  <integrator type="prb"><integer name="max_depth" value="2"/></integrator>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0,0,3" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="4"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere" id="ball"><bsdf type="diffuse" id="mat"/></shape>
  <emitter type="constant"/>
</scene>"""
    )
    scene = torchir.Scene.from_file(xml, res="6")
    assert scene.resolution == (4, 6) and "ball.bsdf.reflectance.value" in scene.parameter_names()
    scene2 = torchir.Scene.from_dict(
        {"type": "scene", "integrator": {"type": "prb"}, "sensor": {"type": "perspective"}, "ball": {"type": "sphere"}}
    )
    assert scene2.sensor_count == 1
    with pytest.raises(ValueError, match="'type': 'scene'"):
        torchir.Scene.from_dict({"ball": {"type": "sphere"}})
