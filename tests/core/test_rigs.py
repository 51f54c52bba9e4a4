"""Sensor rigs (torchir.rigs) and sensors given to the scene loaders and renders as objects:
the Fibonacci lattice of Mitsuba's shape tutorial, orbit spacing (the volume tutorial's half
circle), look_at poses, ``sensors=`` replacing a scene's sensors (dict, XML file, built-in),
``render``/``render_pixels`` with an ``mi.Sensor`` of the scene (the same image as its index)
and the error for one it does not hold; the docs' first lines select a variant."""
from __future__ import annotations

import math
import re
import subprocess
import sys

import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir
from torchir import rigs
from torchir.functions import render, render_pixels

from tests.helpers import ROOT, wall_dict

RES = 8


def _frame(sensor: dict) -> np.ndarray:
    """The 4x4 ``to_world`` matrix of a sensor dict."""
    return np.array(sensor["to_world"].matrix, dtype=np.float64).reshape(4, 4)


def _tutorial_origins(count: int, distance: float) -> np.ndarray:
    """The shape tutorial's camera origins, written out again from its notebook (not torchir's code)."""
    golden = (1 + math.sqrt(5)) / 2
    out = []
    for i in range(count):
        theta = 2 * math.pi * i / golden
        phi = math.acos(1 - 2 * (i + 0.5) / count)
        out.append([distance * math.cos(theta) * math.sin(phi), distance * math.sin(theta) * math.sin(phi), distance * math.cos(phi)])
    return np.array(out)


@pytest.mark.parametrize("target", [(0.0, 0.0, 0.0), (0.5, -1.0, 2.0)])
def test_fibonacci_follows_the_tutorial_lattice_and_every_camera_looks_at_the_target(target):
    """Camera ``i`` sits at the tutorial's lattice point (polar angle ``acos(1 - 2 (i + 0.5) / n)``,
    azimuth ``2 pi i / golden ratio``) at distance 5 from the target, its ``to_world`` z axis
    points at the target and its y axis lies in the plane of the tutorial's up (+y); the film is
    the tutorial's (gaussian filter, sample_border) at the given size and fov."""
    sensors = rigs.fibonacci(8, distance=5, fov=45, resolution=(RES, 12), target=target)
    assert len(sensors) == 8
    expected = _tutorial_origins(8, 5.0) + np.array(target)
    for i, sensor in enumerate(sensors):
        m = _frame(sensor)
        np.testing.assert_allclose(m[:3, 3], expected[i], rtol=0, atol=1e-5)
        towards = (np.array(target) - m[:3, 3]) / np.linalg.norm(np.array(target) - m[:3, 3])
        np.testing.assert_allclose(m[:3, 2], towards, rtol=0, atol=1e-5)
        assert abs(np.cross(m[:3, 2], [0, 1, 0]) @ m[:3, 1]) < 1e-5  # up (+y), forward and the y axis share a plane
        assert sensor["fov"] == 45 and sensor["film"]["rfilter"] == {"type": "gaussian"} and sensor["film"]["sample_border"] is True
        assert (sensor["film"]["height"], sensor["film"]["width"]) == (RES, 12)


