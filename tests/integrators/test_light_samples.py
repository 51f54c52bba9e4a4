"""Light samples of ReSTIR DI (torchir/integrators/_light.py) on tiny scenes, against closed forms.

A diffuse plane z = 0 (albedo A) lit by a point light, a spot light and a downward-facing
rectangle emitter; shading points are hit by rays from z = 0.5 (under the occluder, when there
is one, at z = 1). Closed forms: point  f = I / d^2 * A / pi * cos(theta);
area  f = L * A / pi * cos(theta_x) * |n_y . w| / d^2.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import torchir

torchir.backend.set_variant("auto")

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from torchir.integrators import _light  # noqa: E402

ALBEDO = np.array([0.5, 0.4, 0.3])
I_POINT = np.array([3.0, 2.0, 1.0])
I_SPOT = np.array([1.0, 2.0, 4.0])
L_AREA = np.array([2.0, 1.5, 0.5])
P_POINT = np.array([-1.0, -0.1, 1.8])
P_SPOT = np.array([1.5, 0.0, 2.5])
Z_AREA = 2.0
XY = np.array([[0.0, 0.0], [0.3, -0.2], [-0.5, 0.4], [0.1, 0.25]])  # shading points (x, y, 0)
REL = 1e-5


def _lum(rgb):
    return 0.212671 * rgb[..., 0] + 0.715160 * rgb[..., 1] + 0.072169 * rgb[..., 2]


def _scene(occluder: bool = False, weights=(1.0, 2.0, 3.0), lamp_scale: float = 0.5) -> mi.Scene:
    d = {
        "type": "scene",
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2.0, 2.0, 1.0]),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": ALBEDO.tolist()}}},
        "point": {"type": "point", "position": P_POINT.tolist(), "sampling_weight": weights[0],
                  "intensity": {"type": "rgb", "value": I_POINT.tolist()}},
        "spot": {"type": "spot", "cutoff_angle": 30.0, "beam_width": 25.0, "sampling_weight": weights[1],
                 "to_world": mi.ScalarTransform4f().look_at(origin=P_SPOT.tolist(), target=[0, 0, 0], up=[0, 1, 0]),
                 "intensity": {"type": "rgb", "value": I_SPOT.tolist()}},
        "lamp": {"type": "rectangle",  # normal -z (rotated about x), at z = 2, side 1
                 "to_world": mi.ScalarTransform4f().translate([0, 0, Z_AREA]).rotate([1, 0, 0], 180).scale(lamp_scale),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": L_AREA.tolist()},
                             "sampling_weight": weights[2]}},
    }
    if occluder:
        d["occ"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 1.0]).scale(5.0)}
    return mi.load_dict(d)


@pytest.fixture(scope="module")
def scene():
    return _scene()


@pytest.fixture(scope="module")
def occluded():
    return _scene(occluder=True)


def _emitter_index(scene, name):
    cls = {"point": "PointLight", "spot": "SpotLight", "area": "AreaLight"}[name]
    return [str(e).split("[")[0] for e in scene.emitters()].index(cls)


def _rays(xy=XY):
    n = len(xy)
    return mi.Ray3f(mi.Point3f(xy[:, 0], xy[:, 1], np.full(n, 0.5)), mi.Vector3f(0, 0, -1))


def _si(scene, xy=XY):
    si = scene.ray_intersect(_rays(xy))
    assert bool(dr.all(si.is_valid()))
    return si


def _np(x):
    a = np.array(x, dtype=np.float64)
    return a.T if a.ndim > 1 else a


def _points(xy=XY):
    return np.c_[xy, np.zeros(len(xy))]


def _sample(scene, name, p, n=(0.0, 0.0, 0.0), uv=(0.0, 0.0), lanes=len(XY)):
    y = dr.zeros(_light.LightSample(), lanes)
    y.em = mi.UInt32(_emitter_index(scene, name))
    y.p = mi.Point3f(*[np.broadcast_to(np.asarray(p, dtype=np.float32)[..., k], (lanes,)).copy() for k in range(3)])
    y.n = mi.Vector3f(*[np.broadcast_to(np.asarray(n, dtype=np.float32)[..., k], (lanes,)).copy() for k in range(3)])
    y.uv = mi.Point2f(*uv)
    y.delta = mi.Bool(name != "area")
    return y


def _point_closed_form(pos, intensity, xs=_points()):
    to = pos - xs
    d2 = (to * to).sum(1)
    cos = to[:, 2] / np.sqrt(d2)
    return intensity[None] / d2[:, None] * ALBEDO[None] / math.pi * cos[:, None]


def _area_closed_form(py, xs=_points()):
    to = py - xs
    d2 = (to * to).sum(1)
    cos_x = to[:, 2] / np.sqrt(d2)
    cos_y = to[:, 2] / np.sqrt(d2)  # n_y = -z, w = to / d: |n_y . w| = to_z / d
    return L_AREA[None] * ALBEDO[None] / math.pi * (cos_x * cos_y / d2)[:, None]


def _check(f, p_hat, expected):
    np.testing.assert_allclose(_np(f), expected, rtol=REL, atol=0)
    np.testing.assert_allclose(_np(p_hat), _lum(expected), rtol=REL, atol=0)


def test_struct_types():
    ls, res = _light.LightSample(), _light.Reservoirs()
    assert ls.DRJIT_STRUCT == {"em": mi.UInt32, "p": mi.Point3f, "n": mi.Vector3f, "uv": mi.Point2f, "delta": mi.Bool}
    assert res.DRJIT_STRUCT["y"] is ls
    assert list(res.DRJIT_STRUCT) == ["y", "W", "M", "w_sum", "shape", "prim", "prim_uv", "o", "d", "t", "offset", "p",
                                      "n", "valid"]
    assert res.DRJIT_STRUCT["offset"] is mi.Point2f
    assert [res.DRJIT_STRUCT[k] for k in ("W", "M", "w_sum", "t")] == [mi.Float] * 4
    assert [res.DRJIT_STRUCT[k] for k in ("shape", "prim")] == [mi.UInt32] * 2
    assert res.DRJIT_STRUCT["prim_uv"] is mi.Point2f and res.DRJIT_STRUCT["valid"] is mi.Bool
    assert res.DRJIT_STRUCT["o"] is mi.Point3f and res.DRJIT_STRUCT["p"] is mi.Point3f
    assert res.DRJIT_STRUCT["d"] is mi.Vector3f and res.DRJIT_STRUCT["n"] is mi.Vector3f
    assert _light.LightSample() is ls  # cached per variant
    assert _light.FORWARD_FLAGS == mi.RayFlags.UV | mi.RayFlags.ShadingFrame


def test_point_light_closed_form(scene):
    si = _si(scene)
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "point", P_POINT), mi.Bool(True))
    _check(f, p_hat, _point_closed_form(P_POINT, I_POINT))


def test_spot_light_closed_form(scene):
    si = _si(scene)  # all within 12 degrees of the axis, in the 25 degree beam: falloff 1
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "spot", P_SPOT), mi.Bool(True))
    _check(f, p_hat, _point_closed_form(P_SPOT, I_SPOT))


def test_area_light_closed_form(scene):
    py = np.array([[0.1, 0.2, Z_AREA], [-0.2, 0.1, Z_AREA], [0.0, -0.3, Z_AREA], [0.25, 0.0, Z_AREA]])
    si = _si(scene)
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "area", py, n=(0.0, 0.0, -1.0)), mi.Bool(True))
    _check(f, p_hat, _area_closed_form(py))
    # behind the one-sided emitter (its normal facing away from the shading point): zero
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "area", py, n=(0.0, 0.0, 1.0)), mi.Bool(True))
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)


def test_occluder_and_visibility_flag(occluded):
    si = _si(occluded)
    y = _sample(occluded, "point", P_POINT)
    f, p_hat = _light.eval_target(occluded, si, y, mi.Bool(True))
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)
    f, p_hat = _light.eval_target(occluded, si, y, mi.Bool(True), visibility=False)
    _check(f, p_hat, _point_closed_form(P_POINT, I_POINT))


def test_inactive_lanes_and_on_light(scene):
    si = _si(scene)
    active = mi.Bool([True, False, True, False])
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "point", P_POINT), active)
    expected = _point_closed_form(P_POINT, I_POINT) * np.array([1, 0, 1, 0])[:, None]
    _check(f, p_hat, expected)
    assert np.all(_np(f)[[1, 3]] == 0)
    assert list(active) == [True, False, True, False]  # the caller's mask is not modified
    # a light sample at the shading point itself: zero, not NaN
    pts = _points()
    for name, n in (("point", (0.0, 0.0, 0.0)), ("area", (0.0, 0.0, -1.0))):
        f, p_hat = _light.eval_target(scene, si, _sample(scene, name, pts, n=n), mi.Bool(True))
        assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)
    # invalid shading points (missed rays): zero
    miss = scene.ray_intersect(mi.Ray3f(mi.Point3f([5.0] * 4, [0.0] * 4, [0.5] * 4), mi.Vector3f(0, 0, -1)))
    f, p_hat = _light.eval_target(scene, miss, _sample(scene, "point", P_POINT), mi.Bool(True))
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)


def test_spot_outside_cone_is_zero(scene):
    xy = np.array([[1.9, 1.9], [-1.9, 1.9], [1.9, -1.9], [-1.9, -1.9]])  # 33 to 52 degrees off the axis (cutoff 30)
    si = _si(scene, xy)
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "spot", P_SPOT), mi.Bool(True))
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)


@pytest.mark.parametrize("occ", [False, True])
def test_sample_candidate_matches_emitter_sampling(occ):
    scene = _scene(occluder=occ)
    m = 64
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.2, 1.2, (m, 2))
    si = _si(scene, xy)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, m)
    u = sampler.next_2d()
    ds, spec = scene.sample_emitter_direction(si, u, False)
    sampler.seed(7, m)
    active = mi.Bool(np.arange(m) % 5 != 4)
    y, f, p_hat, w = _light.sample_candidate(scene, si, sampler, active)
    assert list(active) == list(np.arange(m) % 5 != 4)  # the caller's mask is not modified
    act = np.arange(m) % 5 != 4
    # the light sample is the emitter's own
    np.testing.assert_allclose(_np(y.p)[act], _np(ds.p)[act], rtol=REL, atol=1e-6)
    np.testing.assert_allclose(_np(y.n)[act], _np(ds.n)[act], rtol=REL, atol=1e-6)
    np.testing.assert_allclose(_np(y.uv)[act], _np(ds.uv)[act], rtol=REL, atol=1e-6)
    assert np.array_equal(np.array(y.delta)[act], np.array(ds.delta)[act])
    em = np.array(y.em)
    pts = np.array(ds.p).T
    is_area = em == _emitter_index(scene, "area")
    assert np.array_equal(is_area[act], ~np.array(ds.delta)[act])
    np.testing.assert_allclose(pts[act & is_area, 2], Z_AREA, rtol=REL)
    np.testing.assert_allclose(pts[act & (em == _emitter_index(scene, "point"))] - P_POINT[None], 0, atol=1e-6)
    np.testing.assert_allclose(pts[act & (em == _emitter_index(scene, "spot"))] - P_SPOT[None], 0, atol=1e-6)
    # f = Le fs g (and eval_target agrees at y), w = p̂ / p_c, p_c = pdf_sel pdf_dir (delta ? 1 : g)
    f_ref, p_ref = _light.eval_target(scene, si, y, mi.Bool(True), visibility=True)
    f_ref, p_ref = _np(f_ref) * act[:, None], _np(p_ref) * act
    np.testing.assert_allclose(_np(f), f_ref, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(_np(p_hat), p_ref, rtol=1e-4, atol=1e-7)
    dsp = np.array(ds.pdf, dtype=np.float64)  # = pdf_sel * pdf_dir (solid angle)
    to = pts - _points(xy)
    d2 = (to * to).sum(1)
    g = np.where(np.array(ds.delta), 1.0, np.abs((_np(ds.n) * to).sum(1)) / d2 ** 1.5)
    # area: solid-angle pdf = area pdf * d^2 / |cos_y|, so pdf_sel * pdf_area = dsp * g
    p_c = np.where(np.array(ds.delta), dsp, dsp * g)
    # NEE: w = lum(spec * fs * V)
    fs = _np(si.bsdf().eval(mi.BSDFContext(), si, si.to_local(ds.d), True))
    nee = _lum(_np(spec) * fs)
    vis = p_ref > 0
    np.testing.assert_allclose(_np(w), np.where(act & vis, nee, 0.0), rtol=1e-4, atol=1e-7)
    ok = p_c > 0
    np.testing.assert_allclose(_np(w)[ok] * p_c[ok], _np(p_hat)[ok], rtol=1e-4, atol=1e-7)
    # with_inv_pc: the same candidate plus 1 / p_c on every sampled lane, also where p̂ = 0
    sampler.seed(7, m)
    *same, inv_pc = _light.sample_candidate(scene, si, sampler, active, with_inv_pc=True)
    np.testing.assert_array_equal(_np(same[3]), _np(w))
    np.testing.assert_allclose(_np(inv_pc), np.where(act & ok, 1.0 / np.where(ok, p_c, 1.0), 0.0), rtol=1e-4)
    if occ:
        assert np.all(_np(f) == 0) and np.all(_np(w) == 0)
        sampler.seed(7, m)
        y2, f2, p2, w2 = _light.sample_candidate(scene, si, sampler, mi.Bool(True), visibility=False)
        assert np.all(_np(p2) > 0) and np.all(_np(w2) > 0)
        f_ref, _ = _light.eval_target(scene, si, y2, mi.Bool(True), visibility=False)
        np.testing.assert_allclose(_np(f2), _np(f_ref), rtol=1e-4, atol=1e-7)
    else:
        assert np.all(_np(p_hat)[act] > 0) and np.all(_np(p_hat)[~act] == 0) and np.all(_np(w)[~act] == 0)
        assert len(set(em[act].tolist())) == 3  # all three emitters are drawn


@pytest.mark.parametrize("positive_only", [True, False, None])
def test_black_surface_gradient_needs_positive_only_off(positive_only):
    """Albedo 0: f = 0, but df/dA = Le g cos / pi (per channel). ``positive_only=False`` keeps
    those lanes (value 0, gradient intact); the default (None here: not passed) and True drop
    them (p̂ = 0), gradient 0."""
    black = mi.load_dict({
        "type": "scene",
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([2.0, 2.0, 1.0]),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}},
        "point": {"type": "point", "position": P_POINT.tolist(), "intensity": {"type": "rgb", "value": I_POINT.tolist()}},
    })
    params = mi.traverse(black)
    key = "plane.bsdf.reflectance.value"
    albedo = mi.Color3f(0.0)
    dr.enable_grad(albedo)
    params[key] = albedo
    params.update()
    si = _si(black)
    kw = {} if positive_only is None else {"positive_only": positive_only}
    f, p_hat = _light.eval_target(black, si, _sample(black, "point", P_POINT), mi.Bool(True), **kw)
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)
    dr.backward(dr.sum(f.x + f.y + f.z))
    want = _point_closed_form(P_POINT, I_POINT) / ALBEDO  # Le g cos / pi, per channel
    assert (want > 0).all()
    np.testing.assert_allclose(_np(dr.grad(albedo)).ravel(), want.sum(0) if positive_only is False else 0.0, rtol=1e-4)


@pytest.mark.parametrize("lamp_scale", [0.2, 0.8])
def test_inv_pc_of_a_lamp_of_another_area(lamp_scale):
    """``with_inv_pc`` on a lamp whose area 4 s^2 is not 1 (so p_c = pdf_sel / area is not 1/pdf_sel,
    and the area-measure pdf is not its reciprocal), every shading point occluded (p̂ = 0):
    1 / p_c = (sum of the weights / the emitter's weight) * (delta ? 1 : area), on every lane."""
    scene = _scene(occluder=True, lamp_scale=lamp_scale)
    m = 48
    xy = np.random.default_rng(4).uniform(-0.4, 0.4, (m, 2))
    si = _si(scene, xy)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(11, m)
    y, f, p_hat, w, inv_pc = _light.sample_candidate(scene, si, sampler, mi.Bool(True), with_inv_pc=True)
    assert np.all(_np(p_hat) == 0) and np.all(_np(w) == 0)
    em = np.array(y.em)
    weight = {_emitter_index(scene, "point"): 1.0, _emitter_index(scene, "spot"): 2.0, _emitter_index(scene, "area"): 3.0}
    area = 4 * lamp_scale ** 2
    want = np.array([6.0 / weight[e] * (area if e == _emitter_index(scene, "area") else 1.0) for e in em])
    assert len(set(em.tolist())) == 3  # all three emitters are drawn
    np.testing.assert_allclose(_np(inv_pc), want, rtol=1e-4)


def test_sample_candidate_selection_weights():
    """Emitter chosen by sampling_weight: only the area light drawn when it alone has weight."""
    scene = _scene(weights=(0.0, 0.0, 1.0))
    m = 16
    si = _si(scene, np.random.default_rng(1).uniform(-0.5, 0.5, (m, 2)))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(1, m)
    y, f, p_hat, w = _light.sample_candidate(scene, si, sampler, mi.Bool(True))
    assert np.all(np.array(y.em) == _emitter_index(scene, "area")) and not any(y.delta)
    py = _np(y.p)
    np.testing.assert_allclose(_np(f), _area_closed_form(py, _points(_np(si.p)[:, :2])), rtol=1e-4)
    # p_c = pdf_sel * pdf_area = 1 * 1 (unit square): w = p̂
    np.testing.assert_allclose(_np(w), _np(p_hat), rtol=1e-4)
    assert np.all(_np(p_hat) > 0)


def test_rebuild_interaction_matches_ray_intersection(scene):
    rng = np.random.default_rng(2)
    m = 8
    xy = rng.uniform(-1.5, 1.5, (m, 2))
    ray = _rays(xy)
    pi = scene.ray_intersect_preliminary(ray)
    si = pi.compute_surface_interaction(ray)
    r = dr.zeros(_light.Reservoirs(), m)
    r.shape, r.prim, r.prim_uv = pi.shape_index, pi.prim_index, pi.prim_uv
    r.o, r.d, r.t = ray.o, ray.d, pi.t
    r.valid = mi.Bool(np.arange(m) != 3)
    active = mi.Bool(np.arange(m) != 5)
    for flags in (mi.RayFlags.All, _light.FORWARD_FLAGS):
        rb = _light.rebuild_interaction(scene, r, active, flags)
        ok = (np.arange(m) != 3) & (np.arange(m) != 5)
        assert list(rb.is_valid()) == list(ok)
        np.testing.assert_allclose(_np(rb.p)[ok], _np(si.p)[ok], rtol=REL, atol=1e-6)
        np.testing.assert_allclose(_np(rb.uv)[ok], _np(si.uv)[ok], rtol=REL, atol=1e-6)
        np.testing.assert_allclose(_np(rb.sh_frame.n)[ok], _np(si.sh_frame.n)[ok], rtol=REL, atol=1e-6)
        np.testing.assert_allclose(np.array(rb.t)[ok], np.array(si.t)[ok], rtol=REL)
    assert list(active) == list(np.arange(m) != 5)
    ptr = _light.shape_pointers(scene, mi.UInt32(pi.shape_index), mi.Bool(np.arange(m) != 1))
    assert dr.all(ptr.is_emitter() == si.shape.is_emitter() & mi.Bool(np.arange(m) != 1))
    # the shape of the second scene shape (the lamp) is an emitter, the plane is not
    idx = mi.UInt32([i for i in range(len(scene.shapes()))])
    ptr = _light.shape_pointers(scene, idx, mi.Bool(True))
    assert list(ptr.is_emitter()) == [s.is_emitter() for s in scene.shapes()]
    # inactive lanes give null pointers (not the indexed shape)
    ptr = _light.shape_pointers(scene, idx, mi.Bool(False))
    assert not any(ptr.is_emitter()) and any(s.is_emitter() for s in scene.shapes())


def test_close_light_sample(scene):
    """Light samples closer than 1 to the shading point are evaluated, not dropped."""
    py = _points() + np.array([0.1, -0.05, 0.5])
    si = _si(scene)
    f, p_hat = _light.eval_target(scene, si, _sample(scene, "area", py, n=(0.0, 0.0, -1.0)), mi.Bool(True))
    _check(f, p_hat, _area_closed_form(py))


def test_degenerate_distance_is_zero_not_inf():
    """A light sample 2e-19 away from the shading point (dist^2 = 4e-38, Le = I / dist^2 overflows
    to inf): zero, not inf/NaN, with or without the shadow ray."""
    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle"},
                          "point": {"type": "point", "position": [0, 0, 1], "intensity": 1e4}})
    si = _si(scene)
    si.p = mi.Point3f(0.0, 0.0, 0.0)
    y = _sample(scene, "point", np.array([0.0, 0.0, 2e-19]))
    for vis in (True, False):
        f, p_hat = _light.eval_target(scene, si, y, mi.Bool(True), visibility=vis)
        assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0)


