"""``ReSTIRSampler(scene)`` with no options (``preset="auto"``): the probe's measurements, the
choice they lead to, and the sampler's life cycle (chosen once, pinned options kept, saved and
restored with the reservoirs, the trainer's run length)."""
from __future__ import annotations

import dataclasses
import math

import torchir  # noqa: I001  (before torch)

import pytest
import torch

from torchir.functions import render
from torchir.samplers import ReSTIROptions, ReSTIRSampler
from torchir.samplers import _restir_auto as auto
from torchir.samplers._restir_auto import AutoChoice, SceneProbe, choose


def probe(light: float = 1e4, camera: float = 1.0, **changes) -> SceneProbe:
    base = SceneProbe(light_variance=light, camera_variance=camera, camera_resolved=True, step_seconds=0.02,
                      candidate_seconds=4e-4, missed_share=0.0, geometry=False, spp=1, seconds=0.1)
    return dataclasses.replace(base, **changes)


# ------------------------------------------------------------------------------ the choice (pure)
def test_light_bound_coarse_texture_gets_persistent_chains():
    c = choose(probe(light=3e4))
    assert c.strategy == "persistent" and c.options.lane_chains and c.options.light_guide == 0.5
    assert c.costs["persistent"] < c.costs["spatiotemporal"] < 1.0 == c.costs["plain"]


def test_burn_in_minimises_the_charged_cost_and_respects_its_share():
    p = probe(light=3e3)
    c = choose(p, planned_steps=300)
    step = auto.PERSISTENT_STEP * (p.step_seconds + auto.PERSISTENT_CANDIDATES * p.candidate_seconds)

    def cost(x: float) -> float:  # the model choose() minimises, in burn-in candidates x
        return (auto.PERSISTENCE_WINDOW * p.camera_variance + p.light_variance / x) * (300 * step + auto.CHAINS_BURNED_IN * x * p.candidate_seconds)

    x = c.options.burn_in * c.options.candidates
    assert cost(x) <= min(cost(x * 0.9), cost(x * 1.1))
    assert c.options.m_cap == 4 * x
    capped = choose(probe(light=3e5), planned_steps=300)  # its optimum would take longer than the run
    burn = auto.CHAINS_BURNED_IN * capped.options.burn_in * capped.options.candidates * p.candidate_seconds
    assert auto.BURN_IN_SHARE * 300 * step <= burn <= auto.BURN_IN_SHARE * 300 * step + auto.CHAINS_BURNED_IN * 4 * p.candidate_seconds
    short = choose(p, planned_steps=3)  # a short run cannot afford a long burn-in
    burn = auto.CHAINS_BURNED_IN * short.options.burn_in * short.options.candidates * p.candidate_seconds
    assert short.options.burn_in < c.options.burn_in
    assert burn <= max(auto.BURN_IN_SHARE * 3 * step, auto.CHAINS_BURNED_IN * 64 * 4 * p.candidate_seconds) * 1.01
    assert choose(p, planned_steps=3000).options.burn_in > c.options.burn_in


@pytest.mark.parametrize("changes", [{"geometry": True}, {"missed_share": 0.3}])
def test_no_persistent_chains_where_kept_samples_would_starve(changes):
    c = choose(probe(light=3e4, **changes))
    assert "persistent" not in c.costs and c.strategy == "spatiotemporal" and not c.options.lane_chains


@pytest.mark.parametrize("light", [0.0, 0.5, 2.0])
def test_no_reuse_where_light_sampling_is_not_the_bottleneck(light):
    c = choose(probe(light=light))
    assert c.strategy == "plain" and not c.options.reuse
    m = c.options.candidates
    plain = lambda k: (1.0 + light / k) * (0.02 + k * 4e-4)  # noqa: E731
    assert all(plain(m) <= plain(k) for k in auto.PLAIN_CANDIDATES)
    assert m == 1 if light == 0 else m > 1


def test_reuse_needs_its_margin():
    """Just where reuse is predicted to win by less than its margin, plain RIS is kept."""
    lights = [0.1 * 1.25**i for i in range(60)]
    choices = [choose(probe(light=v)) for v in lights]
    first = next(i for i, c in enumerate(choices) if c.strategy != "plain")
    assert 0 < first
    assert min(choices[first].costs[k] for k in choices[first].costs if k != "plain") * auto.REUSE_MARGIN < 1.0
    before = choices[first - 1]
    assert min(before.costs[k] for k in before.costs if k != "plain") * auto.REUSE_MARGIN >= 1.0


