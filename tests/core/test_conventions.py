"""The conventions a user's numbers depend on, each pinned against a reference outside torchir.

A wrong convention passes every self-consistency check (an orthonormal matrix in the wrong axis
order is still a rotation; an image flipped on writing and on reading round-trips): so each is
compared here with Mitsuba's own transforms, Mitsuba's own renders and loaders, scipy, Pillow, or
a pinhole camera worked out by hand, never with torchir's own code.

=====================================  ==============================================  ==========================================================
convention                             outside reference                               test
=====================================  ==============================================  ==========================================================
Euler angles (degrees): R = Rz Ry Rx   ``mi.ScalarTransform4f().rotate`` per axis,     test_euler_rotation_is_mitsubas_rz_ry_rx_in_degrees
                                       composed; scipy ``from_euler("xyz")``
one angle about an axis (Rodrigues)    ``mi.ScalarTransform4f().rotate(axis, angle)``  test_axis_angle_rotation_is_mitsubas_rotate
                                       for an oblique axis; scipy ``from_rotvec``
rigid pose of a mesh,                  the mesh loaded by Mitsuba with ``to_world =    test_rigid_pose_of_a_mesh_moves_it_as_mitsubas_transform
x' = p + s R (x - p) + t               translate(p + t) R scale(s) translate(-p)``
                                       composed before the load's own
rigid pose of an analytic shape        that transform times the shape's ``to_world``;  test_rigid_pose_of_an_analytic_shape_is_mitsubas_to_world
(``to_world``), bound for a render     the bounding box Mitsuba computes for the       test_bound_pose_is_the_to_world_mitsuba_renders_with
                                       shape it renders
image (C, H, W): row 0 the top,        ``mi.render(...)`` (H, W, C), the same seed;    test_render_is_mitsubas_image_for_each_sensor
column 0 the left; ``sensor=k``        per sensor of a two-sensor scene
camera: ``look_at(origin, target,      the image predicted pixel by pixel from a       test_small_spheres_appear_where_a_pinhole_camera_puts_them
up)``, ``fov`` (axis x by default,     pinhole camera worked out by hand (rays cast
or y), pixel (i, j) covers             through each pixel, hit against the spheres)
[j, j+1) x [i, i+1)
PNG/EXR written: top-left stays        Pillow (PNG), ``mi.Bitmap`` (EXR)               test_written_png_and_exr_keep_rows_and_columns
top-left, PNG holds sRGB codes
PNG/EXR read: (C, H, W) row 0 the      files written by Pillow (PNG) and               test_read_png_and_exr_keep_rows_and_columns
file's first row                       ``mi.Bitmap`` (EXR)
=====================================  ==============================================  ==========================================================

(Mitsuba's ``rotate`` takes the axis as given: it does not normalise it, so the references
below pass it a unit axis; torchir normalises ``rotation_axis`` itself.) The units of a run's
``result.yaml`` are pinned the same way in tests/training/test_result_units.py.
"""
from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

import torchir
from torchir.derived import rigid_transform, rotation_matrix
from torchir.functions import render


def T() -> mi.ScalarTransform4f:
    """An identity Mitsuba transform (made when called: Mitsuba needs its variant set first)."""
    return mi.ScalarTransform4f()


ANGLES = (30.0, -50.0, 70.0)  # degrees about x, y, z: no two orders (nor a negated angle) agree
OBLIQUE_AXIS = (0.3, 1.0, -0.2)


def _linear(transform) -> np.ndarray:
    """The (3, 3) linear part of a Mitsuba transform, in float64."""
    return np.array(transform.matrix, dtype=np.float64)[:3, :3]


def _mitsuba_euler(x: float, y: float, z: float) -> np.ndarray:
    return _linear(T().rotate([0, 0, 1], z) @ T().rotate([0, 1, 0], y) @ T().rotate([1, 0, 0], x))


def _mitsuba_pose(pivot, translation, angles, scale: float):
    """Mitsuba's transform of a rigid pose: rotate and scale about ``pivot``, then translate."""
    x, y, z = angles
    return (T().translate([p + t for p, t in zip(pivot, translation)])
            @ T().rotate([0, 0, 1], z) @ T().rotate([0, 1, 0], y) @ T().rotate([1, 0, 0], x)
            @ T().scale(scale) @ T().translate([-p for p in pivot]))