@pytest.mark.parametrize("vis", [True, False])
def test_candidate_at_point_light_is_zero_not_nan(vis):
    """A shading point exactly on a point light (sampled: dist 0, weight inf): zero, never NaN."""
    scene = _scene(weights=(1.0, 0.0, 0.0))
    si = _si(scene)
    si.p = mi.Point3f(*P_POINT.tolist())
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(3, len(XY))
    y, f, p_hat, w = _light.sample_candidate(scene, si, sampler, mi.Bool(True), visibility=vis)
    assert np.all(np.array(y.em) == _emitter_index(scene, "point"))
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0) and np.all(_np(w) == 0)


@pytest.mark.parametrize("vis", [True, False])
def test_candidate_degenerate_distance_is_zero_not_inf(vis):
    """A point light 2e-19 from the shading point: weight = I / dist^2 and f overflow to inf;
    the candidate is dropped (f = p̂ = w = 0), never inf."""
    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle"},
                          "point": {"type": "point", "position": [0, 0, 2e-19], "intensity": 1e4}})
    si = _si(scene)
    si.p = mi.Point3f(0.0, 0.0, 0.0)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(5, len(XY))
    y, f, p_hat, w = _light.sample_candidate(scene, si, sampler, mi.Bool(True), visibility=vis)
    assert np.all(_np(f) == 0) and np.all(_np(p_hat) == 0) and np.all(_np(w) == 0)
