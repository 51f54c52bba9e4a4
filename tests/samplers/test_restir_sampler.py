"""``ReSTIRSampler``'s Python layer without rendering (issue 19: mutation audit of
``torchir/samplers/restir.py``): presets and options as they reach the integrator, exact error
messages, ``render_seed``, ``check_gradients``, ``diagnostics``, state round trip, ``steps``,
``repr``. The rendering itself is covered by ``tests/samplers/test_restir.py``."""
from __future__ import annotations

import copy
import dataclasses
import warnings

import torchir  # noqa: I001  (before torch)

import mitsuba as mi
import numpy as np
import pytest

from torchir.samplers import ReSTIROptions, ReSTIRSampler
from torchir.integrators.restir_options import PRESETS

from tests.helpers import raised_message as _raises


def geometry_message(chained: bool | str) -> str:
    edges = {True: "and kept across steps (edge chains), ", False: "afresh each step, ",
             "auto": "afresh each step, or kept across steps (edge chains) on meshes with many edges, "}[chained]
    return ("ReSTIR with shape parameters: interior term with reuse (ray-following shading points); "
            "boundary terms: shadow edges sampled on the moving meshes under area lights " + edges
            + "silhouettes and the shading-horizon bands of smooth meshes without reuse, the rest from "
            "direct_projective; the temporal support test "
            "uses the current geometry, not the previous step's (a small bias)")


@pytest.fixture(scope="module")
def scene() -> torchir.Scene:
    return torchir.Scene.builtin("oxalis_lite", resolution=8, texture=2, dim_lights=1, hidden_lights=1)


def _integrator_module():
    torchir.backend.variant()  # restir_di needs a Mitsuba variant at import
    from torchir.integrators import restir_di

    return restir_di


def _options(r: ReSTIRSampler) -> dict:
    i = r.integrator
    return {
        "candidates": i.candidates, "neighbors": i.neighbors, "radius": i.radius, "m_cap": i.m_cap,
        "temporal": i.temporal, "spatial": i.spatial, "burn_in": i.burn_in, "grad_paths": i.grad_paths,
        "forward_only": i.forward_only, "nn_backend": i.nn_backend, "normal_threshold": i.normal_threshold,
        "target": i.target, "freeze": i.freeze, "multiview": i.multiview, "spp_chains": i.spp_chains,
        "offset_lifetime": i.offset_lifetime,
    }


# ------------------------------------------------------------------------------ options
@pytest.mark.frozen
def test_defaults(scene):
    r = ReSTIRSampler(scene)
    assert isinstance(r.integrator, _integrator_module().ReSTIRDirectIntegrator)
    assert r.scene is scene and r.preset == "auto" and r.seed == 0  # the defaults until its first render chooses
    assert _options(r) == {
        "candidates": 16, "neighbors": 8, "radius": 0.0, "m_cap": 32.0, "temporal": True, "spatial": True,
        "burn_in": 32, "grad_paths": "decorrelated", "forward_only": False, "nn_backend": "auto",
        "normal_threshold": 0.9, "target": "shadowed", "freeze": True, "multiview": "auto", "spp_chains": True,
        "offset_lifetime": 0.0,
    }
    assert type(r.integrator.radius) is float and type(r.integrator.m_cap) is float


def test_options_reach_the_integrator(scene):
    r = ReSTIRSampler(
        scene, candidates=3, neighbors=5, radius=0.25, m_cap=7, temporal=False, spatial=True, burn_in=4,
        grad_paths="shared", nn_backend="grid", seed=11, normal_threshold=0.5, target="unshadowed",
        freeze=False, multiview="carry_over", spp_chains=False, offset_lifetime=64,
    )
    assert r.preset == "restir" and r.seed == 11
    assert _options(r) == {
        "candidates": 3, "neighbors": 5, "radius": 0.25, "m_cap": 7.0, "temporal": False, "spatial": True,
        "burn_in": 4, "grad_paths": "shared", "forward_only": False, "nn_backend": "grid",
        "normal_threshold": 0.5, "target": "unshadowed", "freeze": False, "multiview": "carry_over", "spp_chains": False,
        "offset_lifetime": 64.0,
    }
    r = ReSTIRSampler(scene, candidates=5, radius=1, temporal=True, spatial=False, nn_backend="screen")
    i = r.integrator
    assert (i.radius, i.m_cap, i.temporal, i.spatial) == (1.0, 10.0, True, False)
    assert type(r.integrator.radius) is float and r.integrator.nn_backend == "screen"


