"""Primary silhouettes sampled on the moving mesh's edges (torchir/integrators/_silhouettes.py):
against finite differences where the silhouette is the whole derivative, against Mitsuba's
``direct_projective`` on a smooth-shaded mesh, with reused light samples, through the ReSTIR
integrator, and at the extremes."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import torchir

torchir.backend.variant()  # the integrator module needs it at import

from torchir.integrators._silhouettes import silhouette_backward, supported  # noqa: E402
from torchir.integrators.restir_di import ReSTIRDirectIntegrator  # noqa: E402
from torchir.scenes import _common  # noqa: E402

RES = 24


def _black_box_scene(res: int = RES, wall: bool = True) -> mi.Scene:
    """A black welded box in front of an emitting wall (radiance 1): the image changes with the
    box's position only at its silhouette, so that is the whole derivative."""
    t = mi.ScalarTransform4f
    scene = {
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": _common.perspective([0, -4, 0.3], [0, 0, 0], [0, 0, 1], 40, res, res, 4),
        "box": _common.welded_box("box", t().rotate([0, 0, 1], 30).rotate([1, 0, 0], 20).scale(0.5),
                                  {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}),
    }
    if wall:
        scene["wall"] = {"type": "rectangle", "to_world": t().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(5),
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
    return mi.load_dict(scene)


class _Translation:
    """``key``'s vertices moved by ``theta * velocity``."""

    def __init__(self, scene: mi.Scene, key: str, velocity) -> None:
        self.params = mi.traverse(scene)
        self.key, self.v0, self.velocity = key, mi.Float(self.params[key]), mi.Vector3f(*velocity)

    def __call__(self, theta) -> None:
        self.params[self.key] = dr.ravel(dr.unravel(mi.Point3f, self.v0) + self.velocity * theta)
        self.params.update()


def _gradients(pose: _Translation, backward, calls: int) -> np.ndarray:
    out = []
    for i in range(calls):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        pose(theta)
        backward(i)
        out.append(dr.grad(theta)[0])
    pose(mi.Float(0.0))
    return np.array(out)


def _vertex_gradients(pose: _Translation, step, calls: int) -> np.ndarray:
    """The derivative along ``pose.velocity`` from ``step(i)`` (a render and its backward pass),
    with the vertices a fresh leaf each call, as torch hands them over."""
    velocity = np.tile(np.array([pose.velocity.x[0], pose.velocity.y[0], pose.velocity.z[0]]), dr.width(pose.v0) // 3)
    out = []
    for i in range(calls):
        vertices = mi.Float(pose.v0)
        dr.enable_grad(vertices)
        pose.params[pose.key] = vertices
        pose.params.update()
        step(i)
        out.append(float(np.dot(np.asarray(dr.grad(vertices)), velocity)))
    pose(mi.Float(0.0))
    return np.array(out)


def _adjoint(res: int, offset: float = 0.0) -> tuple[np.ndarray, mi.TensorXf]:
    a = np.random.default_rng(0).normal(size=(res, res, 3)).astype(np.float32) + offset
    return a, mi.TensorXf(a)


def test_silhouette_of_a_black_box_agrees_with_finite_differences():
    """The box moves along (1, 0, 0.5): central differences of the rendered image (1024 spp,
    common seeds) against 12 calls of 16 samples per pixel, within 4 s.e. of both."""
    scene = _black_box_scene()
    pose = _Translation(scene, "box.vertex_positions", (1.0, 0.0, 0.5))
    adjoint_np, adjoint = _adjoint(RES)
    h, fd = 0.01, []
    for seed in (3, 4):
        pose(mi.Float(h))
        plus = np.asarray(mi.render(scene, spp=1024, seed=seed))
        pose(mi.Float(-h))
        minus = np.asarray(mi.render(scene, spp=1024, seed=seed))
        fd.append(float(((plus - minus) / (2 * h) * adjoint_np).sum()))
    pose(mi.Float(0.0))
    integrator = ReSTIRDirectIntegrator(candidates=1, temporal=False, spatial=False)
    mesh = [s for s in scene.shapes() if s.id() == "box"]
    g = _gradients(pose, lambda i: silhouette_backward(integrator, scene, 0, adjoint, mesh, 16 * RES * RES, 100 + i), 12)
    se = math.sqrt(g.var(ddof=1) / len(g) + (fd[0] - fd[1]) ** 2 / 4)
    assert abs(np.mean(fd)) > 10 * se
    assert abs(g.mean() - np.mean(fd)) < 4 * se, (g.mean(), fd, se)


@pytest.fixture(scope="module")
def pig_problem():
    from torchir.scenes import pig

    scene = mi.load_dict(pig.build(resolution=RES))
    return scene, _Translation(scene, "pig.vertex_positions", (0.0, 0.0, 1.0)), [s for s in scene.shapes() if s.id() == "pig"]


def test_smooth_shaded_silhouette_agrees_with_direct_projective(pig_problem):
    """On the smooth-shaded blob the inside of the silhouette is shaded as seen along its normal
    (see the module): the primary term must agree with ``direct_projective``'s (``sppc=0,
    sppi=0``) within 4 s.e. Shading the grazing view itself gave 0.6x (measured at 64²).
    At 64² with 16 calls each the two differ by 1.3% (6 s.e. there); with the rest of the
    derivative from ``direct_projective`` ours was 1.2 s.e. from finite differences, Mitsuba's
    own 2.4 s.e., so the 1.3% is not resolved here."""
    scene, pose, mesh = pig_problem
    _, adjoint = _adjoint(RES, 1.0)
    ours_integrator = ReSTIRDirectIntegrator(candidates=4, temporal=False, spatial=False)
    ours = _gradients(pose, lambda i: silhouette_backward(ours_integrator, scene, 0, adjoint, mesh, 16 * RES * RES, 200 + i), 12)
    mitsuba = mi.load_dict({"type": "direct_projective", "sppc": 0, "sppi": 0, "guiding": "none"})
    theirs = _gradients(pose, lambda i: mitsuba.render_backward(scene, pose.params, adjoint, seed=300 + i, spp=16), 12)
    se = math.sqrt((ours.var(ddof=1) + theirs.var(ddof=1)) / 12)
    assert abs(theirs.mean()) > 10 * se
    assert abs(ours.mean() - theirs.mean()) < 4 * se, (ours.mean(), theirs.mean(), se)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_reused_light_samples_stay_unbiased(pig_problem):
    """Alg. 5: both sides combined with the reservoirs of an earlier step (the integrator's own,
    at the same pose) against RIS alone, 12 calls each, within 4 s.e."""
    scene, pose, mesh = pig_problem
    _, adjoint = _adjoint(RES, 1.0)
    integrator = ReSTIRDirectIntegrator(candidates=4)
    alone = _gradients(pose, lambda i: silhouette_backward(integrator, scene, 0, adjoint, mesh, 8 * RES * RES, 400 + i), 12)

    def reused(i):
        with dr.suspend_grad():
            _, cache = integrator.step(scene, 0, 500 + i, 1, zero_remainder=False)
        silhouette_backward(integrator, scene, 0, adjoint, mesh, 8 * RES * RES, 400 + i, prev=cache.prev)

    with_reuse = _gradients(pose, reused, 12)
    se = math.sqrt((alone.var(ddof=1) + with_reuse.var(ddof=1)) / 12)
    assert abs(alone.mean()) > 10 * se
    assert abs(with_reuse.mean() - alone.mean()) < 4 * se, (alone.mean(), with_reuse.mean(), se)


def test_silhouette_sampling_through_the_restir_integrator(pig_problem):
    """``silhouette_sampling`` in the integrator's backward pass (driven as torchir's render
    drives it, the vertices a leaf as torch hands them over): the displacement's derivative
    matches the default path (``direct_projective``'s primary term) within 4 s.e."""
    scene, pose, _ = pig_problem
    _, adjoint = _adjoint(RES, 1.0)

    def run(sampling: bool) -> np.ndarray:
        integrator = ReSTIRDirectIntegrator(candidates=4, temporal=False, spatial=False, silhouette_sampling=sampling)

        def step(i):
            _, cache = integrator.step(scene, 0, 600 + i, 4)
            integrator.backward(scene, cache, adjoint, 700 + i, 4, geometry=True, params=pose.params)

        return _vertex_gradients(pose, step, 10)

    ours, default = run(True), run(False)
    se = math.sqrt((ours.var(ddof=1) + default.var(ddof=1)) / 10)
    assert abs(default.mean()) > 8 * se
    assert abs(ours.mean() - default.mean()) < 4 * se, (ours.mean(), default.mean(), se)


def test_silhouette_extremes_give_zero_not_nan():
    """No light in the scene, a zero adjoint, no silhouette in view (the box behind the camera):
    every gradient exactly 0 and finite."""
    scene = _black_box_scene(wall=False)
    pose = _Translation(scene, "box.vertex_positions", (1.0, 0.0, 0.0))
    mesh = [s for s in scene.shapes() if s.id() == "box"]
    integrator = ReSTIRDirectIntegrator(candidates=1, temporal=False, spatial=False)
    _, adjoint = _adjoint(RES)
    black = _gradients(pose, lambda i: silhouette_backward(integrator, scene, 0, adjoint, mesh, 64, i), 2)
    assert (black == 0).all()
    lit = _black_box_scene()
    lit_pose = _Translation(lit, "box.vertex_positions", (1.0, 0.0, 0.0))
    lit_mesh = [s for s in lit.shapes() if s.id() == "box"]
    zero = mi.TensorXf(np.zeros((RES, RES, 3), np.float32))
    assert (_gradients(lit_pose, lambda i: silhouette_backward(integrator, lit, 0, zero, lit_mesh, 64, i), 2) == 0).all()
    behind = _Translation(lit, "box.vertex_positions", (0.0, -10.0, 0.0))  # moved behind the camera
    behind(mi.Float(1.0))
    behind.v0 = mi.Float(behind.params[behind.key])
    g = _gradients(behind, lambda i: silhouette_backward(integrator, lit, 0, adjoint, lit_mesh, 64, i), 2)
    assert np.isfinite(g).all() and (g == 0).all()


def test_silhouette_arguments_and_support():
    scene = _black_box_scene()
    mesh = [s for s in scene.shapes() if s.id() == "box"]
    sensor = scene.sensors()[0]
    integrator = ReSTIRDirectIntegrator(candidates=1)
    _, adjoint = _adjoint(RES)
    assert supported(scene, sensor, mesh)
    assert not supported(scene, sensor, [])
    assert not supported(scene, sensor, [s for s in scene.shapes() if s.id() == "wall"])  # an emitter
    with pytest.raises(ValueError, match="samples"):
        silhouette_backward(integrator, scene, 0, adjoint, mesh, 0, 0)
    with pytest.raises(ValueError, match="candidates"):
        silhouette_backward(integrator, scene, 0, adjoint, mesh, 16, 0, candidates=0)
    gaussian = _common.perspective([0, -4, 0.3], [0, 0, 0], [0, 0, 1], 40, RES, RES, 4)
    gaussian["film"]["rfilter"] = {"type": "gaussian"}  # a pixel is no longer the mean over its square
    assert not supported(scene, mi.load_dict(gaussian), mesh)
    ortho = mi.load_dict({"type": "scene", "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
                          "box": _common.welded_box("box", mi.ScalarTransform4f(), {"type": "diffuse"})})
    assert not supported(ortho, ortho.sensors()[0], [ortho.shapes()[0]])


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_shape_gradient_through_mitsubas_render_op(pig_problem):
    """``mi.render(..., integrator=restir_di)`` then ``dr.backward``: with a mesh's vertices
    moving, the integrator's backward takes the attached shading points and the boundary terms
    (as through torchir's render), and the displacement's derivative matches
    ``direct_projective``'s within 4 s.e. (without them it missed the silhouette and shadow terms)."""
    from torchir.integrators import register

    register()
    scene, pose, _ = pig_problem
    adjoint_np, _ = _adjoint(RES, 1.0)

    def run(integrator) -> np.ndarray:
        def step(i):
            image = mi.render(scene, pose.params, integrator=integrator, spp=16, seed=800 + i)
            dr.backward(dr.sum(mi.TensorXf(adjoint_np) * image, axis=None))

        return _vertex_gradients(pose, step, 10)

    ours = run(mi.load_dict({"type": "restir_di", "candidates": 4, "temporal": False, "spatial": False}))
    theirs = run(mi.load_dict({"type": "direct_projective", "guiding": "none"}))
    se = math.sqrt((ours.var(ddof=1) + theirs.var(ddof=1)) / 10)
    assert abs(theirs.mean()) > 8 * se
    assert abs(ours.mean() - theirs.mean()) < 4 * se, (ours.mean(), theirs.mean(), se)