# ------------------------------------------------------------------------------ rotations
@pytest.mark.parametrize("angles", [ANGLES, (-120.0, 10.0, 200.0)])
def test_euler_rotation_is_mitsubas_rz_ry_rx_in_degrees(angles):
    """``rotation_matrix`` of three angles is x first, then y, then z (``R = Rz Ry Rx``), each
    in degrees and counter-clockwise about its axis, as Mitsuba's ``rotate`` composes them (and
    scipy's extrinsic "xyz"). Any other order, radians, or one negated sine differs by more
    than 0.1 in some entry at these angles (checked below, so the test can tell them apart)."""
    ours = rotation_matrix(torch.tensor(angles, dtype=torch.float64)).cpu().numpy()
    np.testing.assert_allclose(ours, _mitsuba_euler(*angles), atol=1e-6)
    np.testing.assert_allclose(ours, Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), atol=1e-12)
    x, y, z = angles
    others = {
        "Rx Ry Rz": _linear(T().rotate([1, 0, 0], x) @ T().rotate([0, 1, 0], y) @ T().rotate([0, 0, 1], z)),
        "Ry Rz Rx": _linear(T().rotate([0, 1, 0], y) @ T().rotate([0, 0, 1], z) @ T().rotate([1, 0, 0], x)),
        "x negated": _mitsuba_euler(-x, y, z), "y negated": _mitsuba_euler(x, -y, z), "z negated": _mitsuba_euler(x, y, -z),
    }
    for name, other in others.items():
        assert np.abs(other - ours).max() > 0.1, name


def test_axis_angle_rotation_is_mitsubas_rotate():
    """One angle (degrees) about an oblique axis (not of unit length: torchir normalises it) is
    Mitsuba's ``rotate(axis, angle)`` about that axis, counter-clockwise (right-hand rule)."""
    axis = np.array(OBLIQUE_AXIS) / np.linalg.norm(OBLIQUE_AXIS)
    for angle in (37.0, -110.0):
        ours = rotation_matrix(torch.tensor([angle], dtype=torch.float64), torch.tensor(OBLIQUE_AXIS, dtype=torch.float64))
        ours = ours.cpu().numpy()
        np.testing.assert_allclose(ours, _linear(T().rotate(axis.tolist(), angle)), atol=1e-6)
        np.testing.assert_allclose(ours, Rotation.from_rotvec(math.radians(angle) * axis).as_matrix(), atol=1e-12)
        assert np.abs(ours - _linear(T().rotate(axis.tolist(), -angle))).max() > 0.1  # the direction tells


# ------------------------------------------------------------------------------ rigid poses
CUBE_CENTER = (0.3, -0.2, 0.5)
RECT_ORIGIN = (0.2, -0.1, 0.4)
POSE = {"translation": (0.1, -0.2, 0.3), "rotation": ANGLES, "scale": 1.3}
PIVOT = (0.5, 0.25, -0.3)


def _cube_load() -> mi.ScalarTransform4f:
    return T().translate(list(CUBE_CENTER)) @ T().rotate([0, 1, 0], 25) @ T().scale([0.2, 0.3, 0.4])


def _rect_load() -> mi.ScalarTransform4f:
    return T().translate(list(RECT_ORIGIN)) @ T().rotate([1, 0, 0], 20) @ T().scale([0.5, 0.3, 1.0])


def _pose_scene(rect_world=None, cube_world=None) -> dict:
    """An 8x8 view of an emitting rectangle and a cube (a mesh: Mitsuba bakes its ``to_world``
    into the vertex positions), each at its load-time pose unless given another."""
    rect_world = _rect_load() if rect_world is None else rect_world
    cube_world = _cube_load() if cube_world is None else cube_world
    return {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": 40, "to_world": T().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "rect": {"type": "rectangle", "to_world": rect_world, "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        "cube": {"type": "cube", "to_world": cube_world, "bsdf": {"type": "diffuse"}},
    }


def _pose_values(name: str) -> dict[str, torch.Tensor]:
    return {f"{name}.translation": torch.tensor(POSE["translation"]), f"{name}.rotation": torch.tensor(POSE["rotation"]),
            f"{name}.scale": torch.tensor([POSE["scale"]])}