def test_presets(scene):
    assert tuple(PRESETS) == ("restir", "persistent", "b1", "b2", "forward_only")
    kw = dict(candidates=6, neighbors=3, burn_in=9, temporal=True, spatial=True)
    b1 = ReSTIRSampler(scene, preset="b1")
    assert b1.preset == "b1"
    o = _options(b1)
    assert (o["candidates"], o["temporal"], o["spatial"], o["burn_in"], o["forward_only"]) == (1, False, False, 0, False)
    assert (o["neighbors"], o["m_cap"]) == (8, 2.0)
    o = _options(ReSTIRSampler(scene, preset="b1", **kw))  # explicit arguments win over the preset's
    assert (o["candidates"], o["temporal"], o["spatial"], o["burn_in"], o["neighbors"]) == (6, True, True, 9, 3)
    b2 = ReSTIRSampler(scene, preset="b2", candidates=6, neighbors=3)
    o = _options(b2)
    assert (o["candidates"], o["temporal"], o["spatial"], o["burn_in"], o["forward_only"]) == (6, False, False, 0, False)
    assert (o["neighbors"], o["m_cap"]) == (3, 12.0)
    fo = ReSTIRSampler(scene, preset="forward_only", **kw)
    o = _options(fo)
    assert (o["candidates"], o["temporal"], o["spatial"], o["burn_in"], o["forward_only"]) == (6, True, True, 9, True)
    re_ = ReSTIRSampler(scene, preset="restir", **kw)
    o = _options(re_)
    assert (o["candidates"], o["temporal"], o["spatial"], o["burn_in"], o["forward_only"]) == (6, True, True, 9, False)
    assert (o["offset_lifetime"], o["m_cap"], re_.integrator.chain_cap) == (0.0, 12.0, 384.0)
    persistent = _options(ReSTIRSampler(scene, preset="persistent", **{**kw, "spatial": False}))
    assert (persistent["candidates"], persistent["temporal"], persistent["spatial"], persistent["burn_in"]) == (6, True, False, 9)
    assert (persistent["offset_lifetime"], persistent["multiview"]) == (2048.0, "per_sensor")
    assert _options(ReSTIRSampler(scene, preset="persistent", offset_lifetime=float("inf")))["offset_lifetime"] == float("inf")
    assert ReSTIRSampler(scene, m_cap=50).integrator.chain_cap == 50.0  # an explicit cap bounds both
    for preset in PRESETS:
        assert ReSTIRSampler(scene, preset=preset).preset == preset


def test_bad_scene_and_preset(scene):
    assert _raises(TypeError, ReSTIRSampler, "oxalis") == "scene must be a torchir.Scene, got str"
    assert _raises(TypeError, ReSTIRSampler, scene.mi_scene).startswith("scene must be a torchir.Scene, got ")
    msg = _raises(ValueError, ReSTIRSampler, scene, preset="B1")
    assert msg == "preset must be one of ('auto', 'restir', 'persistent', 'b1', 'b2', 'forward_only'), got 'B1'"
    assert ReSTIRSampler(scene, preset=None).preset == "auto"  # None and no options: the default
    assert ReSTIRSampler(scene, preset=None, candidates=4).preset == "restir"  # None with options


@pytest.mark.parametrize("seed", [True, False, -1, 2**32, 2**40, 3.0, "3", None])
def test_bad_seed(scene, seed):
    assert _raises(ValueError, ReSTIRSampler, scene, seed=seed) == f"seed must be an int in [0, 2^32), got {seed!r}"