def test_pinned_options_are_kept_and_a_misfit_is_named():
    c = choose(probe(light=3e4), pinned={"candidates": 2, "grad_paths": "shared"})
    assert (c.options.candidates, c.options.grad_paths, c.strategy) == (2, "shared", "persistent")
    with pytest.raises(ValueError, match="ReSTIR auto chose 'spatiotemporal'.*light_guide"):
        choose(probe(light=3e4, geometry=True), pinned={"light_guide": 0.5})
    with pytest.raises(ValueError, match="planned_steps must be >= 1"):
        choose(probe(), planned_steps=0)


def test_choice_round_trips_and_describes_itself():
    c = choose(probe(light=3e4, camera_resolved=False))
    assert AutoChoice.from_dict(c.to_dict()) == c
    line = c.describe()
    assert line.startswith("ReSTIR auto: persistent lane chains: 4 candidates") and "3e+04+" in line
    assert math.isinf(probe(camera=0.0).light_to_camera)


# ------------------------------------------------------------------------------ the probe (renders)
def one_point_light(resolution: int = 12) -> torchir.Scene:
    """A textured quad under one point light: one candidate is exact, nothing to resample."""
    import mitsuba as mi

    texture = {"type": "bitmap", "bitmap": mi.Bitmap(mi.TensorXf([[[0.2, 0.5, 0.8]] * 4] * 4)), "raw": True,
               "filter_type": "nearest"}
    return torchir.Scene.from_dict({
        "type": "scene", "integrator": {"type": "prb", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 40, "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"}}},
        "quad": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": texture}},
        "light": {"type": "point", "position": [0.3, 0.2, 1.5], "intensity": {"type": "rgb", "value": 4.0}},
    })


def _probe(scene: torchir.Scene, key: str, spp: int = 1) -> SceneProbe:
    value = scene.get(key)
    plain = tuple(ReSTIRSampler(scene, preset="b2", candidates=m, burn_in=0) for m in auto.PROBE_CANDIDATES)
    return auto.probe_scene(scene, {key: value.requires_grad_()}, frozenset({key}), 0, spp, 7, plain)


def test_probe_separates_light_from_camera_noise():
    ajar = torchir.Scene.builtin("ajar_painting", resolution=24)
    p = _probe(ajar, "painting.bsdf.reflectance.data")
    assert p.light_to_camera > 100 and p.missed_share == 0.0 and not p.geometry
    assert p.step_seconds > 0 and p.candidate_seconds > 0 and p.spp == 1
    quad = one_point_light()
    q = _probe(quad, "quad.bsdf.reflectance.data")
    assert q.light_variance < 1e-6 * q.camera_variance  # one light, no occluder: every candidate is the same
    assert choose(q).strategy == "plain" and choose(q).options.candidates == 1


def test_probe_sees_texels_finer_than_pixels():
    fine = torchir.Scene.builtin("ajar_painting", resolution=12, texture=64)
    p = _probe(fine, "painting.bsdf.reflectance.data")
    assert p.missed_share > auto.MISSED_SHARE
    assert choose(dataclasses.replace(p, light_variance=1e4 * p.camera_variance)).strategy != "persistent"


# ------------------------------------------------------------------------------ the sampler
@pytest.fixture(scope="module")
def ajar() -> torchir.Scene:
    return torchir.Scene.builtin("ajar_painting", resolution=16)


KEY = "painting.bsdf.reflectance.data"


def test_no_options_means_auto_and_options_mean_what_they_say(ajar):
    assert ReSTIRSampler(ajar).preset == "auto" and ReSTIRSampler(ajar).choice is None
    assert ReSTIRSampler(ajar, candidates=8).preset == "restir"  # options given: the spatiotemporal default
    assert ReSTIRSampler(ajar, preset="auto", candidates=8).preset == "auto"
    with pytest.raises(TypeError, match="preset='auto' chooses the options itself"):
        ReSTIRSampler(ajar, ReSTIROptions(), preset="auto")
    with pytest.raises(ValueError, match="planned_steps must be an int >= 1"):
        ReSTIRSampler(ajar, planned_steps=0)