def test_orbit_spaces_cameras_evenly_and_reproduces_the_volume_tutorial():
    """Mitsuba's volume tutorial turns the camera at (0, 0, 4) about +y by ``180 / 5 * i - 90``
    degrees: ``orbit(5, 4, 0, ..., start=-90, arc=180)`` gives those five frames; with an
    elevation, consecutive cameras are ``arc / count`` apart in azimuth, all at the same height
    and distance, looking at the target."""
    ours = rigs.orbit(5, 4, 0, 45, RES, start=-90, arc=180, filter="tent", sample_border=False)
    for i, sensor in enumerate(ours):
        angle = 180.0 / 5 * i - 90.0
        theirs = mi.ScalarTransform4f().rotate([0, 1, 0], angle) @ mi.ScalarTransform4f().look_at(target=[0, 0, 0], origin=[0, 0, 4], up=[0, 1, 0])
        np.testing.assert_allclose(_frame(sensor), np.array(theirs.matrix, dtype=np.float64).reshape(4, 4), rtol=0, atol=1e-5)
        assert sensor["film"]["rfilter"] == {"type": "tent"} and sensor["film"]["sample_border"] is False

    target = np.array([0.0, 1.0, 0.0])
    origins = np.array([_frame(s)[:3, 3] for s in rigs.orbit(6, 3, 30, 45, RES, target=tuple(target))]) - target
    np.testing.assert_allclose(np.linalg.norm(origins, axis=1), 3.0, rtol=1e-6)
    np.testing.assert_allclose(origins[:, 1], 3.0 * math.sin(math.radians(30)), rtol=1e-6)
    azimuths = np.degrees(np.arctan2(origins[:, 0], origins[:, 2]))  # from +z, turning towards +x
    np.testing.assert_allclose(np.diff(np.unwrap(azimuths, period=360)), 60.0, rtol=0, atol=1e-4)
    assert azimuths[0] == pytest.approx(0.0, abs=1e-6)


def test_look_at_poses_and_bad_rigs_get_clear_errors():
    """look_at places each camera at its origin looking at its target; a pose with an unknown
    key, an up along the view, a bad count or resolution, or an unknown YAML type or key is a
    ValueError naming it."""
    (sensor,) = rigs.look_at([{"origin": [1, 2, 3], "target": [0, 1, 0], "up": [0, 0, 1]}], fov=30, resolution=RES)
    m = _frame(sensor)
    np.testing.assert_allclose(m[:3, 3], [1, 2, 3], atol=1e-6)
    np.testing.assert_allclose(m[:3, 2], -np.array([1, 1, 3]) / math.sqrt(11), atol=1e-6)
    with pytest.raises(ValueError, match=r"views\[0\] must be a mapping \{origin, target, up\}"):
        rigs.look_at([{"origin": [1, 2, 3], "look": [0, 0, 0]}], fov=30, resolution=RES)
    with pytest.raises(ValueError, match="looks along its up direction"):
        rigs.look_at([{"origin": [0, 3, 0]}], fov=30, resolution=RES)
    with pytest.raises(ValueError, match="count must be an int >= 1"):
        rigs.fibonacci(0, 5, 45, RES)
    with pytest.raises(ValueError, match="resolution must be an int or"):
        rigs.orbit(3, 5, 0, 45, "big")
    with pytest.raises(ValueError, match=r"model.sensors.type must be one of \['fibonacci', 'look_at', 'orbit'\], got 'ring'"):
        rigs.from_spec({"type": "ring", "count": 3})
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['radius'\]; allowed: .*'distance'"):
        rigs.from_spec({"type": "fibonacci", "count": 3, "radius": 5, "fov": 45, "resolution": RES})
    with pytest.raises(ValueError, match=r"needs \['resolution'\] \(or set model.resolution\)"):
        rigs.from_spec({"type": "fibonacci", "count": 3, "distance": 5, "fov": 45})


@pytest.fixture(scope="module")
def rig_scene():
    """The 8² multiview sphere seen by three Fibonacci cameras given as mi.Sensor objects."""
    objects = [mi.load_dict(s) for s in rigs.fibonacci(3, 3, 40, RES, filter="box")]
    return torchir.Scene.builtin("multiview", resolution=RES, sensors=objects), objects


def test_render_with_a_sensor_object_is_the_render_with_its_index(rig_scene):
    """``render(sensor=obj)`` is bit for bit ``render(sensor=i)`` for the scene's sensor ``i``
    (also in a render_pixels list); the views differ, so an index off by one would show."""
    scene, objects = rig_scene
    assert scene.sensor_count == 3 and all(scene.sensor(i) is objects[i] for i in range(3))
    images = [render(scene, {}, spp=2, seed=3, sensor=i) for i in range(3)]
    for i in (2, 1):
        assert torch.equal(render(scene, {}, spp=2, seed=3, sensor=objects[i]), images[i])
    assert not torch.equal(images[1], images[2]) and not torch.equal(images[0], images[1])
    index = torch.tensor([0, 9, 27, 64 + 27, 64 + 40])
    assert torch.equal(render_pixels(scene, {}, index, spp=2, seed=1, sensor=[objects[1], 2]),
                       render_pixels(scene, {}, index, spp=2, seed=1, sensor=[1, 2]))