@pytest.mark.parametrize("seed", [0, 1, 2**31, 2**32 - 1])
def test_good_seed(scene, seed):
    assert ReSTIRSampler(scene, seed=seed).seed == seed


def test_unsupported_scene_is_refused():
    envmap = torchir.Scene.from_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}},
        "sphere": {"type": "sphere"},
        "sky": {"type": "constant"},
    })
    msg = _raises(ValueError, ReSTIRSampler, envmap)
    assert msg == "ReSTIR direct illumination does not support environment emitters (envmap, constant) yet"


# ------------------------------------------------------------------------------ render()
def test_render_seed(scene):
    r = ReSTIRSampler(scene)
    assert [r.render_seed(s) for s in (0, 1, 7, 2**32 - 1)] == [0, 1, 7, 2**32 - 1]
    for sampler_seed in (1, 5, 2**32 - 1):
        r = ReSTIRSampler(scene, seed=sampler_seed)
        for s in (0, 3, 12345):
            got = r.render_seed(s)
            assert type(got) is int
            assert got == int(mi.sample_tea_32(s, sampler_seed)[0])
            assert got != int(mi.sample_tea_32(s, sampler_seed)[1])
            assert got != int(mi.sample_tea_32(sampler_seed, s)[0])
    # fixed values: the mixing is part of the reproducibility contract
    assert ReSTIRSampler(scene, seed=5).render_seed(3) == 2010459632


@pytest.mark.parametrize("name", [
    "spot_left.to_world", "spot_left.cutoff_angle", "spot_left.beam_width", "dim_00.position",
    "hidden_00.position", "spot_right.sampling_weight", "spot_left", "spot_left.",
])
def test_check_gradients_refuses_light_placement(scene, name):
    r = ReSTIRSampler(scene)
    msg = _raises(ValueError, r.check_gradients, ["canvas.bsdf.reflectance.data", name])
    assert msg == (
        f"ReSTIR gives no gradient for the light parameter {name!r} (light samples are reused, not "
        f"re-sampled, when a light moves): optimise it without sampler=, e.g. with the scene's own integrator"
    )


def test_check_gradients_allows_appearance(scene):
    r = ReSTIRSampler(scene)
    names = [
        "spot_left.intensity.value", "dim_00.intensity.value", "hidden_00.intensity.value",
        "spot_right.radiance.value", "spot_right.irradiance.value", "spot_left.scale",
        "canvas.bsdf.reflectance.data", "leaf.bsdf.reflectance.value", "wall.bsdf.reflectance.value",
        "not_a_light.position", "leaf.silhouette_sampling_weight",
    ]
    scene._warned.discard("restir-geometry")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r.check_gradients(names)
        r.check_gradients(tuple(names))
        r.check_gradients([])
    assert "restir-geometry" not in scene._warned


@pytest.mark.parametrize("names", [
    ["canvas.to_world"], ["leaf.bsdf.reflectance.value", "leaf.to_world"], ["wall.vertex_positions"],
    ["ball.radius", "canvas.bsdf.reflectance.data"], ["ball.center"],
])
def test_check_gradients_warns_once_about_geometry(scene, names):
    r = ReSTIRSampler(scene)
    scene._warned.discard("restir-geometry")
    with pytest.warns(UserWarning) as record:
        r.check_gradients(names)
    assert [str(w.message) for w in record] == [geometry_message(chained="auto")]
    assert "restir-geometry" in scene._warned
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r.check_gradients(names)  # once per scene and key
    for preset, chains, chained in (("forward_only", True, False), ("b2", "auto", False), ("restir", True, True)):
        scene._warned.discard("restir-geometry")  # the warning says whether edge samples are kept across steps
        sampler = ReSTIRSampler(scene, preset=preset, edge_temporal=chains)
        with pytest.warns(UserWarning) as record:
            sampler.check_gradients(names)
        assert [str(w.message) for w in record] == [geometry_message(chained=chained)]
        ReSTIRSampler(scene).check_gradients(names)
    scene._warned.discard("restir-geometry")