def test_auto_chooses_once_at_the_first_render_and_keeps_pins(ajar, monkeypatch):
    r = ReSTIRSampler(ajar, preset="auto", planned_steps=50, m_cap=9000)
    x = torch.full_like(ajar.get(KEY), 0.5).requires_grad_()
    render(ajar, {KEY: x}, spp=1, seed=0, sampler=r).sum().backward()
    assert r.choice is not None and r.options is r.choice.options and r.choice.planned_steps == 50
    assert r.options.m_cap == 9000 and x.grad.abs().sum() > 0
    calls = []
    monkeypatch.setattr(auto, "probe_scene", lambda *a: calls.append(a))
    render(ajar, {KEY: x}, spp=1, seed=1, sampler=r)
    assert calls == [] and r.steps[0] == 2

    state = r.state_dict()
    assert state["auto"] == r.choice.to_dict() and state["preset"] == "auto"
    resumed = ReSTIRSampler(ajar)
    monkeypatch.setattr("torchir.samplers.restir.probe_scene", lambda *a: pytest.fail("a resumed run probed again"))
    resumed.load_state_dict(state)
    assert resumed.choice == r.choice and resumed.options == r.options
    render(ajar, {KEY: x.detach()}, spp=1, seed=2, sampler=resumed)
    assert resumed.steps[0] == 3


def test_trainer_charges_the_burn_in_over_its_max_steps(ajar):
    r = ReSTIRSampler(ajar)
    r.plan_run(40)
    assert r.planned_steps == 40
    given = ReSTIRSampler(ajar, planned_steps=500)
    given.plan_run(40)  # an explicit run length wins
    assert given.planned_steps == 500


def test_a_state_from_before_auto_keeps_its_options(ajar, monkeypatch):
    """A checkpoint without a choice (another preset, an older run): its chains continue under
    their own options, pins on top, and nothing is probed."""
    b2 = ReSTIRSampler(ajar, preset="b2", candidates=3)
    b2.integrator.states.clear()
    r = ReSTIRSampler(ajar, preset="auto", burn_in=5)
    monkeypatch.setattr("torchir.samplers.restir.probe_scene", lambda *a: pytest.fail("probed"))
    with pytest.warns(UserWarning, match=r"continue under this sampler's \(burn_in: 0 -> 5\)"):  # the pin, named
        r.load_state_dict(b2.state_dict())
    assert r.options == b2.options.replace(burn_in=5) and r.choice is None
    render(ajar, {}, spp=1, seed=0, sampler=r)


def test_yaml_restir_without_options_chooses_and_checkpoints_the_choice(tmp_path, monkeypatch):
    """``sampler: {type: restir}`` through ``torchir fit``: the sampler is told max_steps, chooses
    at the first step, and the checkpoint keeps the choice."""
    import yaml

    from torchir import cli

    config = {"model": {"scene": "ajar_painting", "resolution": 12, "parameters": {KEY: {"init": 0.5}},
                        "sampler": {"type": "restir"}, "spp": 1},
              "data": {"target_spp": 16}, "trainer": {"max_steps": 2}}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    monkeypatch.chdir(tmp_path)
    assert cli.main(["fit", "--config", "run.yaml", "--trainer.enable_progress_bar", "false"]) == 0
    (last,) = tmp_path.rglob("last.ckpt")
    state = torch.load(last, map_location="cpu", weights_only=False)["torchir_sampler"]
    assert state["preset"] == "auto" and state["auto"]["planned_steps"] == 2
    assert state["auto"]["strategy"] in ("persistent", "spatiotemporal", "plain")
    assert state["options"] == state["auto"]["options"]


def test_renders_without_gradients_wait_for_one_with(ajar):
    """What the choice measures is the gradient's noise: a preview render before the first
    gradient step renders by plain RIS and leaves the choice to that step."""
    r = ReSTIRSampler(ajar)
    image = render(ajar, {}, spp=1, seed=0, sampler=r)
    assert torch.isfinite(image).all() and image.sum() > 0
    assert r.choice is None and not r.options.reuse
    x = torch.full_like(ajar.get(KEY), 0.5).requires_grad_()
    render(ajar, {KEY: x}, spp=1, seed=1, sampler=r)
    assert r.choice is not None and r.options is r.choice.options