@pytest.mark.parametrize("pivot", ["center", PIVOT])
def test_rigid_pose_of_a_mesh_moves_it_as_mitsubas_transform(pivot):
    """``rigid_transform`` of a mesh's vertices (three Euler angles, a translation, a scale) puts
    every vertex where Mitsuba puts it when it loads the mesh with the pose's transform composed
    before the load's own: ``translate(p + t) Rz Ry Rx scale(s) translate(-p)``, ``p`` the pivot
    (``"center"``: the centre of the loaded bounding box, here the cube's centre)."""
    scene = torchir.Scene.from_dict(_pose_scene())
    rigid_transform(scene, "cube", pivot=pivot)
    moved = scene.expand_derived(_pose_values("cube"))["cube.vertex_positions"].reshape(-1, 3).cpu().numpy()
    p = CUBE_CENTER if pivot == "center" else pivot
    native = mi.load_dict(_pose_scene(cube_world=_mitsuba_pose(p, POSE["translation"], POSE["rotation"], POSE["scale"]) @ _cube_load()))
    expected = np.array(mi.traverse(native)["cube.vertex_positions"].numpy()).reshape(-1, 3)  # host: a Dr.Jit array
    np.testing.assert_allclose(moved, expected, atol=2e-6)
    assert np.abs(moved - scene.get("cube.vertex_positions").reshape(-1, 3).cpu().numpy()).max() > 0.3  # it moved


@pytest.mark.parametrize("pivot", ["center", PIVOT])
def test_rigid_pose_of_an_analytic_shape_is_mitsubas_to_world(pivot):
    """``rigid_transform`` of an analytic shape sets ``to_world`` to Mitsuba's pose transform
    times the loaded ``to_world`` (``"center"``: the loaded ``to_world``'s origin)."""
    scene = torchir.Scene.from_dict(_pose_scene())
    rigid_transform(scene, "rect", pivot=pivot)
    ours = scene.expand_derived(_pose_values("rect"))["rect.to_world"].cpu().numpy()
    p = RECT_ORIGIN if pivot == "center" else pivot
    expected = np.array((_mitsuba_pose(p, POSE["translation"], POSE["rotation"], POSE["scale"]) @ _rect_load()).matrix)
    np.testing.assert_allclose(ours, expected, atol=1e-6)


def _bbox(shape) -> np.ndarray:
    box = shape.bbox()
    return np.array([list(box.min), list(box.max)])


def test_bound_pose_is_the_to_world_mitsuba_renders_with():
    """The pose a render binds reaches Mitsuba as that transform (not its transpose): after the
    render, the rectangle's bounding box, as Mitsuba computes it from the ``to_world`` it renders
    with, is the box of the same rectangle loaded by Mitsuba with the pose composed in."""
    scene = torchir.Scene.from_dict(_pose_scene())
    rigid_transform(scene, "rect", pivot=PIVOT)
    with torch.no_grad():
        render(scene, _pose_values("rect"), spp=1)
    assert scene.bound_names == {"rect.to_world"}  # still bound: what the render used
    bound = next(s for s in scene.mi_scene.shapes() if s.id() == "rect")
    native = mi.load_dict(_pose_scene(rect_world=_mitsuba_pose(PIVOT, POSE["translation"], POSE["rotation"], POSE["scale"]) @ _rect_load()))
    expected = _bbox(next(s for s in native.shapes() if s.id() == "rect"))
    np.testing.assert_allclose(_bbox(bound), expected, atol=1e-5)
    assert np.abs(expected - _bbox(next(s for s in mi.load_dict(_pose_scene()).shapes() if s.id() == "rect"))).max() > 0.3


# ------------------------------------------------------------------------------ cameras and images
W, H = 16, 12  # not square: the fov's axis and the aspect ratio matter
SPP = 1024
CAMERAS = (  # sensor 0: Mitsuba's default fov axis (x) and a rolled up vector; sensor 1: fov axis y
    {"origin": (0.3, 0.2, 4.0), "target": (0.1, -0.1, 0.0), "up": (0.15, 1.0, 0.0), "fov": 40.0, "fov_axis": None},
    {"origin": (3.0, 1.5, 2.5), "target": (0.0, 0.2, 0.0), "up": (0.0, 1.0, 0.0), "fov": 35.0, "fov_axis": "y"},
)
SPHERES = {"red": ((-0.6, 0.5, 0.2), 0.3), "green": ((0.5, -0.3, -0.4), 0.25)}  # (centre, radius); channel 0, 1