def test_check_gradients_uses_its_own_scene(scene):
    other = torchir.Scene.builtin("oxalis_lite", resolution=8, texture=2, dim_lights=1, hidden_lights=1)
    r = ReSTIRSampler(other)
    with pytest.warns(UserWarning):
        r.check_gradients(["canvas.to_world"])
    assert "restir-geometry" in other._warned and "restir-geometry" not in scene._warned


# ------------------------------------------------------------------------------ state API
def test_diagnostics_without_a_step(scene):
    assert ReSTIRSampler(scene).diagnostics() == {}


def test_diagnostics_timings(scene):
    r = ReSTIRSampler(scene)
    r.integrator.timings = {"burn_in": 8, "ris": 1, "nn": 2, "combine": 3, "backward": 4}
    d = r.diagnostics()
    assert d == {
        "time_burn_in": 8.0, "time_ris": 1.0, "time_nn": 2.0, "time_combine": 3.0, "time_backward": 4.0,
        "reuse_fraction": 0.5,
    }
    assert all(type(v) is float for v in d.values())
    r.integrator.timings = {"burn_in": 100.0, "ris": 3.0, "combine": 1.0}
    assert r.diagnostics()["reuse_fraction"] == 0.25
    r.integrator.timings = {"burn_in": 100.0, "ris": 3.0, "nn": 1.0}
    assert r.diagnostics()["reuse_fraction"] == 0.25
    r.integrator.timings = {"ris": 0.5}
    assert r.diagnostics() == {"time_ris": 0.5, "reuse_fraction": 0.0}
    r.integrator.timings = {"nn": 0.25, "combine": 0.25}
    assert r.diagnostics()["reuse_fraction"] == 1.0
    r.integrator.timings = {"burn_in": 2.0}  # burn-in only: no step time, no fraction
    assert r.diagnostics() == {"time_burn_in": 2.0}
    r.integrator.timings = {"burn_in": 2.0, "ris": 0.0}
    assert r.diagnostics() == {"time_burn_in": 2.0, "time_ris": 0.0}


def test_diagnostics_includes_the_reservoir_stats(scene, monkeypatch):
    stats = property(lambda self: {"mean_M": 3.0, "max_W": 2.0})
    monkeypatch.setattr(_integrator_module().ReSTIRDirectIntegrator, "stats", stats)
    r = ReSTIRSampler(scene)
    r.integrator.timings = {"ris": 2.0, "nn": 1.0}
    assert r.diagnostics() == {"mean_M": 3.0, "max_W": 2.0, "time_ris": 2.0, "time_nn": 1.0, "reuse_fraction": 1 / 3}


def _fake_states(r: ReSTIRSampler) -> None:
    sig = (4, tuple(int(s.primitive_count()) for s in r.scene.mi_scene.shapes()))
    SensorState = _integrator_module().SensorState
    r.integrator.states[0] = SensorState(prev=None, radius=0.5, window=3, steps=4, signature=sig,
                                         camera=((1.0, 2.0), 8, 8, 1), lights=None)
    r.integrator.states[2] = SensorState(prev=None, radius=0.25, steps=1, signature=sig)


def test_state_round_trip_and_steps(scene):
    a = ReSTIRSampler(scene, preset="b2", seed=9)
    assert a.steps == {}
    assert a.state_dict() == {"preset": "b2", "seed": 9, "options": dataclasses.asdict(a.options), "sensors": {}}
    _fake_states(a)
    assert a.steps == {0: 4, 2: 1}
    state = a.state_dict()
    assert set(state) == {"preset", "seed", "options", "sensors"}
    assert (state["preset"], state["seed"]) == ("b2", 9)
    assert state["sensors"] == a.integrator.state_dict()
    b = ReSTIRSampler(scene, preset="restir")
    with pytest.warns(UserWarning, match=r"other options; they continue under this sampler's \(temporal: False -> True; "
                                         r"spatial: False -> True; burn_in: 0 -> 32\)"):
        b.load_state_dict(state)
    assert b.steps == {0: 4, 2: 1}
    assert b.integrator.states[0].radius == 0.5 and b.integrator.states[0].window == 3
    assert b.integrator.states[0].camera == ((1.0, 2.0), 8, 8, 1)
    assert b.state_dict()["sensors"] == state["sensors"]
    assert (b.preset, b.seed) == ("restir", 0)  # the options stay the constructor's
    b.reset()
    assert b.steps == {} and b.state_dict()["sensors"] == {}
    assert a.steps == {0: 4, 2: 1}


