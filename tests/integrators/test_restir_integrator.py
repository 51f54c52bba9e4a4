"""``torchir/integrators/restir_di.py`` on 8x8 scenes, fast enough for its mutation run.

Two scenes share one geometry (a textured floor, a tilted panel whose normal fails the 0.9
normal test against the floor, a small blocker casting a shadow, and background pixels):

- ``point``: a single point light. Every light sample is then that point, so W = 1 on every
  lit shading point for every configuration (RIS: w_sum / (M p̂) with w = p̂ / 1; reuse: the
  1/Z weights with Z counting exactly the neighbours whose reservoirs could hold it): each
  configuration's image equals plain next-event estimation on the same camera rays, exactly.
- ``multi``: a point light, a spot light and an area light seen by the camera: plain RIS is
  checked against an independent implementation of streaming RIS (Alg. A1) on the same
  random numbers, and reuse against a converged ``prb`` reference, with bounds from the
  spread of independent chains (standard error of the image mean).
"""
from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
import time

import torchir  # noqa: I001  (before torch)

torchir.backend.set_variant("auto")

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from torchir import backend  # noqa: E402
from torchir.integrators import _knn, _light, _restir_pass, _restir_state, restir_di  # noqa: E402
from torchir.integrators.restir_di import ReSTIRDirectIntegrator, check_scene  # noqa: E402

from tests.helpers import raised_message as _msg  # noqa: E402

RES = 8
T = mi.ScalarTransform4f
TEX = np.array([[[0.8, 0.5, 0.3], [0.3, 0.6, 0.7]], [[0.5, 0.5, 0.5], [0.9, 0.2, 0.4]]])
KEY = "floor.bsdf.reflectance.data"
SPOT = "spot.intensity.value"


def _dict(multi: bool, res: int = RES) -> dict:
    from torchir.scenes._common import bitmap, perspective

    d = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": 2},
        "sensor": perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 50.0, res, res),
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": bitmap(TEX)}},
        "tilt": {"type": "rectangle", "to_world": T().translate([0.9, 0, 0.2]).rotate([0, 1, 0], -60).scale(0.5),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}},
        "blocker": {"type": "rectangle", "to_world": T().translate([-0.3, 0.3, 0.6]).scale(0.15), "bsdf": {"type": "diffuse"}},
        "point": {"type": "point", "position": [-1.2, 0.8, 1.2], "intensity": {"type": "rgb", "value": [3.0, 2.5, 2.0]}},
    }
    if multi:
        d["spot"] = {"type": "spot", "to_world": T().look_at(origin=[0.8, -0.6, 1.8], target=[0.2, -0.2, 0], up=[0, 1, 0]),
                     "intensity": {"type": "rgb", "value": [8.0, 9.0, 10.0]}, "cutoff_angle": 25.0}
        d["panel"] = {"type": "rectangle", "to_world": T().translate([-0.5, -0.6, 0.4]).scale(0.2),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [3.0, 2.0, 1.0]}}}
    return d


