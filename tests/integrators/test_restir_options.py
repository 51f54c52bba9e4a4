"""ReSTIROptions: one validated, immutable settings object; named configurations whose explicit
arguments win; the sampler and the integrator read it and nothing else sets it."""
from __future__ import annotations

import dataclasses
import math

import torchir  # noqa: I001  (before torch)
import pytest

from torchir.integrators.restir_options import PERSISTENT_LIFETIME, PRESETS, ReSTIROptions
from torchir.samplers import PIXEL_SAMPLERS, RENDER_SAMPLERS, SAMPLERS, PixelSampler, RenderSampler, ReSTIRSampler


@pytest.fixture(scope="module")
def scene() -> torchir.Scene:
    return torchir.Scene.builtin("oxalis_lite", resolution=8)


def test_named_configurations_set_what_their_names_say():
    assert ReSTIROptions.spatiotemporal() == ReSTIROptions()
    no_reuse, one = ReSTIROptions.no_reuse(), ReSTIROptions.one_light_sample()
    assert (no_reuse.temporal, no_reuse.spatial, no_reuse.burn_in, no_reuse.candidates) == (False, False, 0, 16)
    assert (one.temporal, one.spatial, one.burn_in, one.candidates) == (False, False, 0, 1)
    persistent = ReSTIROptions.persistent()
    assert (persistent.spatial, persistent.multiview, persistent.offset_lifetime) == (False, "per_sensor", PERSISTENT_LIFETIME)
    assert persistent.lane_chains and not ReSTIROptions().lane_chains
    assert ReSTIROptions.reuse_for_image_only().forward_only
    assert {name: ReSTIROptions.preset(name) for name in PRESETS} == {
        "restir": ReSTIROptions(), "persistent": persistent, "b2": no_reuse, "b1": one,
        "forward_only": ReSTIROptions(forward_only=True)}


def test_explicit_arguments_win_over_a_configuration():
    assert ReSTIROptions.one_light_sample(candidates=4).candidates == 4
    assert ReSTIROptions.no_reuse(temporal=True).temporal
    assert ReSTIROptions.persistent(offset_lifetime=math.inf).offset_lifetime == math.inf
    assert ReSTIROptions.persistent(offset_lifetime=None).offset_lifetime == PERSISTENT_LIFETIME  # None: the preset's
    assert ReSTIROptions.persistent(multiview="auto").multiview == "per_sensor"  # a carried-over store keeps no lanes
    assert ReSTIROptions.preset("b1", neighbors=3, burn_in=5) == ReSTIROptions(candidates=1, neighbors=3, temporal=False,
                                                                                spatial=False, burn_in=5)


def test_frozen_and_replace_validates():
    o = ReSTIROptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.candidates = 3
    assert o.replace(candidates=3).candidates == 3 and o.candidates == 16
    with pytest.raises(ValueError, match="candidates must be >= 1, got 0"):
        o.replace(candidates=0)
    with pytest.raises(TypeError, match=r"unknown ReSTIR option\(s\) \['candidate'\] \(did you mean 'candidates'\?\)"):
        o.replace(candidate=3)
    assert hash(o) == hash(ReSTIROptions())  # usable as a key (a benchmark's configurations)


@pytest.mark.parametrize("changes, error, message", [
    ({"candidates": 2.0}, TypeError, "candidates must be an int, got float"),
    ({"burn_in": -1}, ValueError, "burn_in must be >= 0, got -1"),
    ({"edge_candidates": 0}, ValueError, "edge_candidates must be >= 1, got 0"),
    ({"radius": math.nan}, ValueError, "radius must be >= 0 (0 = automatic), got nan"),
    ({"normal_threshold": math.nan}, ValueError, "normal_threshold is a cosine, got nan"),
    ({"temporal": "yes"}, TypeError, "temporal must be True or False, got 'yes'"),
    ({"freeze": 2}, TypeError, "freeze must be True or False, got 2"),
    ({"edge_temporal": "always"}, ValueError, "edge_temporal must be True, False or 'auto', got 'always'"),
    ({"shading_bands": 1.0}, ValueError, "shading_bands must be True, False or 'auto', got 1.0"),
    ({"edge_chain_cap": 0.0}, ValueError, "edge_chain_cap must be > 0, got 0.0"),
    ({"offset_lifetime": 0.5}, ValueError, "offset_lifetime must be None or 0"),
    ({"light_guide": 0.5}, ValueError, "light_guide needs lane chains"),
    ({"light_guide": 1.0, "spatial": False, "offset_lifetime": 8}, ValueError, "light_guide must be a share"),
])
def test_bad_values_are_refused_when_built(changes, error, message):
    with pytest.raises(error) as info:
        ReSTIROptions(**changes)
    assert str(info.value).startswith(message)


def test_flags_accept_zero_and_one_as_mitsuba_properties_give_them():
    o = ReSTIROptions(temporal=0, spatial=1, freeze=0)
    assert (o.temporal, o.spatial, o.freeze) == (False, True, False) and type(o.temporal) is bool


def test_sampler_takes_options_or_a_preset_with_changes(scene):
    opts = ReSTIROptions.no_reuse(candidates=4)
    r = ReSTIRSampler(scene, opts)
    assert r.options == opts and r.integrator.options is opts and r.preset is None
    assert ReSTIRSampler(scene, opts, burn_in=3).options == opts.replace(burn_in=3)
    assert ReSTIRSampler(scene, preset="b2", candidates=4).options == opts
    assert ReSTIRSampler(scene).options == ReSTIROptions() and ReSTIRSampler(scene).preset == "auto"  # until it chooses
    assert SAMPLERS["restir"](scene, preset="b1", candidates=2).options == ReSTIROptions.one_light_sample(candidates=2)
    with pytest.raises(TypeError, match="give options= or preset=, not both"):
        ReSTIRSampler(scene, opts, preset="b2")
    with pytest.raises(TypeError, match=r"options must be a ReSTIROptions, got int \(other settings are keyword"):
        ReSTIRSampler(scene, 16)
    with pytest.raises(TypeError, match=r"unknown ReSTIR option\(s\) \['candidats'\]"):
        ReSTIRSampler(scene, candidats=4)


def test_options_have_one_channel(scene):
    """Setting an option on the integrator is refused with what to write instead."""
    r = ReSTIRSampler(scene, edge_temporal=True, silhouette_candidates=8)
    assert (r.integrator.edge_temporal, r.integrator.silhouette_candidates) == (True, 8)
    with pytest.raises(AttributeError, match=r"ReSTIRSampler\(scene, edge_guiding=False\)"):
        r.integrator.edge_guiding = False
    with pytest.raises(AttributeError, match=r"ReSTIROptions\(candidates=4\)"):
        r.integrator.candidates = 4
    assert r.integrator.edge_guiding == "auto" and r.integrator.candidates == 16


def test_pixel_and_render_samplers_are_apart(scene):
    """Two kinds under one YAML namespace: pixel samplers choose pixels, render samplers render
    (the public RenderSampler protocol that render(..., sampler=) takes)."""
    assert SAMPLERS == {**PIXEL_SAMPLERS, **RENDER_SAMPLERS} and not PIXEL_SAMPLERS.keys() & RENDER_SAMPLERS.keys()
    assert all(issubclass(cls, PixelSampler) for cls in PIXEL_SAMPLERS.values())
    assert all(isinstance(cls(scene), RenderSampler) for cls in RENDER_SAMPLERS.values())
    assert not isinstance(PIXEL_SAMPLERS["uniform"](scene), RenderSampler)