def test_load_state_dict_copies(scene, monkeypatch):
    a = ReSTIRSampler(scene)
    _fake_states(a)
    state = a.state_dict()
    state["sensors"][0]["reservoirs"] = {"x": np.zeros(2)}
    seen = []
    b = ReSTIRSampler(scene, preset="restir")
    monkeypatch.setattr(b.integrator, "load_state_dict", seen.append)
    b.load_state_dict(state)
    (got,) = seen
    assert got is not state["sensors"] and got[0] is not state["sensors"][0]
    assert got[0]["reservoirs"]["x"] is not state["sensors"][0]["reservoirs"]["x"]
    assert got.keys() == state["sensors"].keys() and got[2] == state["sensors"][2]


@pytest.mark.parametrize("bad", [{"nope": 1}, {}, ["sensors"], "sensors", None, ({"sensors": {}},)])
def test_load_state_dict_refuses(scene, bad):
    r = ReSTIRSampler(scene)
    _fake_states(r)
    assert _raises(ValueError, r.load_state_dict, bad) == "expected a dict from ReSTIRSampler.state_dict()"
    assert r.steps == {0: 4, 2: 1}


def test_load_state_dict_replaces(scene):
    r = ReSTIRSampler(scene)
    _fake_states(r)
    r.load_state_dict({"sensors": {}})
    assert r.steps == {}
    r.load_state_dict(copy.deepcopy({"preset": "b1", "seed": 1, "sensors": {}}))
    assert r.steps == {} and r.seed == 0


def test_repr(scene):
    assert repr(ReSTIRSampler(scene, preset="restir")) == (
        "ReSTIRSampler(preset='restir', candidates=16, neighbors=8, temporal=True, spatial=True, burn_in=32, "
        "grad_paths='decorrelated', m_cap=32, nn_backend='auto', target='shadowed')"
    )
    r = ReSTIRSampler(scene, preset="b1", neighbors=3, m_cap=5, grad_paths="shared", nn_backend="grid",
                      target="unshadowed")
    assert repr(r) == (
        "ReSTIRSampler(preset='b1', candidates=1, neighbors=3, temporal=False, spatial=False, burn_in=0, "
        "grad_paths='shared', m_cap=5, nn_backend='grid', target='unshadowed')"
    )
    assert str(r) == repr(r)


def test_options_travel_with_the_state_and_a_resume_under_others_says_which(scene):
    """The options the chains were built with are saved; loading them into a sampler with the same
    options is silent, with other ones warns field by field; a state without options (older
    checkpoints) loads silently."""
    a = ReSTIRSampler(scene, candidates=4, light_guide=0.5, offset_lifetime=64.0, spatial=False)
    _fake_states(a)
    state = a.state_dict()
    assert ReSTIROptions(**state["options"]) == a.options  # the saved options rebuild the same object
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ReSTIRSampler(scene, a.options).load_state_dict(state)
        ReSTIRSampler(scene).load_state_dict({k: v for k, v in state.items() if k != "options"})
    other = ReSTIRSampler(scene, a.options.replace(candidates=8))
    with pytest.warns(UserWarning) as record:
        other.load_state_dict(state)
    (warning,) = record
    assert str(warning.message).endswith("(candidates: 4 -> 8)") and other.steps == {0: 4, 2: 1}