def test_a_sensor_the_scene_does_not_hold_is_an_error_saying_how_to_add_it(rig_scene):
    """An mi.Sensor that is not one of the scene's (even one built from the same dict) raises a
    ValueError naming ``Scene.from_dict(d, sensors=sensors)``; a non-sensor is a TypeError."""
    scene, _ = rig_scene
    foreign = mi.load_dict(rigs.fibonacci(3, 3, 40, RES, filter="box")[0])
    with pytest.raises(ValueError, match=re.escape("not one of the scene's 3 sensor(s)") + ".*" + re.escape("Scene.from_dict(d, sensors=sensors)")):
        render(scene, {}, spp=1, sensor=foreign)
    with pytest.raises(ValueError, match="Scene.from_dict"):
        render_pixels(scene, {}, torch.tensor([0]), sensor=[0, foreign])
    with pytest.raises(TypeError, match="int index or one of the scene's mi.Sensor"):
        render(scene, {}, spp=1, sensor="front")
    with pytest.raises(IndexError, match="sensor 3 out of range"):
        render(scene, {}, spp=1, sensor=3)


def test_sensors_replace_the_sensors_of_a_dict_and_of_a_file():
    """``sensors=`` replaces a scene dict's sensors (the wall's two) and an XML file's (the room's
    one, its film 48²) by the rig's, in the rig's order and size; a list that holds no sensor is
    a TypeError."""
    rig = rigs.orbit(3, 4, 10, 40, (RES, 6), filter="box")
    wall = torchir.Scene.from_dict(wall_dict(sensors=2), sensors=rig)
    room = torchir.Scene.from_file(ROOT / "configs" / "examples" / "room" / "scene.xml", sensors=rig)
    for scene in (wall, room):
        assert scene.sensor_count == 3 and scene.sensor_resolution(2) == (RES, 6)
        for i in range(3):
            np.testing.assert_allclose(np.array(scene.sensor(i).world_transform().matrix).reshape(4, 4), _frame(rig[i]), atol=1e-5)
    with pytest.raises(TypeError, match=r"sensors\[0\] is not a Mitsuba sensor dict"):
        torchir.Scene.from_dict(wall_dict(), sensors=[{"type": "sphere"}])


def test_the_docs_first_lines_select_a_variant_for_mitsuba_dicts():
    """``import torchir`` selects no Mitsuba variant (on a GPU machine that would start CUDA at
    import), so the README's and docs/rendering.md's first code lines call
    ``torchir.backend.set_variant("auto")``: those lines, run in a fresh interpreter, make a
    Mitsuba dict with ``mi.ScalarTransform4f`` loadable."""
    firsts = []
    for page in ("README.md", "docs/rendering.md"):
        block = re.search(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S).group(1).splitlines()
        firsts.append(block[: next(i for i, line in enumerate(block) if "set_variant" in line) + 1])
        assert 'torchir.backend.set_variant("auto")' in firsts[-1][-1] and len(firsts[-1]) <= 3, (page, firsts[-1])
    assert firsts[0] == firsts[1]  # one fresh interpreter checks both
    code = "\n".join([*firsts[0], "import mitsuba as mi",
                      "scene = torchir.Scene.from_dict({'type': 'scene', 'shape': {'type': 'sphere', 'to_world': mi.ScalarTransform4f().translate([0, 0, 1])}},",
                      "                                sensors=torchir.rigs.look_at([{'origin': [0, 0, 5]}], fov=40, resolution=4))",
                      "print(scene.sensor_count, mi.variant())"])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[0] == "1" and out.stdout.split()[1].endswith("_ad_rgb")