@pytest.fixture(autouse=True)
def _no_gc_inside_a_test():
    """Python's cyclic garbage collector running during a ``dr.freeze`` recording aborted the
    process under mutmut's trampolines (which allocate more): collect between tests only."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


@pytest.fixture(scope="module")
def point() -> mi.Scene:
    return mi.load_dict(_dict(False))


@pytest.fixture(scope="module")
def multi() -> mi.Scene:
    return mi.load_dict(_dict(True))


def _np(x) -> np.ndarray:
    return np.array(x, dtype=np.float64)


def _camera(scene: mi.Scene, seed: int, spp: int):
    """Mitsuba's camera-ray convention (``ADIntegrator.sample_rays``, box filter): lane i is
    pixel i // spp, row-major; the sampler's first 2D sample jitters the pixel position."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    n = w * h * spp
    sampler = sensor.sampler().fork()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n)
    pix = np.repeat(np.arange(w * h), spp)
    jitter = sampler.next_2d()
    pos = mi.Point2f((mi.Float((pix % w).astype(np.float32)) + jitter.x) / w,
                     (mi.Float((pix // w).astype(np.float32)) + jitter.y) / h)
    ray, weight = sensor.sample_ray_differential(0.0, 0.0, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(mi.Ray3f(ray))
    return sampler, si, mi.Color3f(weight), (h, w)


def _image(lanes: mi.Color3f, spp: int, hw) -> np.ndarray:
    return _np(lanes).T.reshape(hw[0], hw[1], spp, 3).mean(2)


def _mitsuba_camera(scene: mi.Scene, seed: int, spp: int):
    """As ``_camera``, with Mitsuba's own ``ADIntegrator.sample_rays`` (which draws an aperture
    sample for a thin lens, then a time sample for an open shutter) on the sampler a step seeds."""
    from mitsuba.python.ad.integrators.common import ADIntegrator

    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    sampler = sensor.sampler().fork()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, w * h * spp)
    ray, weight, _ = ADIntegrator.sample_rays(None, scene, sensor, sampler)
    return sampler, scene.ray_intersect(mi.Ray3f(ray)), mi.Color3f(weight), (h, w)


def _nee(scene: mi.Scene, seed: int, spp: int, camera=_camera) -> np.ndarray:
    """Next-event estimation with Mitsuba's own emitter sampling (visibility tested)."""
    sampler, si, weight, hw = camera(scene, seed, spp)
    valid = si.is_valid()
    ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(valid), True, valid)
    fs = si.bsdf().eval(mi.BSDFContext(), si, si.to_local(ds.d), valid)
    return _image(weight * (si.emitter(scene).eval(si, valid) + dr.select(valid, em_weight * fs, 0.0)), spp, hw)


def _ris(scene: mi.Scene, seed: int, spp: int, candidates: int, shadowed: bool):
    """Streaming RIS written from Alg. A1: candidate m is kept with probability w_m / w_sum;
    W = w_sum / (M p̂(y)); the unshadowed target tests the kept sample's visibility once."""
    sampler, si, weight, hw = _camera(scene, seed, spp)
    valid = si.is_valid()
    n = dr.width(valid)
    y = dr.zeros(_light.LightSample(), n)
    f, phat, w_sum = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
    for _ in range(candidates):
        y_m, f_m, phat_m, w_m = _light.sample_candidate(scene, si, sampler, valid, visibility=shadowed)
        w_sum += w_m
        keep = valid & (sampler.next_1d(valid) * w_sum < w_m)
        y, f, phat = dr.select(keep, y_m, y), dr.select(keep, f_m, f), dr.select(keep, phat_m, phat)
    if not shadowed:
        seen = valid & (phat > 0) & ~scene.ray_test(si.spawn_ray_to(y.p), valid & (phat > 0))
        f = dr.select(seen, f, 0.0)
        w_sum = dr.select(seen, w_sum, 0.0)
    W = dr.select(phat > 0, w_sum / (candidates * dr.select(phat > 0, phat, 1.0)), 0.0)
    img = _image(weight * (si.emitter(scene).eval(si, valid) + f * W), spp, hw)
    return img, {"W": _np(W), "w_sum": _np(w_sum), "em": _np(y.em), "valid": _np(valid), "p": _np(si.p)}


def _integrator(**kw) -> ReSTIRDirectIntegrator:
    return ReSTIRDirectIntegrator(**kw)


B1 = {"candidates": 1, "temporal": False, "spatial": False, "burn_in": 0}


# ------------------------------------------------------------------------------ options
def test_defaults_and_initial_state():
    i = ReSTIRDirectIntegrator()
    names = ("candidates", "neighbors", "radius", "normal_threshold", "m_cap", "temporal", "spatial", "burn_in",
             "grad_paths", "forward_only", "nn_backend", "target", "freeze", "multiview", "spp_chains",
             "offset_lifetime", "light_guide")
    got = {k: getattr(i, k) for k in names}
    assert got == {"candidates": 16, "neighbors": 8, "radius": 0.0, "normal_threshold": 0.9, "m_cap": 32.0,
                   "temporal": True, "spatial": True, "burn_in": 32, "grad_paths": "decorrelated", "forward_only": False,
                   "nn_backend": "auto", "target": "shadowed", "freeze": torchir.backend.frozen_renders(),
                   "multiview": "auto", "spp_chains": True, "offset_lifetime": 0.0, "light_guide": 0.0}
    assert i.options == restir_di.ReSTIROptions()
    assert type(i.m_cap) is float and type(i.radius) is float and type(i.normal_threshold) is float
    assert i.states == {} and i.last == {} and i.timings == {} and i.stats == {}
    assert i.last_pass_frozen is False and i._frozen_pass is None and i._last_pass is None
    assert i.shadowed and i.reuse and i._neighbour_search.backend == "auto"
    assert i.to_string() == ("ReSTIRDirectIntegrator[candidates=16, neighbors=8, temporal=True, spatial=True, "
                             "grad_paths='decorrelated']")
    assert _integrator(candidates=3).m_cap == 6.0 and _integrator(candidates=3, m_cap=7).m_cap == 7.0
    j = _integrator(temporal=0, spatial=1, target="unshadowed", forward_only=1, freeze=0, nn_backend="grid")
    assert (j.temporal, j.spatial, j.forward_only, j.freeze) == (False, True, True, False)
    assert not j.shadowed and j.reuse and j._neighbour_search.backend == "grid"
    assert not _integrator(temporal=False, spatial=False).reuse and _integrator(spatial=False).reuse
    assert _integrator(candidates=np.int64(5), burn_in=0, m_cap=0).candidates == 5


def test_properties_and_their_overrides():
    props = mi.Properties()
    props["candidates"] = 5
    props["temporal"] = False
    props["radius"] = 0.5
    props["max_depth"] = 2
    i = ReSTIRDirectIntegrator(props)
    assert (i.candidates, i.temporal, i.radius, i.m_cap, i.neighbors) == (5, False, 0.5, 10.0, 8)
    i = ReSTIRDirectIntegrator(props, candidates=7)
    assert (i.candidates, i.temporal, i.m_cap) == (7, False, 14.0)
    props["max_depth"] = 3
    assert _msg(ValueError, ReSTIRDirectIntegrator, props) == (
        "ReSTIR direct illumination renders direct light only: max_depth must be 2")


def test_option_errors(monkeypatch):
    known = sorted(f.name for f in dataclasses.fields(restir_di.ReSTIROptions))
    assert _msg(TypeError, _integrator, spp=2, candidatez=1) == (
        f"unknown ReSTIR option(s) ['candidatez', 'spp'] (did you mean 'candidates'?); known: {known}")
    assert _msg(TypeError, _integrator, candidates=2.0) == "candidates must be an int, got float"
    assert _msg(TypeError, _integrator, candidates=True) == "candidates must be an int, got bool"
    assert _msg(TypeError, _integrator, neighbors="4") == "neighbors must be an int, got str"
    assert _msg(ValueError, _integrator, candidates=0) == "candidates must be >= 1, got 0"
    assert _msg(ValueError, _integrator, neighbors=0) == "neighbors must be >= 1, got 0"
    assert _msg(ValueError, _integrator, m_cap=-1) == "m_cap must be >= 0, got -1"
    assert _msg(ValueError, _integrator, burn_in=-1) == "burn_in must be >= 0, got -1"
    assert _integrator(neighbors=1, burn_in=0, candidates=1).neighbors == 1
    assert _msg(ValueError, _integrator, multiview="shared") == "multiview must be 'auto', 'per_sensor' or 'carry_over', got 'shared'"
    for bad in (-0.5, float("inf"), float("nan")):
        assert _msg(ValueError, _integrator, radius=bad) == f"radius must be >= 0 (0 = automatic), got {bad}"
    assert _msg(ValueError, _integrator, grad_paths="both") == "grad_paths must be 'shared' or 'decorrelated', got 'both'"
    assert _msg(ValueError, _integrator, nn_backend="ball") == "nn_backend must be 'auto', 'kdtree', 'grid' or 'screen', got 'ball'"
    assert _msg(ValueError, _integrator, target="visible") == "target must be 'shadowed' or 'unshadowed', got 'visible'"
    assert _integrator(grad_paths="decorrelated").grad_paths == "decorrelated"
    for backend in ("kdtree", "grid", "screen"):
        assert _integrator(nn_backend=backend).nn_backend == backend
    monkeypatch.setattr(_knn, "have_scipy", lambda: False)
    assert _msg(ValueError, _integrator, nn_backend="kdtree") == (
        "nn_backend='kdtree' needs scipy (pip install scipy); use 'grid' or 'auto'")
    assert _integrator(nn_backend="grid").nn_backend == "grid"


def _with(res: int = 4, **changes) -> mi.Scene:
    """The point scene (a fresh dict: loading consumes its texture) with entries replaced."""
    d = _dict(False, res=res)
    d.update(changes)
    return mi.load_dict(d)


def test_check_scene(point, monkeypatch):
    check_scene(point)
    base = _dict(False, res=4)
    for depth in (0, 1, 2):
        check_scene(_with(4, integrator={"type": "prb", "max_depth": depth}))
    check_scene(_with(4, integrator={"type": "path"}))  # no max_depth attribute: not checked here
    for depth in (3, -1):  # prb keeps max_depth unsigned: -1 (no limit) reads 2^32 - 1
        assert _msg(ValueError, check_scene, _with(4, integrator={"type": "prb", "max_depth": depth})) == (
            f"the scene's integrator renders indirect light (max_depth={depth % 2**32}); ReSTIR handles direct "
            f"illumination only: use a direct-illumination scene (max_depth=2, e.g. 'painting', 'oxalis_lite')")

    class Signed:  # an integrator whose max_depth is signed
        max_depth = -1

    class Proxy:
        def __init__(self, scene):
            self.scene = scene

        def __getattr__(self, name):
            return getattr(self.scene, name)

        def integrator(self):
            return Signed()

    assert "(max_depth=-1)" in _msg(ValueError, check_scene, Proxy(point))
    Signed.max_depth = 0
    check_scene(Proxy(point))
    assert _msg(ValueError, check_scene, _with(4, env={"type": "constant"})) == (
        "ReSTIR direct illumination does not support environment emitters (envmap, constant) yet")
    medium = dict(base["blocker"], interior={"type": "homogeneous"})
    assert _msg(ValueError, check_scene, _with(4, blocker=medium)) == (
        "ReSTIR direct illumination does not support participating media (volumes)")
    medium = dict(base["blocker"], exterior={"type": "homogeneous"})
    assert "participating media" in _msg(ValueError, check_scene, _with(4, blocker=medium))
    sensor = dict(base["sensor"], film=dict(base["sensor"]["film"], rfilter={"type": "gaussian"}))
    assert _msg(ValueError, check_scene, _with(4, sensor=sensor)) == (
        "ReSTIR direct illumination needs a box reconstruction filter on every film")
    second = _with(4, sensor2=sensor)  # the second of two films
    assert "box reconstruction filter" in _msg(ValueError, check_scene, second)
    for variant in ("llvm_ad_spectral", "llvm_ad_rgb_polarized", "scalar_mono"):
        monkeypatch.setattr(mi, "variant", lambda v=variant: v)
        assert _msg(ValueError, check_scene, point) == f"ReSTIR direct illumination supports RGB variants only, not {variant!r}"


# ------------------------------------------------------------------------------ plain RIS, exact
@pytest.mark.parametrize("target", ["shadowed", "unshadowed"])
def test_one_candidate_is_next_event_estimation(multi, target):
    """B.1: one candidate, W = 1 / p_c: Mitsuba's NEE on the same random numbers, both targets
    (the unshadowed one tests the chosen sample's visibility), spp 1 and 2 (block mean)."""
    i = _integrator(target=target, **B1)
    for seed, spp in ((3, 1), (4, 2)):
        img, cache = i.step(multi, 0, seed, spp)
        want = _nee(multi, seed, spp)
        assert want.max() > 1.0 and (want == 0).any()  # the panel is in view; so is the background
        np.testing.assert_allclose(_np(img), want, rtol=1e-5, atol=1e-6)
        assert cache.prev is None and i.states[0].prev is None and i.last_pass_frozen


@pytest.mark.parametrize("target", ["shadowed", "unshadowed"])
def test_streaming_ris_equals_algorithm_a1(multi, target, monkeypatch):
    """Three candidates: image and reservoirs (W, w_sum, light, shading point, M) equal Alg. A1
    on the same random numbers, unrolled and as a symbolic loop (more than
    ``UNROLLED_CANDIDATES``, or a wavefront of at most ``SYMBOLIC_UP_TO_LANES``)."""
    want, res = _ris(multi, 5, 2, 3, target == "shadowed")
    assert len(np.unique(res["em"][res["W"] > 0])) == 3  # every light is chosen somewhere
    for unrolled, symbolic_lanes in ((32, 0), (2, 0), (32, 10**9)):
        monkeypatch.setattr(_restir_pass, "UNROLLED_CANDIDATES", unrolled)
        monkeypatch.setattr(_restir_pass, "SYMBOLIC_UP_TO_LANES", symbolic_lanes)
        i = _integrator(candidates=3, temporal=False, spatial=False, burn_in=0, target=target, freeze=unrolled == 2)
        img, cache = i.step(multi, 0, 5, 2)
        np.testing.assert_allclose(_np(img), want, rtol=1e-5, atol=1e-6)
        r = cache.lanes
        np.testing.assert_allclose(_np(r.W), res["W"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(_np(r.w_sum), res["w_sum"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(_np(r.p).T[res["valid"] > 0], res["p"].T[res["valid"] > 0], atol=1e-6)
        assert np.array_equal(_np(r.y.em)[res["W"] > 0], res["em"][res["W"] > 0])
        assert np.array_equal(_np(r.valid), res["valid"])
        assert np.array_equal(_np(r.M), 3.0 * res["valid"])
        assert np.array_equal(_np(r.shape)[res["valid"] > 0] >= 0, np.ones(int(res["valid"].sum()), bool))
    mi_r = ReSTIRDirectIntegrator(**B1)
    img, _ = mi_r.step(multi, 0, 5, 2)
    assert not np.allclose(_np(img), want)  # the candidates count


def test_render_api(point):
    i = _integrator(**B1)
    sensor = point.sensors()[0]
    want = _nee(point, 2, 4)  # the sensor's sampler has 4 samples per pixel
    np.testing.assert_allclose(_np(i.render(point, seed=2)), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_np(i.render(point, sensor=sensor, seed=2, spp=4)), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_np(i.render(point, sensor=np.int64(0), seed=2, spp=1)), _nee(point, 2, 1), rtol=1e-5, atol=1e-6)
    assert set(i.last) == {0} and i.last[0].spp == 1 and i.last[0].sensor == 0
    other = mi.load_dict(_dict(False, res=4)).sensors()[0]
    assert _msg(ValueError, i.render, point, sensor=other) == "the sensor does not belong to the scene"
    assert _msg(NotImplementedError, i.render_forward, point, None) == "ReSTIR DI implements reverse mode only (render_backward)"
    grad = mi.TensorXf(np.ones((RES, RES, 3), np.float32))
    assert _msg(RuntimeError, _integrator().render_backward, point, None, grad) == "render_backward() needs a render() of the same sensor first"


def test_thin_lens_camera_with_an_open_shutter(point):
    """A defocused thin-lens camera whose shutter is open: the step draws the aperture sample,
    then the time, as Mitsuba's ``sample_rays``, so B.1 is NEE on Mitsuba's own camera rays
    (and not on the pinhole rays through the lens centre)."""
    base = _dict(False, res=4)
    lens = dict(base["sensor"], type="thinlens", aperture_radius=0.4, focus_distance=1.0,
                shutter_open=0.0, shutter_close=0.5)
    scene = _with(4, sensor=lens)
    sensor = scene.sensors()[0]
    assert sensor.needs_aperture_sample() and sensor.shutter_open_time() == 0.5
    img, _ = _integrator(**B1, freeze=False).step(scene, 0, 4, 2)  # (Mitsuba 3.9's thinlens cannot be frozen)
    want = _nee(scene, 4, 2, camera=_mitsuba_camera)
    assert want.max() > 0.1 and (want == 0).any()
    np.testing.assert_allclose(_np(img), want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(_np(img), _nee(scene, 4, 2), rtol=0.05)  # the check can tell the lens apart
    np.testing.assert_allclose(_nee(point, 4, 2, camera=_mitsuba_camera), _nee(point, 4, 2), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------ reuse, exact on one point light
REUSE = {"both": {}, "temporal": {"spatial": False}, "spatial": {"temporal": False}}


@pytest.mark.parametrize("target", ["shadowed", "unshadowed"])
def test_reuse_of_one_point_light_is_exact(point, target):
    """With one point light W = 1 wherever it is seen, for every reuse mode, so each step's
    image equals NEE on the same camera rays (a wrong Z, m_i or p̂ gives W != 1)."""
    lit_frac = []
    for mode, opts in REUSE.items():
        i = _integrator(candidates=2, neighbors=4, burn_in=2, target=target, **opts)
        for seed in range(3):
            img, cache = i.step(point, 0, seed, 2)
            np.testing.assert_allclose(_np(img), _nee(point, seed, 2), rtol=1e-5, atol=1e-6, err_msg=mode)
            W = _np(cache.lanes.W)
            assert np.all((W == 0) | (np.abs(W - 1) < 1e-5)), mode
            lit_frac.append((W > 0).mean())
        n_ok = _np(i._last_pass[1].neighbor_count)
        assert n_ok.sum() > 0 and n_ok.max() == (1 if mode == "temporal" else 4), mode
    assert 0.3 < min(lit_frac) and max(lit_frac) < 0.9  # shadow and background both present


def _m_and_count(i):
    out, stats = i._last_pass
    return _np(out.M), _np(stats.neighbor_count), _np(out.valid)


def test_m_bookkeeping_and_caps(point):
    """M = min(M_0 + sum of the valid neighbours' min(M_i, cap), cap): fresh reservoirs have
    M = candidates (0 on background lanes)."""
    i = _integrator(candidates=3, neighbors=4, burn_in=0, m_cap=100, spatial=False, nn_backend="grid")
    i.step(point, 0, 0, 1)
    M, count, valid = _np(i.states[0].prev.M), None, _np(i.states[0].prev.valid)
    assert np.array_equal(M, 3.0 * valid) and i._last_pass[1].neighbor_count is None
    i.step(point, 0, 1, 1)
    M, count, valid = _m_and_count(i)
    assert count.max() == 1 and count.sum() > 0.5 * valid.sum()
    assert np.array_equal(M, 3.0 * (1 + count) * valid)
    i.step(point, 0, 2, 1)
    M, count, valid = _m_and_count(i)
    assert M.max() == 9.0 and np.all(M <= 3.0 * (1 + 2 * count))
    j = _integrator(candidates=3, neighbors=4, burn_in=0, m_cap=100, temporal=False)
    for seed in range(2):
        j.step(point, 0, seed, 1)
        M, count, valid = _m_and_count(j)
        assert count.max() == 4 and np.array_equal(M, 3.0 * (1 + count) * valid)
    k = _integrator(candidates=3, neighbors=4, burn_in=0, m_cap=5, temporal=False)
    k.step(point, 0, 0, 1)
    M, count, valid = _m_and_count(k)
    assert np.array_equal(M, np.minimum(3.0 * (1 + count), 5.0) * valid) and M.max() == 5.0
    d = _integrator(candidates=3, neighbors=4, burn_in=0)  # default cap 2 x candidates, temporal + spatial
    d.step(point, 0, 0, 1)
    d.step(point, 0, 1, 1)
    M, count, valid = _m_and_count(d)
    assert np.array_equal(M, np.minimum(3.0 * (1 + count), 6.0) * valid)
    assert count.max() == 4 and ((count > 0) & (count < 4)).any()


def test_neighbour_tests(point):
    """Spatial reuse never counts the lane itself (a radius that holds no other point gives
    no neighbour); the normal test drops all (threshold above 1) or none of the neighbours a
    threshold of -1 keeps; the tilted panel and the floor are not each other's neighbours."""
    def counts(**kw):
        i = _integrator(candidates=1, neighbors=4, burn_in=0, temporal=False, **kw)
        i.step(point, 0, 0, 1)
        return _m_and_count(i)

    M, count, valid = counts(radius=1e-6)
    assert count.max() == 0 and np.array_equal(M, valid)
    _, none, _ = counts(radius=0.5, normal_threshold=1.01)
    _, some, _ = counts(radius=0.5, normal_threshold=0.9)
    _, every, valid = counts(radius=0.5, normal_threshold=-1.01)
    assert none.max() == 0 and (some <= every).all() and (some < every).any()
    assert every.max() == 4 and (every[valid > 0] > 0).all()


# ------------------------------------------------------------------------------ reuse, unbiased
@pytest.fixture(scope="module")
def reference(multi):
    """Converged direct illumination (prb, max_depth 2): image means of 4 independent renders."""
    imgs = np.stack([_np(mi.render(multi, spp=256, seed=1000 + s)) for s in range(4)])
    means = imgs.reshape(4, -1).mean(1)
    return float(means.mean()), float(means.std(ddof=1) / 2.0)


@pytest.mark.parametrize("mode, target", [("both", "shadowed"), ("both", "unshadowed"), ("temporal", "shadowed"),
                                          ("spatial", "shadowed")])
def test_reuse_is_unbiased(multi, reference, mode, target):
    """Mean of 10 independent chains' image means (burn-in 2, 4 steps, spp 2) against the
    reference: within 4 standard errors of the difference, the chains' spread giving theirs."""
    ref, ref_se = reference
    chains = []
    for c in range(12):
        i = _integrator(candidates=2, neighbors=3, burn_in=2, target=target, **REUSE[mode])
        chains.append(np.mean([_np(i.step(multi, 0, 100 * c + s, 2)[0]).mean() for s in range(4)]))
    chains = np.array(chains)
    se = math.hypot(chains.std(ddof=1) / math.sqrt(len(chains)), ref_se)
    assert se < 0.03 * ref  # power: a 12 % bias lies 4 standard errors away
    assert abs(chains.mean() - ref) < 4 * se


# ------------------------------------------------------------------------------ steps and state
def test_burn_in_and_step_state(point, monkeypatch):
    i = _integrator(candidates=1, neighbors=2, burn_in=3)
    calls = []
    original = i.sample_paths

    def spy(scene, sensor, seed, spp, prev, st, prev_camera=None, zero_remainder=False):
        calls.append((seed, prev, prev_camera, zero_remainder))
        return original(scene, sensor, seed, spp, prev, st, prev_camera, zero_remainder)

    monkeypatch.setattr(i, "sample_paths", spy)
    t0 = time.perf_counter()
    img, cache = i.step(point, 0, 7, 2)
    elapsed = time.perf_counter() - t0
    assert 0 < i.timings["burn_in"] <= elapsed  # a duration within the step
    seeds = [c[0] for c in calls]
    assert len(calls) == 4 and seeds[-1] == 7 and len(set(seeds)) == 4  # three burn-in passes, then the step
    assert seeds[:3] == [int(mi.sample_tea_32(7, 0x5EED0000 + b)[0]) for b in range(3)]
    assert calls[0][1] is None and calls[0][2] is None and calls[1][1] is not None and calls[3][1] is not None
    assert [c[3] for c in calls] == [False] * 3 + [True]  # the remainder: the step's own pass only
    assert cache.zero is not None and i.step(point, 0, 7, 2, zero_remainder=False)[1].zero is None
    calls.clear()
    i.reset()
    img, cache = i.step(point, 0, 7, 2)
    st = i.states[0]
    camera = (tuple(np.array(point.sensors()[0].world_transform().matrix).ravel().tolist()), RES, RES, 2)
    assert st.camera == camera and calls[3][2] == camera and cache.prev_camera == camera
    assert calls[1][2] == calls[2][2] == camera  # later burn-in passes search the previous one's screen
    assert st.steps == 1 and st.prev is cache.lanes and cache.prev is calls[3][1] and cache.spp == 2 and cache.sensor == 0
    assert dr.width(cache.lanes.W) == RES * RES * 2
    assert st.lights == i._emitter_watch(point) and set(i.timings) >= {"burn_in"} and i.timings["burn_in"] > 0
    calls.clear()
    img2, cache2 = i.step(point, 0, 8, 1)  # another spp: another lane layout
    assert len(calls) == 1 and cache2.prev is cache.lanes and cache2.prev_camera == camera
    assert dr.width(cache2.lanes.W) == RES * RES and st.steps == 2 and st.camera == camera[:3] + (1,)
    assert not i.last_pass_frozen  # the temporal neighbours of another layout: searched in world space
    i.reset()
    assert i.states == {} and i.last == {}
    calls.clear()
    i.step(point, 0, 9, 1)
    assert len(calls) == 4 and i.states[0].steps == 1
    for opts in ({"temporal": False}, {"burn_in": 0}):
        j = _integrator(candidates=1, neighbors=2, **{"burn_in": 3, **opts})
        seen = []
        monkeypatch.setattr(j, "sample_paths", lambda *a, _o=j.sample_paths, _s=seen: _s.append(a) or _o(*a))
        j.step(point, 0, 0, 1)
        assert len(seen) == 1 and j.timings["burn_in"] < i.timings["burn_in"] + 1.0, opts
        assert (j.states[0].prev is None) == ("temporal" in opts) and j.states[0].lights == (
            None if "temporal" in opts else j._emitter_watch(point))


def test_a_light_switched_on_pauses_temporal_reuse(multi):
    params = mi.traverse(multi)
    spot = mi.Color3f(params[SPOT])
    i = _integrator(candidates=2, neighbors=2, burn_in=1)
    try:
        params[SPOT] = mi.Color3f(0.0)
        params.update()
        _, first = i.step(multi, 0, 0, 1)
        _, second = i.step(multi, 0, 1, 1)
        assert first.prev is not None and second.prev is first.lanes
        params[SPOT] = spot
        params.update()
        _, on = i.step(multi, 0, 2, 1)
        assert on.prev is None and i._last_pass[1].neighbor_count is None  # no reuse on that step
        _, after = i.step(multi, 0, 3, 1)
        assert after.prev is on.lanes and i._last_pass[1].neighbor_count is not None
    finally:
        params[SPOT] = spot
        params.update()


def test_topology_change_resets_and_sensors_keep_their_own_state(point):
    i = _integrator(candidates=1, neighbors=2, burn_in=1)
    i.step(point, 0, 0, 1)
    i.step(point, 0, 1, 1)
    assert i.states[0].steps == 2 and i.states[0].signature == (1, (2, 2, 2))
    i.states[0].signature = (-1,)
    i.step(point, 0, 2, 1)
    assert i.states[0].steps == 1 and i.states[0].signature == (1, (2, 2, 2))
    st = i.state(point, 1)
    assert st is i.states[1] and st.steps == 0 and st.prev is None and i.state(point, 1) is st


def test_stats(point, multi):
    i = _integrator(candidates=2, neighbors=3, burn_in=1)
    i.step(multi, 0, 0, 2)
    out, pstats = i._last_pass
    v = _np(out.valid) > 0
    M, W, count = _np(out.M)[v], _np(out.W)[v], _np(pstats.neighbor_count)
    assert pstats.k == 3 and (W == 0).any() and W.max() > 0
    want = {"mean_M": M.mean(), "max_M": M.max(), "frac_W0": (W <= 0).mean(), "max_W": W.max(),
            "valid_neighbors": count.sum() / (3 * v.sum())}
    assert i.stats == pytest.approx(want, rel=1e-6)
    assert 0 < want["valid_neighbors"] < 1
    j = _integrator(**B1)
    j.step(multi, 0, 0, 2)
    assert j.stats["valid_neighbors"] == 0.0 and j._last_pass[1].k == 0 and j.stats["max_M"] == 1.0
    from torchir.scenes._common import perspective

    away = _with(4, sensor=perspective([0, 0, 3.0], [0, 0, 6.0], [0, 1, 0], 30.0, 4, 4))  # sees nothing
    k = _integrator(candidates=1, neighbors=2, burn_in=1)
    img, _ = k.step(away, 0, 0, 1)
    assert k.stats == {"mean_M": 0.0, "max_M": 0.0, "frac_W0": 0.0, "max_W": 0.0, "valid_neighbors": 0.0}
    assert _np(img).max() == 0 and k.states[0].radius == 1e-2 and k.states[0].window == 2


def test_footprints_and_radius(point):
    """The pixel footprint of a plane facing the camera at distance 3 (fov 50 over 8 pixels)
    is b = 3 * 2 tan(25°) / 8 at the centre and b cos(view angle) off-centre (down to 0.835 b
    in the corners)."""
    base = 3 * 2 * math.tan(math.radians(25)) / RES
    flat = mi.load_dict(_with_only_floor())
    radius, small = _restir_pass.footprints(flat, flat.sensors()[0], 0, 2, RES, RES)
    assert 2 * base * 0.95 <= radius <= 2 * base * 1.001 and base * 0.83 <= small <= base * 0.95
    assert small < radius / 2
    for opt, window in ((1e-3, 1), (1.5 * small, 2), (100.0, 3), (0.0, 3)):  # ceil(radius / small footprint) in [1, 3]
        i = _integrator(candidates=1, neighbors=2, burn_in=0, radius=opt)
        i.step(flat, 0, 0, 2)
        st = i.states[0]
        assert st.radius == (opt if opt else pytest.approx(radius, rel=0.05)) and st.window == window
        r0 = st.radius
        i.step(flat, 0, 1, 1)
        assert st.radius == r0  # resolved once


def _with_only_floor() -> dict:
    d = _dict(False)
    del d["tilt"], d["blocker"]
    d["floor"] = dict(d["floor"], to_world=T().scale(4.0))
    return d


def test_state_dict_round_trip(point):
    a = _integrator(candidates=2, neighbors=2, burn_in=1)
    for s in range(2):
        a.step(point, 0, s, 1)
    state = a.state_dict()
    d = state[0]
    assert set(d) == {"radius", "window", "steps", "signature", "camera", "lights", "reservoirs", "guide"}
    assert d["guide"] is None  # no light guide: nothing to keep
    assert d["steps"] == 2 and d["camera"] == a.states[0].camera and d["lights"] == a.states[0].lights
    res = d["reservoirs"]
    assert set(res) == {"y.em", "y.p", "y.n", "y.uv", "y.delta", "W", "M", "w_sum", "shape", "prim", "prim_uv",
                        "o", "d", "t", "offset", "p", "n", "valid"}
    assert res["y.p"].shape == (RES * RES, 3) and res["prim_uv"].shape == (RES * RES, 2) and res["W"].shape == (RES * RES,)
    assert np.array_equal(res["W"], _np(a.states[0].prev.W).astype(np.float32))
    assert np.array_equal(res["y.p"], _np(a.states[0].prev.y.p).T.astype(np.float32))
    W = _np(a.states[0].prev.W)
    for leaf in ("W", "M", "t"):
        res[leaf][:] = 0.0  # the state dict is a copy: writing to it leaves the reservoirs alone
    assert np.array_equal(_np(a.states[0].prev.W), W) and _np(a.states[0].prev.M).max() == 4.0
    state = a.state_dict()
    res = state[0]["reservoirs"]
    b = _integrator(candidates=2, neighbors=2, burn_in=1)
    b.load_state_dict(state)
    sb = b.states[0]
    assert (sb.radius, sb.window, sb.steps, sb.signature, sb.camera, sb.lights) == (
        d["radius"], d["window"], 2, d["signature"], d["camera"], d["lights"])
    for path, value in b.state_dict()[0]["reservoirs"].items():
        assert value.dtype == res[path].dtype and value.tobytes() == res[path].tobytes(), path  # bits: NaN on misses
    ia, ca = a.step(point, 0, 5, 1)
    ib, cb = b.step(point, 0, 5, 1)
    assert np.array_equal(_np(ia), _np(ib)) and np.array_equal(_np(ca.lanes.W), _np(cb.lanes.W))
    old = {0: {k: v for k, v in d.items() if k not in ("camera", "window", "lights")}, "1": {**d, "reservoirs": None}}
    old[0]["signature"] = list(old[0]["signature"])
    c = _integrator()
    c.states[3] = None
    c.load_state_dict(old)
    assert set(c.states) == {0, 1}
    assert (c.states[0].window, c.states[0].camera, c.states[0].lights) == (2, None, None)
    assert c.states[0].signature == d["signature"] and c.states[1].prev is None and c.states[1].camera == d["camera"]
    assert isinstance(c.states[1].camera[0], tuple) and c.states[1].lights == d["lights"]
    assert c.state_dict()[1]["reservoirs"] is None  # a state without reservoirs saves as None
    e = _integrator(**B1)  # no temporal reuse: no reservoirs kept
    e.step(point, 0, 0, 1)
    assert e.states[0].prev is None and e.state_dict()[0]["reservoirs"] is None and e.state_dict()[0]["steps"] == 1


# ------------------------------------------------------------------------------ frozen pass
def test_frozen_and_traced_passes_agree(multi, settled_registry):
    """Replayed passes render what traced ones do; reuse replays only with the screen search,
    and a pass after another lane layout (spp) runs traced."""
    params = mi.traverse(multi)
    base = mi.Transform4f(params["blocker.to_world"])
    out, flags, searches = {}, {}, {}
    for freeze, backend in ((False, "grid"), (True, "screen"), (True, "kdtree"), (True, "auto")):
        i = _integrator(candidates=2, neighbors=2, burn_in=1, nn_backend=backend, freeze=freeze)
        out[freeze, backend], flags[freeze, backend], searches[freeze, backend] = [], [], []
        for s, (spp, moved) in enumerate(((1, False), (1, False), (1, True), (1, True), (2, True))):
            params["blocker.to_world"] = mi.Transform4f(base).translate([0.1, 0, 0]) if moved else base
            params.update()
            img, _ = i.step(multi, 0, s, spp)
            out[freeze, backend].append(_np(img))
            flags[freeze, backend].append(i.last_pass_frozen)
            searches[freeze, backend].append(i._neighbour_search.last)
            stages = set(i.timings) - {"burn_in"}
            assert stages == ({"pass"} if i.last_pass_frozen else {"ris", "nn", "combine", "develop"})
            assert all(type(v) is float and v >= 0 for v in i.timings.values())  # durations, not placeholders
    params["blocker.to_world"] = base
    params.update()
    assert flags[False, "grid"] == [False] * 5
    assert flags[True, "screen"] == flags[True, "auto"] == [True, True, False, True, False]
    assert flags[True, "kdtree"] == [False] * 5
    assert searches[True, "screen"][:4] == ["screen"] * 4  # traced (step 3) with the same lane layout too
    assert searches[True, "screen"][4] == _knn._default_backend()  # another spp: searched in world space
    for key in out:
        for a, b in zip(out[False, "grid"], out[key]):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(out[True, "screen"][1], out[True, "screen"][3])
    b2 = _integrator(candidates=2, temporal=False, spatial=False)
    b2.step(multi, 0, 0, 1)
    assert b2.last_pass_frozen and b2._neighbour_search.last is None and set(b2.timings) == {"burn_in", "pass"}
    for seed in (1, 2):  # the seed is an opaque input: replayed, not recorded again per seed
        b2.step(multi, 0, seed, 1)
    assert b2.last_pass_frozen and b2._frozen_pass.n_recordings == 1
    grid = _integrator(candidates=2, temporal=False, spatial=False, nn_backend="grid")
    grid.step(multi, 0, 0, 1)
    assert grid.last_pass_frozen  # no reuse: frozen whatever the neighbour search


def test_a_failing_frozen_pass_falls_back_loudly(point, monkeypatch):
    """A frozen pass that raises: one warning, the pass runs traced (the same image) and the
    integrator stays unfrozen from then on (no second attempt, no second warning)."""
    import warnings

    i = _integrator(**B1)
    attempts = []

    def broken(*args):
        attempts.append(args)
        raise RuntimeError("replay failed")

    def ready(scene, geometry):
        i._frozen_pass = broken
        return True

    monkeypatch.setattr(i, "_frozen_pass_ready", ready)
    with pytest.warns(UserWarning) as record:
        img, cache = i.step(point, 0, 2, 2)
    assert [str(w.message) for w in record] == [
        "frozen ReSTIR pass failed (RuntimeError('replay failed')); this integrator now runs unfrozen"]
    np.testing.assert_allclose(_np(img), _nee(point, 2, 2), rtol=1e-5, atol=1e-6)
    assert len(attempts) == 1 and i.freeze is False and not i.last_pass_frozen and cache.zero is not None
    assert set(i.timings) == {"burn_in", "ris", "develop"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        img, _ = i.step(point, 0, 3, 2)
    np.testing.assert_allclose(_np(img), _nee(point, 3, 2), rtol=1e-5, atol=1e-6)
    assert len(attempts) == 1 and not i.last_pass_frozen


# ------------------------------------------------------------------------------ gradients
def _texel_gradient(scene, seed, spp, weights):
    """d(sum(weights * image)) / d(texel): the B.1 image is linear in the texture (bilinear
    lookup), so the gradient is image(t + e) - image(t) on the same random numbers."""
    params = mi.traverse(scene)
    tex = np.array(params[KEY])
    i = _integrator(**B1)
    base = (_np(i.step(scene, 0, seed, spp)[0]) * weights).sum()
    out = np.zeros_like(tex, dtype=np.float64)
    try:
        for idx in np.ndindex(*tex.shape):
            t = tex.copy()
            t[idx] += 1.0
            params[KEY] = mi.TensorXf(t)
            params.update()
            out[idx] = (_np(i.step(scene, 0, seed, spp)[0]) * weights).sum() - base
    finally:
        params[KEY] = mi.TensorXf(tex)
        params.update()
    return out


@contextlib.contextmanager
def _texture_bound(params, value):
    """``value`` bound as the texture ``KEY`` within the block (yielded); the original again after it."""
    tex = mi.TensorXf(params[KEY])
    params[KEY] = value
    params.update()
    try:
        yield value
    finally:
        params[KEY] = tex
        params.update()


def _texture_with_grad(params):
    """The texture ``KEY`` as a fresh differentiable variable within the block (yielded)."""
    value = mi.TensorXf(params[KEY])
    dr.enable_grad(value)
    return _texture_bound(params, value)


def _black_texture(params):
    """The texture ``KEY`` all 0 within the block."""
    return _texture_bound(params, mi.TensorXf(np.zeros_like(np.array(params[KEY]))))


def _backward(scene, i, weights, seed, spp, seed_grad, spp_grad, steps=2):
    params = mi.traverse(scene)
    for s in range(steps - 1):
        i.step(scene, 0, seed + 100 + s, spp)
    with _texture_with_grad(params) as value:
        image, cache = i.step(scene, 0, seed, spp)
        i.backward(scene, cache, mi.TensorXf(weights.astype(np.float32)), seed_grad, spp_grad)
        return _np(dr.grad(value)), _np(image)


@pytest.mark.parametrize("target", ["shadowed", "unshadowed"])
def test_albedo_gradient(point, target):
    """On the point-light scene every configuration's image is NEE on its camera rays, so its
    gradient is that of B.1: of the image's seed (``shared``), or of ``seed_grad`` and
    ``spp_grad`` (``decorrelated``, the default, and ``forward_only``), against exact differences."""
    weights = np.random.default_rng(0).random((RES, RES, 3))
    fd = {(seed, spp): _texel_gradient(point, seed, spp, weights) for seed, spp in ((3, 2), (9, 1))}
    assert not np.allclose(fd[3, 2], fd[9, 1], rtol=0.05)  # the check can tell the paths apart
    carry = {"grad_paths": "decorrelated", "multiview": "carry_over"}  # the pass reads the one store's state
    for opts, want in (({"grad_paths": "shared"}, fd[3, 2]), ({}, fd[9, 1]), ({"forward_only": True}, fd[9, 1]),
                       ({**B1, "grad_paths": "decorrelated"}, fd[9, 1]), ({**B1, "grad_paths": "shared"}, fd[3, 2]),
                       (carry, fd[9, 1])):
        i = _integrator(**{"candidates": 2, "neighbors": 2, "burn_in": 1, "target": target, **opts})
        saved = (i.temporal, i.spatial)
        t0 = time.perf_counter()
        g, _ = _backward(point, i, weights, 3, 2, 9, 1)
        elapsed = time.perf_counter() - t0
        np.testing.assert_allclose(g, want, rtol=2e-4, atol=1e-6, err_msg=str(opts))
        assert (i.temporal, i.spatial) == saved and set(i.states) == ({_restir_state.STORE} if opts is carry else {0})
        assert type(i.timings["backward"]) is float and 0 < i.timings["backward"] <= elapsed  # within the call


@pytest.mark.parametrize("opts", [B1, {"candidates": 3, "neighbors": 2, "burn_in": 1},
                                  {"candidates": 3, "neighbors": 2, "burn_in": 1, "target": "unshadowed"}])
def test_black_texture_gradient_is_the_p_hat_zero_remainder(point, opts):
    """An all-black floor: f = 0 (p̂ = 0, no reservoir holds a sample) but df/dalbedo > 0. The
    remainder (module docstring) draws the first p̂ = 0 candidate, here the point light with
    n0 = M, so every configuration's gradient is NEE's on its camera rays, exactly (the image
    is linear in the texture: differences of the B.1 image); without it, the gradient is 0."""
    weights = np.random.default_rng(1).random((RES, RES, 3))
    with _black_texture(mi.traverse(point)):
        fd = _texel_gradient(point, 3, 2, weights)
        assert (fd > 0).all()
        g, image = _backward(point, _integrator(grad_paths="shared", **opts), weights, 3, 2, 9, 1)  # fd: the image's seed
        np.testing.assert_allclose(g, fd, rtol=2e-4, atol=1e-6)
        i = _integrator(grad_paths="shared", **opts)
        original = i.step
        i.step = lambda *a, **kw: original(*a, **{**kw, "zero_remainder": False})
        g_off, _ = _backward(point, i, weights, 3, 2, 9, 1)
        assert not g_off.any()


def test_zero_remainder_adds_nothing_where_no_value_is_zero(multi):
    """The spot's cone and the panel's back zero f and its derivative together: with a texture
    of no 0 entry the remainder's gradient is exactly 0 (its samples' df = 0), so the step's
    gradient is the same with and without it, on the same random numbers."""
    weights = np.random.default_rng(2).random((RES, RES, 3))
    grads = []
    for remainder in (True, False):
        i = _integrator(candidates=3, neighbors=2, burn_in=1)
        original = i.step
        i.step = lambda *a, _o=original, _r=remainder, **kw: _o(*a, **{**kw, "zero_remainder": _r})
        grads.append(_backward(multi, i, weights, 5, 2, 9, 1)[0])
    assert np.abs(grads[0]).sum() > 0
    # equal up to the order of float32 atomic adds across threads (seen: 2.8e-7 relative on a
    # loaded machine); where the remainder contributes, it changes the gradient by O(1)
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-5, atol=0)


def _remainder_gradient(scene: mi.Scene, seed: int, spp: int, candidates: int, shadowed: bool, weights: np.ndarray):
    """d(sum(weights * image)) / d(texel) of the ``p̂ = 0`` remainder alone, written from the module
    docstring on Alg. A1's random numbers (each candidate, then the draw that decides whether
    the reservoir keeps it): the candidates drawn (1 / p_c > 0) with p̂ = 0 count (n0), the first
    of them is y0, and a lane adds f(y0) n0 / (M p_c(y0)) where y0 is unoccluded.
    Also returns the candidates' emitters, p̂ = 0 and drawn (1 / p_c > 0) masks (M, lanes)."""
    params = mi.traverse(scene)
    with _texture_with_grad(params) as value:
        sampler, si, weight, hw = _camera(scene, seed, spp)
        valid = si.is_valid()
        drawn = []
        with dr.suspend_grad():
            for _ in range(candidates):
                y_m, _, phat_m, _, inv_pc = _light.sample_candidate(scene, si, sampler, valid, visibility=shadowed,
                                                                    with_inv_pc=True)
                sampler.next_1d(valid)
                drawn.append((y_m, _np(phat_m), _np(inv_pc)))
        zero = np.stack([(inv > 0) & (phat == 0) for _, phat, inv in drawn]) & np.array(valid)
        n0 = zero.sum(0)
        first = np.where(zero.any(0), zero.argmax(0), -1)
        y0 = dr.zeros(_light.LightSample(), dr.width(valid))
        inv0 = np.zeros(len(n0))
        for m, (y_m, _, inv) in enumerate(drawn):
            y0 = dr.select(mi.Bool(first == m), y_m, y0)
            inv0 = np.where(first == m, inv, inv0)
        w0 = n0 * inv0 / candidates
        some = mi.Bool(w0 > 0)
        w0 = np.where(np.array(some & ~scene.ray_test(si.spawn_ray_to(y0.p), some)), w0, 0.0)
        f0, _ = _light.eval_target(scene, si, y0, mi.Bool(w0 > 0), visibility=False, positive_only=False)
        adjoint = weights.reshape(-1, 3)[np.arange(len(n0)) // spp] / spp
        contrib = weight * f0 * mi.Float(w0.astype(np.float32))
        dr.backward(dr.sum(dr.dot(contrib, mi.Color3f(*adjoint.T.astype(np.float32)))))
        return (_np(dr.grad(value)), np.stack([np.array(y.em) for y, _, _ in drawn]), zero,
                np.stack([inv > 0 for _, _, inv in drawn]))


@pytest.fixture(scope="module")
def edge_lit() -> mi.Scene:
    """The multi scene plus a fourth light: an area light in the floor's plane, beside it, which
    no floor point can sample (its cosine there is 0: 1 / p_c = 0, a candidate not drawn)."""
    d = _dict(True)
    d["edge"] = {"type": "rectangle", "to_world": T().translate([1.6, 0.0, 0.0]).scale(0.3),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 2.0, 3.0]}}}
    return mi.load_dict(d)


@pytest.mark.parametrize("opts", [{}, {"target": "unshadowed"}, {"temporal": True, "spatial": True, "burn_in": 1},
                                  {"temporal": True, "spatial": True, "burn_in": 1, "grad_paths": "decorrelated"}])
def test_p_hat_zero_remainder_under_four_lights(edge_lit, opts):
    """A black floor under four lights (f = 0 there, so its texels' gradient is the remainder
    alone): the step's gradient (or its decorrelated pass's) equals the remainder written
    independently. On floor lanes some candidates are not drawn (the edge light: 1 / p_c = 0,
    not counted in n0), 1 / p_c = 4 (four lights) for the others, and the first and last p̂ = 0
    candidates are of different lights on some lanes, so the count, 1 / p_c and the first are
    each checked."""
    scene = edge_lit
    opts = {"candidates": 3, "neighbors": 2, "temporal": False, "spatial": False, "burn_in": 0, "grad_paths": "shared", **opts}
    weights = np.random.default_rng(5).random((RES, RES, 3))
    with _black_texture(mi.traverse(scene)):
        seed, spp = (9, 1) if opts.get("grad_paths") == "decorrelated" else (3, 2)
        want, em, zero, drawn = _remainder_gradient(scene, seed, spp, 3, opts.get("target") != "unshadowed", weights)
        n0 = zero.sum(0)
        assert (n0 == 3).any() and np.abs(want).sum() > 0
        assert (~drawn & (n0 > 0)).sum() >= 10  # undrawn candidates beside drawn p̂ = 0 ones (the edge light's)
        last = 2 - zero[::-1].argmax(0)
        lanes = np.arange(zero.shape[1])
        assert ((n0 > 1) & (em[zero.argmax(0), lanes] != em[last, lanes])).any()
        g, _ = _backward(scene, _integrator(**opts), weights, 3, 2, 9, 1)
        np.testing.assert_allclose(g, want, rtol=2e-4, atol=1e-6)


def _gradient_of_step(scene, i, weights, seeds, spp, seed_grad, spp_grad):
    """Steps with ``seeds`` (parameters held still but for the last), then the last one's gradient."""
    params = mi.traverse(scene)
    for seed in seeds[:-1]:
        i.step(scene, 0, seed, spp)
    with _texture_with_grad(params) as value:
        _, cache = i.step(scene, 0, seeds[-1], spp)
        i.backward(scene, cache, mi.TensorXf(weights.astype(np.float32)), seed_grad, spp_grad)
        return _np(dr.grad(value))


def test_decorrelated_and_forward_only_passes_are_steps_on_seed_grad(multi):
    """``decorrelated``: the gradient passes are the steps of a chain of their own, on the
    ``seed_grad`` of each backward (burned in as a first step on the first one would be), never
    reusing the image's reservoirs: its gradients are the ``shared`` ones of an integrator that
    stepped on those seeds alone. ``forward_only``: that of plain RIS's step on ``seed_grad``.
    Under three lights reuse changes the gradient, so both can fail."""
    weights = np.random.default_rng(6).random((RES, RES, 3))
    opts = {"candidates": 2, "neighbors": 2, "burn_in": 1}
    dec = _integrator(grad_paths="decorrelated", **opts)
    dec.step(multi, 0, 103, 2)  # an image step without a backward: the gradient chain does not move
    g_dec = [_gradient_of_step(multi, dec, weights, (s,), 2, g, 2) for s, g in ((3, 9), (4, 11))]
    chain = _integrator(grad_paths="shared", **opts)
    g_chain = [_gradient_of_step(multi, chain, weights, (g,), 2, 0, 1) for g in (9, 11)]
    for a, b in zip(g_dec, g_chain):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert dec.grad_states[0].steps == 2 and dec.states[0].steps == 3
    fwd = _integrator(forward_only=True, **opts)
    g_fwd = _gradient_of_step(multi, fwd, weights, (103, 3), 2, 9, 2)
    assert (fwd.temporal, fwd.spatial) == (True, True) and not fwd.grad_states
    plain = _integrator(**{**opts, "temporal": False, "spatial": False, "grad_paths": "shared"})
    np.testing.assert_allclose(g_fwd, _gradient_of_step(multi, plain, weights, (9,), 2, 0, 1), rtol=1e-5, atol=1e-7)
    assert not np.allclose(g_dec[0], g_fwd, rtol=0.05)  # reuse (the chain's burn-in) changes the gradient


# ------------------------------------------------------------------------------ multi-view (Alg. 8)
def _views_scene() -> mi.Scene:
    """The point scene with four sensors: 0 the original; 1 the same camera, fov 20; 2 under
    the floor looking up (the reservoirs' back side); 3 oblique, the blocker hiding some floor."""
    from torchir.scenes._common import perspective

    d = _dict(False)
    d["sensor1"] = perspective([0, 0, 3.0], [0, 0, 0], [0, 1, 0], 20.0, RES, RES)
    d["sensor2"] = perspective([0, 0, -3.0], [0, 0, 0], [0, 1, 0], 50.0, RES, RES)
    d["sensor3"] = perspective([-1.2, 1.2, 1.2], [0.2, -0.2, 0], [0, 0, 1], 60.0, RES, RES)
    return mi.load_dict(d)


def _seen_reference(scene: mi.Scene, sensor: int, p: np.ndarray, n: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Seen from sensor ``sensor``, computed another way: in its camera frame (Mitsuba cameras
    look down +z) inside the film's fov, on the camera's side of the surface, and the camera's
    own ray towards the point reaching it (ray_intersect from the camera, t ~ distance)."""
    s = scene.sensors()[sensor]
    to_world = np.array(s.world_transform().matrix, dtype=np.float64)[..., 0]
    eye = to_world[:3, 3]
    local = (np.linalg.inv(to_world) @ np.c_[p, np.ones(len(p))].T).T[:, :3]
    half = math.tan(math.radians(float(mi.traverse(s)["x_fov"][0])) / 2)
    inside = (local[:, 2] > 0) & (np.abs(local[:, 0] / local[:, 2]) < half) & (np.abs(local[:, 1] / local[:, 2]) < half)
    to_p = p - eye
    dist = np.linalg.norm(to_p, axis=1)
    d = to_p / dist[:, None]
    ray = mi.Ray3f(mi.Point3f(*[np.full(len(p), e, np.float32) for e in eye]), mi.Vector3f(*d.T.astype(np.float32)))
    t = np.array(scene.ray_intersect_preliminary(ray).t, dtype=np.float64)
    facing = (n * -d).sum(1) > 0
    return valid & inside & facing & (t > dist * (1 - 1e-3))


def test_seen_by_the_four_sensors():
    scene = _views_scene()
    _, cache = _integrator(**B1).step(scene, 0, 3, 2)
    r = cache.lanes
    p, n, valid = _np(r.p).T, _np(r.n).T, np.array(r.valid)
    assert valid.sum() > 0.5 * len(valid)
    counts = []
    for sensor in range(4):
        seen = np.array(_restir_state.seen_by(scene, sensor, r))
        want = _seen_reference(scene, sensor, p, n, valid)
        # a point within a float32 rounding of the film's edge may go either way
        assert (seen != want).sum() <= 2, (sensor, int((seen != want).sum()))
        counts.append(int(seen.sum()))
    assert counts[0] == valid.sum() and counts[2] == 0  # its own first hits; the back side
    assert 0 < counts[1] < counts[0] and 0 < counts[3] < counts[0]  # narrower; partly hidden or outside


def test_project_gives_the_pixel_of_each_camera_ray():
    """A step's reservoirs projected into the film that rendered them (a floor filling it): all
    inside it, facing the camera, each in the pixel its camera ray was drawn through (lane //
    spp, the film's edge pixels included); invalid reservoirs are outside."""
    scene = mi.load_dict(_with_only_floor())
    spp = 2
    _, cache = _integrator(**B1).step(scene, 0, 3, spp)
    valid = np.array(cache.lanes.valid)
    assert valid.all()
    inside, pixel = _restir_state.project(scene.sensors()[0], cache.lanes)
    assert np.array(inside).all()
    # a point within a float32 rounding of a pixel's edge may go either way
    assert (np.array(pixel) != np.arange(len(valid)) // spp).sum() <= 2
    lanes = cache.lanes
    lanes.valid = mi.Bool(np.arange(len(valid)) % 3 != 0)
    assert np.array_equal(np.array(_restir_state.project(scene.sensors()[0], lanes)[0]), np.arange(len(valid)) % 3 != 0)


def test_carry_over_keeps_what_the_rendering_view_does_not_see():
    """Alg. 8's store: after view v renders, it holds v's new reservoirs plus exactly the old
    valid ones v does not see; per-sensor chains keep one store per sensor instead."""
    scene = _views_scene()
    i = _integrator(candidates=2, neighbors=2, burn_in=1, multiview="carry_over")
    i.step(scene, 0, 1, 1)
    store0 = i.states[_restir_state.STORE].prev
    assert set(i.states) == {_restir_state.STORE} and dr.width(store0.valid) == RES * RES
    _, cache = i.step(scene, 3, 2, 1)
    store = i.states[_restir_state.STORE].prev
    kept = np.array(store0.valid) & ~np.array(_restir_state.seen_by(scene, 3, store0))
    assert 0 < kept.sum() < np.array(store0.valid).sum()
    assert dr.width(store.valid) == RES * RES + kept.sum()
    np.testing.assert_array_equal(_np(store.p).T[: RES * RES], _np(cache.lanes.p).T)  # new first
    np.testing.assert_array_equal(_np(store.p).T[RES * RES:], _np(store0.p).T[kept])  # then the carried
    np.testing.assert_array_equal(_np(store.W)[RES * RES:], _np(store0.W)[kept])
    assert cache.prev is store0 and i.states[_restir_state.STORE].camera is None  # world-space search
    restored = _integrator(candidates=2, neighbors=2, burn_in=1, multiview="carry_over")
    restored.load_state_dict(i.state_dict())  # the store survives a checkpoint
    np.testing.assert_array_equal(_np(restored.step(scene, 0, 3, 1)[0]), _np(i.step(scene, 0, 3, 1)[0]))
    # view 0 again: it sees (and replaces) its own old reservoirs
    assert dr.width(i.states[_restir_state.STORE].prev.valid) < dr.width(store.valid)
    auto = _integrator(candidates=2, neighbors=2, burn_in=1)  # "auto": the store with several sensors
    auto.step(scene, 3, 1, 1)
    single = _integrator(candidates=2, neighbors=2, burn_in=1)
    single.step(mi.load_dict(_dict(False)), 0, 1, 1)
    assert set(auto.states) == {_restir_state.STORE} and set(single.states) == {0}
    per = _integrator(candidates=2, neighbors=2, burn_in=1, multiview="per_sensor")
    per.step(scene, 0, 1, 1)
    per.step(scene, 3, 2, 1)
    assert set(per.states) == {0, 3} and dr.width(per.states[3].prev.valid) == RES * RES


def test_carry_over_search_is_frozen_and_equals_the_traced_one():
    """The store's neighbours come from reprojection (its points bucketed by their pixel in the
    rendering film): a pure Dr.Jit pass, frozen like the screen search, whose replays follow the
    store's changing size; frozen and traced runs over the views give the same images."""
    scene = _views_scene()
    images = {}
    for freeze in (True, False):
        i = _integrator(candidates=2, neighbors=3, burn_in=1, multiview="carry_over", freeze=freeze)
        images[freeze] = []
        for step, view in enumerate((0, 3, 1, 0, 3, 1, 0)):
            images[freeze].append(_np(i.step(scene, view, step, 1)[0]))
            if step > 0:
                assert i.last_pass_frozen == freeze and i._neighbour_search.last == "reprojected"
        assert dr.width(i.states[_restir_state.STORE].prev.valid) > RES * RES  # the store outgrew one view
    for a, b in zip(images[True], images[False]):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_knn_reprojected_equals_brute_force():
    """Against brute force on random points: the k nearest within the radius among the points
    bucketed into the window pixels around each query's pixel (ties by index)."""
    rng = np.random.default_rng(4)
    w, h, spp, k, radius = 6, 5, 2, 3, 0.35
    n = 70
    pts = rng.random((n, 3)).astype(np.float32)
    pix = rng.integers(0, w * h, n)
    valid = rng.random(n) > 0.2
    q = rng.random((w * h * spp, 3)).astype(np.float32)
    windows = rng.integers(1, 3, w * h * spp)
    idx, ok = _knn.knn_reprojected(mi.Point3f(*pts.T), mi.Bool(valid), mi.UInt32(pix.astype(np.uint32)), mi.Point3f(*q.T),
                                   w, h, spp, k, radius, mi.UInt32(windows.astype(np.uint32)))
    px, py = pix % w, pix // w
    for lane in range(w * h * spp):
        qx, qy, win = (lane // spp) % w, (lane // spp) // w, windows[lane]
        cand = [j for j in range(n) if valid[j] and abs(px[j] - qx) <= win and abs(py[j] - qy) <= win]
        d2 = {j: float(((pts[j] - q[lane]) ** 2).sum()) for j in cand}
        want = sorted((j for j in cand if d2[j] < radius**2), key=lambda j: (d2[j], j))[:k]
        got = [int(np.array(idx[t])[lane]) for t in range(k) if bool(np.array(ok[t])[lane])]
        assert got == want, lane


def test_emitter_gradients_obey_eulers_identity(multi):
    """Direct light is linear in every emitter's intensity or radiance (seen or reflected) and
    W is a constant of the gradient: sum_l I_l dL/dI_l = L, per channel, on the step's paths."""
    params = mi.traverse(multi)
    keys = [SPOT, "point.intensity.value", "panel.emitter.radiance.value"]
    saved = {k: mi.Color3f(params[k]) for k in keys}
    i = _integrator(candidates=2, neighbors=2, burn_in=1, grad_paths="shared")
    try:
        values = {}
        for k in keys:
            values[k] = mi.Color3f(saved[k])
            dr.enable_grad(values[k])
            params[k] = values[k]
        params.update()
        image, cache = i.step(multi, 0, 0, 2)
        i.backward(multi, cache, mi.TensorXf(np.ones((RES, RES, 3), np.float32)), 1, 1)
        euler = sum(_np(dr.grad(values[k])).ravel() * _np(saved[k]).ravel() for k in keys)
        assert all((np.abs(_np(dr.grad(values[k]))) > 0).all() for k in keys)
        np.testing.assert_allclose(euler, _np(image).sum((0, 1)), rtol=1e-4)
    finally:
        for k in keys:
            params[k] = saved[k]
        params.update()


def test_mitsuba_render_and_render_backward(point):
    """Through Mitsuba's ``mi.render``: the gradient is the integrator's own backward."""
    from torchir.integrators import register

    register()
    integrator = mi.load_dict({"type": "restir_di", "candidates": 2, "burn_in": 1, "neighbors": 2, "grad_paths": "shared"})
    assert integrator.m_cap == 4.0 and integrator.candidates == 2
    weights = np.random.default_rng(1).random((RES, RES, 3))
    params = mi.traverse(point)
    with _texture_with_grad(params) as value:
        image = mi.render(point, params, integrator=integrator, spp=2, seed=3)
        dr.backward(dr.sum(image * mi.TensorXf(weights.astype(np.float32)), axis=None))
        g = _np(dr.grad(value))
    np.testing.assert_allclose(_np(image), _nee(point, 3, 2), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(g, _texel_gradient(point, 3, 2, weights), rtol=2e-4, atol=1e-6)
    assert integrator.last == {}


def test_render_backward_passes_its_seed_and_spp(point):
    """``render_backward``'s seed and spp (0: the sensor's) reach the decorrelated pass."""
    weights = np.random.default_rng(2).random((RES, RES, 3))
    params = mi.traverse(point)
    for spp_grad, want in ((1, _texel_gradient(point, 9, 1, weights)), (0, _texel_gradient(point, 9, 4, weights))):
        i = _integrator(candidates=2, neighbors=2, burn_in=1, grad_paths="decorrelated")
        with _texture_with_grad(params) as value:
            i.render(point, seed=3, spp=2)
            i.render_backward(point, params, mi.TensorXf(weights.astype(np.float32)), seed=9, spp=spp_grad)
            g = _np(dr.grad(value))
        np.testing.assert_allclose(g, want, rtol=2e-4, atol=1e-6)
        assert i.last == {}


def test_geometry_backward_adds_the_boundary_terms(point, monkeypatch):
    """``geometry=True``: the interior term on re-intersected shading points (the same points
    here: the albedo gradient is unchanged) plus ``direct_projective``'s boundary terms
    (``sppc=0``), called with the step's sensor and the gradient seed and spp."""
    b = ReSTIRDirectIntegrator().boundary_integrator()
    assert type(b).__name__ == "DirectProjectiveIntegrator" and b.sppc == 0
    i = _integrator(candidates=2, neighbors=2, burn_in=1)
    assert i.boundary_integrator() is i.boundary_integrator()
    calls = []

    class Spy:
        def render_backward(self, *args):
            calls.append(args)

    weights = np.random.default_rng(3).random((RES, RES, 3))
    plain = _integrator(candidates=2, neighbors=2, burn_in=1)
    monkeypatch.setattr(plain, "boundary_integrator", lambda **kw: Spy())
    g_plain, _ = _backward(point, plain, weights, 3, 2, 9, 1)
    assert calls == []  # geometry=False by default: no boundary terms
    asked = []
    monkeypatch.setattr(i, "boundary_integrator", lambda **kw: asked.append(kw) or Spy())
    params = mi.traverse(point)
    i.step(point, 0, 103, 2)
    with _texture_with_grad(params) as value:
        _, cache = i.step(point, 0, 3, 2)
        grad_in = mi.TensorXf(weights.astype(np.float32))
        the_params = {"no.mesh": mi.Float(0.0)}
        i.backward(point, cache, grad_in, 9, 1, geometry=True, params=the_params)
        g = _np(dr.grad(value))
    np.testing.assert_allclose(g, g_plain, rtol=1e-5, atol=1e-7)
    assert len(calls) == 1 and calls[0][0] is point and calls[0][1] is the_params and calls[0][2] is grad_in
    assert calls[0][3:] == (0, 9, 1)
    assert asked == [{"secondary": True, "primary": True}]  # no mesh differentiated: Mitsuba's shadow edges and silhouettes too


# ------------------------------------------------------------------------------ persistent offsets
@pytest.mark.parametrize("bad", [-1.0, 0.5, float("nan")])
def test_offset_lifetime_is_checked(bad):
    msg = _msg(ValueError, _integrator, offset_lifetime=bad)
    assert msg.startswith("offset_lifetime must be None or 0 (a fresh camera offset every step) or >= 1 steps")


def _offsets(i: ReSTIRDirectIntegrator) -> np.ndarray:
    return np.stack([_np(i.states[0].prev.offset.x), _np(i.states[0].prev.offset.y)], 1)


def test_persistent_offsets_stay_and_the_lane_reuses_its_own_reservoir(point):
    """offset_lifetime=inf: every lane keeps the camera offset it drew first (so its shading
    point), and the reuse is the lane's own reservoir (no search), whose M grows to the chain
    cap; the offsets are uniform in the pixel (means and variances within 5 standard errors)."""
    i = _integrator(candidates=2, burn_in=3, spatial=False, offset_lifetime=float("inf"))
    assert i.chain_cap == 128.0 and i.m_cap == 4.0
    i.step(point, 0, 0, 4)
    first = _offsets(i)
    for s in range(1, 4):
        i.step(point, 0, s, 4)
        assert np.array_equal(_offsets(i), first)
        assert i._neighbour_search.last == "lane"
    valid = _np(i.states[0].prev.valid) > 0
    assert _np(i.states[0].prev.M)[valid].min() == 2.0 * (3 + 4)  # 7 passes, nothing capped yet
    n = first.size
    assert abs(first.mean() - 0.5) < 5 * math.sqrt(1 / 12 / n)
    assert abs(first.var() - 1 / 12) < 5 * math.sqrt(1 / 180 / n)  # Var of (u - 1/2)^2 is 1/180


def test_offsets_are_redrawn_at_the_lifetime_rate_whatever_their_rays_hit(point):
    """offset_lifetime=2: each step about half the lanes draw a new offset, as often where the
    ray missed the scene as where it hit (a redraw that depended on the hit would drift the
    offsets towards hits: biased); lifetime 1 redraws every lane, so nothing is reused."""
    i = _integrator(candidates=2, burn_in=1, spatial=False, offset_lifetime=2)
    i.step(point, 0, 0, 4)
    changed, hit = [], []
    for s in range(1, 9):
        before, valid = _offsets(i), _np(i.states[0].prev.valid) > 0
        i.step(point, 0, s, 4)
        changed.append((_offsets(i) != before).any(1))
        hit.append(valid)
    changed, hit = np.concatenate(changed), np.concatenate(hit)
    assert 0 < hit.mean() < 1  # the point scene has background lanes
    for group in (hit, ~hit):
        k = group.sum()
        assert abs(changed[group].mean() - 0.5) < 5 * math.sqrt(0.25 / k), (changed[group].mean(), k)
    j = _integrator(candidates=2, burn_in=2, spatial=False, offset_lifetime=1)
    for s in range(3):
        j.step(point, 0, s, 2)
    valid = _np(j.states[0].prev.valid) > 0
    # every lane started afresh: one step's 2 candidates and the burn-in's count (2 x 2) more
    assert (_np(j.states[0].prev.M)[valid] == 2.0 + 2 * 2.0).all()


def test_offsets_are_fresh_after_a_geometry_edit_and_for_older_checkpoints(point):
    """A moved shape changes the shading points behind the kept offsets: that step draws new
    offsets and searches (the lane's own reservoir is no longer at its point); a state dict
    without offsets (saved before they existed) loads and draws them."""
    i = _integrator(candidates=2, burn_in=2, spatial=False, offset_lifetime=float("inf"))
    i.step(point, 0, 0, 1)
    kept = _offsets(i)
    params = mi.traverse(point)
    key = "blocker.to_world"
    original = type(params[key])(params[key])
    try:
        params[key] = type(original)().translate([0.01, 0.0, 0.0]) @ original
        params.update()
        i.step(point, 0, 1, 1)
        assert i._neighbour_search.last != "lane" and not np.array_equal(_offsets(i), kept)
    finally:
        params[key] = original
        params.update()
    state = i.state_dict()
    del state[0]["reservoirs"]["offset"]
    j = _integrator(candidates=2, burn_in=2, spatial=False, offset_lifetime=float("inf"))
    j.load_state_dict(state)
    assert np.isnan(_offsets(j)).all()
    j.step(point, 0, 2, 1)
    assert np.isfinite(_offsets(j)).all() and (_offsets(j) >= 0).all() and (_offsets(j) < 1).all()


@pytest.mark.parametrize("spatial", [False, True])
def test_the_lanes_own_chain_reuses_visibility_it_already_knows(point, spatial):
    """On its own chain a lane's shading point and the geometry are those of its previous
    reservoir, whose sample (W > 0, shadowed target) was visible from that very point: the pass
    neither traces that shadow ray again nor rebuilds the point for the support test. With the
    same seeds, tracing them gives the same image and reservoirs (the scene's blocker makes
    some samples occluded, so visibility matters). With spatial reuse the neighbours sit at
    other points: everything is traced."""
    runs = []
    for known in (True, False):
        i = _integrator(candidates=2, burn_in=2, spatial=spatial, offset_lifetime=float("inf"))
        if not known:  # the same passes with the own chain's visibility traced again
            settings = i._pass_settings
            i._pass_settings = lambda *args, settings=settings: dataclasses.replace(settings(*args), same_point=False)
        images = [_np(i.step(point, 0, s, 2)[0]) for s in range(4)]
        assert (i._neighbour_search.last == "lane") == (not spatial)
        r = i.states[0].prev
        runs.append([np.stack(images), _np(r.W), _np(r.M), _np(r.y.p.x), _np(r.y.em)])
    mine, traced = runs
    assert (mine[1] > 0).any() and (mine[1] == 0).any()  # lit and unlit lanes
    for a, b in zip(mine, traced):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)


def test_lane_chains_burn_in_with_one_pass_over_all_its_candidates(point, monkeypatch):
    """A lane chain resamples at one shading point, so burn_in passes of its candidates equal
    one RIS over all of them: the burn-in is one pass (here 40 x 2 candidates: past the unrolled
    count, the symbolic loop), its reservoirs hold M = 80, and the step after it keeps them."""
    i = _integrator(candidates=2, burn_in=40, spatial=False, offset_lifetime=float("inf"))
    assert i.lane_chains and not _integrator(candidates=2, burn_in=4).lane_chains
    calls = []
    original = i.sample_paths

    def spy(*args, **kw):
        calls.append(kw.get("candidates"))
        return original(*args, **kw)

    monkeypatch.setattr(i, "sample_paths", spy)
    i.step(point, 0, 0, 1)
    assert calls == [80, None]  # the burn-in pass, then the step's
    valid = _np(i.states[0].prev.valid) > 0
    assert (_np(i.states[0].prev.M)[valid] == 82.0).all() and i._neighbour_search.last == "lane"
    assert np.isfinite(_np(i.states[0].prev.W)).all() and (_np(i.states[0].prev.W)[valid] > 0).any()


@pytest.mark.parametrize("options", [
    {"spatial": False, "offset_lifetime": 64.0},  # lane chains
    {"nn_backend": "kdtree"},  # spatiotemporal (a fixed search: "auto" tries each in turn)
    {"target": "unshadowed", "nn_backend": "grid"},
    {"temporal": False, "spatial": False},  # B.2
], ids=["lane chains", "spatiotemporal", "unshadowed", "b2"])
def test_unfrozen_steps_launch_the_same_kernels_for_every_seed(point, options):
    """Not frozen, a step's seed must reach the kernels as an opaque value: the offsets' redraw
    hash once took it as a literal, so every step compiled a new kernel (2 s a step at 32²)."""
    i = _integrator(candidates=2, burn_in=2, freeze=False, **options)
    assert i.lane_chains == ("offset_lifetime" in options)
    i.step(point, 0, 0, 1)
    i.step(point, 0, 1, 1)  # the first step with kept offsets
    kernels = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for seed in (2, 3):
            dr.kernel_history_clear()
            i.step(point, 0, seed, 1)
            dr.eval()
            kernels.append(sorted(k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT))
    assert kernels[0] and kernels[0] == kernels[1]


@pytest.mark.parametrize("freeze", [False, True], ids=["unfrozen", "frozen"])
def test_a_new_radius_reuses_the_compiled_kernels(point, freeze):
    """Each sensor state's radius (automatic: from its footprints and first seed) entered the
    kernels as a literal, so every new state and every view compiled them again (32 times in one
    test of 16 runs)."""
    kernels = []
    for radius in (0.05, 0.0625):
        i = _integrator(candidates=2, burn_in=0, radius=radius, freeze=freeze, nn_backend="screen")
        i.step(point, 0, 0, 1)
        with backend.count_kernels() as stats:
            i.step(point, 0, 1, 1)  # a spatiotemporal step: the radius bounds the search
        kernels.append(stats)
    assert kernels[0].launched > 0 and kernels[1].compiled == 0, kernels


@pytest.mark.parametrize("options", [{"temporal": False, "spatial": False}, {}], ids=["b2", "spatiotemporal"])
def test_another_candidate_count_or_cap_reuses_the_compiled_kernels(point, options):
    """On a small wavefront the candidates run as a symbolic loop whose count, like the M cap,
    is an opaque value: samplers with other counts (a burn-in pass, B.1 against B.2, a tuning
    trial) or caps share the kernels instead of compiling their own."""
    kernels = []
    for candidates, m_cap in ((3, 7), (5, 9)):
        i = _integrator(candidates=candidates, burn_in=0, freeze=False, nn_backend="screen",
                        **{"m_cap": m_cap, **options})
        i.step(point, 0, 0, 1)
        with backend.count_kernels() as stats:
            i.step(point, 0, 1, 1)
        kernels.append(stats)
    assert kernels[0].launched > 0 and kernels[1].compiled == 0, kernels


def test_temporal_memory_is_short_while_the_geometry_moves(point):
    """A step after a geometry edit caps M at ``moving_geometry_m_cap`` (4): a long memory let
    the image's error follow the moved shadow for many steps. Unmoved, M grows to the cap."""
    i = _integrator(candidates=3, neighbors=4, burn_in=0, m_cap=100, spatial=False, nn_backend="grid")
    params = mi.traverse(point)
    for seed in range(3):
        i.step(point, 0, seed, 1)
    assert _np(i.states[0].prev.M).max() == 9.0
    try:
        params["blocker.to_world"] = mi.Transform4f(T().translate([-0.28, 0.3, 0.6]).scale(0.15))
        params.update()
        i.step(point, 0, 3, 1)
        assert _np(i.states[0].prev.M).max() == 4.0
        i.step(point, 0, 4, 1)  # unmoved since: the memory grows again
        assert _np(i.states[0].prev.M).max() == 7.0
        i.options = i.options.replace(moving_geometry_m_cap=0)  # off: the m_cap alone
        params["blocker.to_world"] = mi.Transform4f(T().translate([-0.3, 0.3, 0.6]).scale(0.15))
        params.update()
        i.step(point, 0, 5, 1)
        assert _np(i.states[0].prev.M).max() == 10.0
    finally:
        params["blocker.to_world"] = mi.Transform4f(T().translate([-0.3, 0.3, 0.6]).scale(0.15))
        params.update()