def _sensor(camera: dict) -> dict:
    sensor = {"type": "perspective", "fov": camera["fov"], "to_world": T().look_at(camera["origin"], camera["target"], camera["up"]),
              "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}}, "sampler": {"type": "independent"}}
    if camera["fov_axis"] is not None:
        sensor["fov_axis"] = camera["fov_axis"]
    return sensor


@pytest.fixture(scope="module")
def spheres() -> torchir.Scene:
    """Two small emitting spheres (radiance 1 in red, 1 in green) seen by two cameras, nothing
    else: with a box filter each pixel's channel is the fraction of its area the sphere covers."""
    scene = {"type": "scene", "integrator": {"type": "direct"}, "sensor": _sensor(CAMERAS[0]), "sensor_1": _sensor(CAMERAS[1])}
    for (name, (center, radius)), colour in zip(SPHERES.items(), ([1, 0, 0], [0, 1, 0])):
        scene[name] = {"type": "sphere", "center": list(center), "radius": radius,
                       "emitter": {"type": "area", "radiance": {"type": "rgb", "value": colour}}}
    return torchir.Scene.from_dict(scene)


def _pinhole_hits(camera: dict, center, radius: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Whether the pinhole ray through film point ``(u, v)`` hits the sphere. The camera by hand:
    it looks from ``origin`` at ``target``; image right is ``forward x up``, image up is
    ``right x forward``; the film spans ``[0, W) x [0, H)``, pixel (i, j) is ``[j, j+1) x
    [i, i+1)``, row 0 at the top; ``fov`` spans its width (axis x) or its height (axis y)."""
    origin, target, up = (np.array(camera[k], dtype=np.float64) for k in ("origin", "target", "up"))
    forward = (target - origin) / np.linalg.norm(target - origin)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half = W / 2 if camera["fov_axis"] in (None, "x") else H / 2  # pixels from the centre to the fov's edge
    focal = half / math.tan(math.radians(camera["fov"]) / 2)  # in pixels
    d = forward + ((u - W / 2) / focal)[..., None] * right - ((v - H / 2) / focal)[..., None] * true_up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = origin - np.array(center)
    b = d @ oc
    return (b * b - (oc @ oc - radius**2) > 0) & (b < 0)  # meets the sphere, in front of the camera


def _pinhole_coverage(camera: dict, center, radius: float, grid: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) fractions of each pixel whose rays hit the sphere, by a ``grid`` x ``grid``
    midpoint rule, and the most that rule can be off: the cells whose corners do not all agree
    (the outline crosses them), plus 4 cells for where the outline's extreme points may poke
    into a cell between two corners (the outline is convex and far wider than a cell)."""
    cells = (np.arange(W * grid) + 0.5) / grid, (np.arange(H * grid) + 0.5) / grid
    mid = _pinhole_hits(camera, center, radius, *np.meshgrid(*cells))
    corners = _pinhole_hits(camera, center, radius, *np.meshgrid(np.arange(W * grid + 1) / grid, np.arange(H * grid + 1) / grid))
    crossed = (corners[:-1, :-1] != corners[1:, :-1]) | (corners[:-1, :-1] != corners[:-1, 1:]) | (corners[:-1, :-1] != corners[1:, 1:])
    per_pixel = lambda a: a.reshape(H, grid, W, grid).mean(axis=(1, 3))  # noqa: E731
    return per_pixel(mid), per_pixel(crossed) + 4 / grid**2


def test_small_spheres_appear_where_a_pinhole_camera_puts_them(spheres):
    """Each sensor's image is the one a pinhole camera worked out by hand predicts, pixel by
    pixel: ``look_at(origin, target, up)`` (a rolled up vector too), ``fov`` across the width by
    default (Mitsuba's fov axis x; sensor 1 sets axis y), row 0 at the top, column 0 at the left.

    The render estimates each pixel's covered fraction ``p`` from ``SPP`` independent uniform
    samples (standard error ``sqrt(p (1 - p) / SPP)``); the hand prediction is off by at most
    its midpoint rule's bound. Each pixel must agree within 4 standard errors plus that bound
    (at most 0.09 here; the largest error measured 0.034). A flipped row or column, the other
    fov axis or the opposite up vector each put some pixel off by 0.67 to 1."""
    for sensor, camera in enumerate(CAMERAS):
        with torch.no_grad():
            image = render(spheres, {}, spp=SPP, seed=11, sensor=sensor).double().cpu().numpy()
        assert image.shape == (3, H, W)
        for channel, (name, (center, radius)) in enumerate(SPHERES.items()):
            expected, rule = _pinhole_coverage(camera, center, radius)
            assert expected.sum() > 3.0  # a sphere of pixels, clear of the image's edges:
            assert expected[[0, -1]].sum() == expected[:, [0, -1]].sum() == 0
            bound = 4 * np.sqrt(expected * (1 - expected) / SPP) + rule
            error = np.abs(image[channel] - expected)
            assert (error <= bound).all(), (sensor, name, float(error.max()), np.argwhere(error > bound).tolist())


def test_render_is_mitsubas_image_for_each_sensor(spheres):
    """``render(scene, sensor=k)`` is ``mi.render(scene, sensor=k)`` with the same seed and spp,
    bit for bit, as (C, H, W) of Mitsuba's (H, W, C): its row 0 and column 0 are Mitsuba's. The
    two sensors' images differ (so ``sensor`` picks one), and the scene has no symmetry a flip
    or a transpose would keep (the other test: the spheres sit off every axis of the image)."""
    images = []
    for sensor in (0, 1):
        with torch.no_grad():
            ours = render(spheres, {}, spp=16, seed=5, sensor=sensor)
        native = mi.render(spheres.mi_scene, sensor=sensor, seed=5, spp=16).torch()
        assert native.shape == (H, W, 3)
        assert torch.equal(ours, native.permute(2, 0, 1).to(ours.device))
        images.append(ours)
    assert not torch.allclose(images[0], images[1])
    for image in images:  # asymmetric: a row flip, a column flip or both would change it
        assert not torch.allclose(image, image.flip(1)) and not torch.allclose(image, image.flip(2))
        assert not torch.allclose(image, image.flip(1, 2))


def _distinct_image() -> torch.Tensor:
    """(3, 5, 7) linear values in (0, 1), different in every pixel and channel: rows in red,
    columns in green, both in blue; on the host, where read_image gives images."""
    y, x = torch.meshgrid(torch.arange(5, device="cpu"), torch.arange(7, device="cpu"), indexing="ij")
    return torch.stack([(y + 1) / 6, (x + 1) / 8, (y * 7 + x + 1) / 36]).float()


def _srgb_codes(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes of linear values in [0, 1] (IEC 61966-2-1), nearest code."""
    encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)
    return np.rint(encoded * 255).astype(np.uint8)


def test_written_png_and_exr_keep_rows_and_columns(tmp_path):
    """``write_image`` of a (C, H, W) image: Pillow reads the PNG as (H, W, C) with the same
    pixel at row 0, column 0 (no flip, no transpose), holding the sRGB codes of the linear
    values; Mitsuba's own reader gives the EXR's linear values in the same places."""
    from torchir.imageio import write_image

    image = _distinct_image()
    expected = image.permute(1, 2, 0).double().cpu().numpy()
    with Image.open(write_image(tmp_path / "x.png", image)) as png:
        assert png.mode == "RGB" and png.size == (7, 5)  # (width, height)
        codes = np.array(png)
    assert np.array_equal(codes, _srgb_codes(expected))
    exr = np.array(mi.Bitmap(str(write_image(tmp_path / "x.exr", image))), dtype=np.float64)
    assert exr.shape == (5, 7, 3)
    np.testing.assert_array_equal(exr, expected.astype(np.float32))


def test_read_png_and_exr_keep_rows_and_columns(tmp_path):
    """``read_image`` of files written outside torchir (a PNG by Pillow, an EXR by Mitsuba):
    (C, H, W) with the file's first row at row 0 and first column at column 0; the PNG's codes
    sRGB-decoded to linear."""
    from torchir.imageio import read_image

    image = _distinct_image()
    hwc = image.permute(1, 2, 0).double().cpu().numpy()
    codes = _srgb_codes(hwc)
    Image.fromarray(codes, "RGB").save(tmp_path / "x.png")
    decoded = codes / 255.0
    linear = np.where(decoded <= 0.04045, decoded / 12.92, ((decoded + 0.055) / 1.055) ** 2.4)
    png = read_image(tmp_path / "x.png")
    assert png.shape == (3, 5, 7)
    np.testing.assert_allclose(png.permute(1, 2, 0).double().cpu().numpy(), linear, atol=1e-6)
    mi.Bitmap(np.ascontiguousarray(hwc.astype(np.float32)), mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "x.exr"))
    assert torch.equal(read_image(tmp_path / "x.exr"), image)
