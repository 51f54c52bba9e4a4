"""Light guides of ReSTIR's lane chains (``light_guide``, ``torchir/integrators/_light_guide.py``).

The guide only changes where candidates are drawn; RIS weighs them by the mixture's density.
So: draws follow the density the weights use (checked bin by bin against the histograms), the
RIS normalisation ``mean(p̂ / q)`` keeps its expectation with a learned guide (and falls in
variance behind a door slit, the guide's reason to exist), lanes forget on a redrawn offset,
and chains with a guide stay unbiased. Bounds come from the estimators' own spread.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import torchir
from torchir.functions import render
from torchir.samplers import ReSTIRSampler

@pytest.fixture(scope="module")
def ajar() -> torchir.Scene:
    return torchir.Scene.builtin("ajar_painting", resolution=16, texture=4)


@pytest.fixture(scope="module")
def guide_module(ajar):
    from torchir.integrators import _light_guide

    return _light_guide


def _at_one_point(scene: mi.Scene, n: int, x: float = 0.3, y: float = 0.1) -> mi.SurfaceInteraction3f:
    """``n`` copies of the painting's point near ``(x, y)``, seen from the camera."""
    o = mi.Point3f(dr.full(mi.Float, 0.0, n), dr.full(mi.Float, 0.0, n), dr.full(mi.Float, 3.0, n))
    d = dr.normalize(mi.Vector3f(x, y, -3.0))
    return scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(d.x + 0.0 * o.x, d.y + 0.0 * o.x, d.z + 0.0 * o.x)))


def _sampler(n: int, seed: int) -> mi.Sampler:
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    return sampler


def _learned_guide(gm, scene, si, n: int, candidates: int, seed: int = 1):
    from torchir.integrators._light import sample_candidate

    draws = gm.GuideDraws(gm.empty_guide(n, gm.guided_lights(scene)), 0.5)  # empty: every candidate drawn as usual
    sampler, light = _sampler(n, seed), mi.UInt32(draws.light)
    for _ in range(candidates):
        y, _, _, w, u = sample_candidate(scene, si, sampler, si.is_valid(), guide=draws)
        light = draws.learn(light, y.em, u, w, ~y.delta, si.is_valid())
        sampler.schedule_state()  # else its state is a chain growing by a step per candidate: a new kernel each
        dr.eval(light, draws.learned.mass_x, draws.learned.mass_y)
    return draws.finish(light)


def test_draws_follow_the_density_the_weights_use(ajar, guide_module):
    """Each lane holds the same made-up histograms (empty bins included): emitters 3 : 1 (the
    slit's area light : the point fill), and marginals over the area light's ``u``. 2^16 draws
    pick each emitter, and on the area light land in each bin (half bins: uniformly within
    it), at the rate of its mass plus the prior (``GUIDE_PRIOR`` of the total, spread evenly;
    5 binomial sd); on the fill ``u`` stays uniform. ``density_factor`` of a draw is
    ``(1 - s) + s h_l(l) / p_sel(l) (h_x h_y on the area light)``."""
    gm, scene = guide_module, ajar.mi_scene
    bins, n = gm.GUIDE_BINS, 1 << 16
    area = [i for i, e in enumerate(scene.emitters()) if not mi.has_flag(e.flags(), mi.EmitterFlags.Delta)]
    assert len(scene.emitters()) == 2 and len(area) == 1
    area, fill = area[0], 1 - area[0]
    rng = np.random.default_rng(0)
    mx = rng.random(bins) * (rng.random(bins) < 0.6)
    my = np.zeros(bins)
    my[[0, 5, bins - 1]] = [1.0, 3.0, 0.5]  # the edges of [0, 1) too
    ml = np.zeros(2)
    ml[[area, fill]] = [3.0, 1.0]

    def density(mass):  # per bin (for u: on [0, 1))
        smoothed = mass + gm.GUIDE_PRIOR * mass.sum() / len(mass)
        return len(mass) * smoothed / smoothed.sum()

    guide = gm.LightGuide(dr.full(mi.UInt32, area, n), *(mi.Float(np.tile(m, n).astype(np.float32)) for m in (ml, mx, my)))
    draws = gm.GuideDraws(guide, 0.999)
    taken, light, u = draws.draw(_sampler(n, 3), mi.Bool(True))
    taken, light = np.asarray(taken), np.asarray(light)
    assert taken.mean() > 0.99
    p_area = density(ml)[area] / 2
    sd = math.sqrt(taken.sum() * p_area * (1 - p_area))
    assert abs((light[taken] == area).sum() - taken.sum() * p_area) < 5 * sd
    on_area, on_fill = taken & (light == area), taken & (light == fill)
    for axis, mass in ((np.asarray(u.x), mx), (np.asarray(u.y), my), (np.asarray(u.x), None)):
        axis = axis[on_area] if mass is not None else axis[on_fill]
        assert axis.min() >= 0.0 and axis.max() < 1.0
        counts = np.bincount(np.minimum((axis * 2 * bins).astype(int), 2 * bins - 1), minlength=2 * bins)
        p = np.repeat(density(mass) / bins if mass is not None else np.full(bins, 1.0 / bins), 2) / 2.0
        sd = np.sqrt(len(axis) * p * (1 - p))
        assert np.all(np.abs(counts - len(axis) * p) <= 5 * sd), (counts, len(axis) * p)
    has_u = mi.Bool(light != fill)
    sel_weight = 1.0 / scene.pdf_emitter(mi.UInt32(light))
    factor = np.asarray(draws.density_factor(mi.UInt32(light), u, has_u, sel_weight, mi.Bool(taken)))
    bx = np.minimum((np.asarray(u.x) * bins).astype(int), bins - 1)
    by = np.minimum((np.asarray(u.y) * bins).astype(int), bins - 1)
    p_sel = np.asarray(scene.pdf_emitter(mi.UInt32(light)))
    h = np.where(light == area, density(mx)[bx] * density(my)[by], 1.0)
    expected = 0.001 + 0.999 * density(ml)[light] / 2 * h / p_sel
    np.testing.assert_allclose(factor[taken], expected[taken], rtol=1e-4)
    empty = gm.GuideDraws(gm.empty_guide(n, gm.guided_lights(scene)), 0.5)  # nothing learned: the usual draws
    assert np.all(np.asarray(empty.density_factor(mi.UInt32(light), u, has_u, sel_weight, mi.Bool(True))) == 1.0)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_learned_guide_keeps_ris_unbiased_and_cuts_its_variance_behind_the_slit(ajar, guide_module):
    """At one painting point, ``mean(p̂ / q)`` estimates ``∫ p̂`` (the light reaching it,
    visibility included). Lanes that learned from 1024 usual candidates each then draw half
    their candidates from their guides: the mean agrees with usual sampling within 4 s.e.,
    and the variance per candidate is at least 4x lower (measured: 6.3x; the bright
    light is seen through the slit as a strip ~1 % of its area). (The unbiasedness at CI size:
    test_learned_guide_keeps_the_ris_weights_expectation.)"""
    from torchir.integrators._light import sample_candidate

    gm, scene, n = guide_module, ajar.mi_scene, 1 << 12
    si = _at_one_point(scene, n)
    assert bool(dr.all(si.is_valid()))
    learned = _learned_guide(gm, scene, si, n, 1024)
    lit = np.asarray(learned.light) != gm.NO_LIGHT
    assert lit.mean() > 0.9  # nearly every lane found the strip in 1024 candidates
    usual, guided = [], []
    sampler_u, sampler_g = _sampler(n, 7), _sampler(n, 8)
    draws = gm.GuideDraws(learned, 0.5)
    for _ in range(256):
        usual.append(np.asarray(sample_candidate(scene, si, sampler_u, si.is_valid())[3]))
        guided.append(np.asarray(sample_candidate(scene, si, sampler_g, si.is_valid(), guide=draws)[3]))
        sampler_u.schedule_state(), sampler_g.schedule_state()
        dr.eval()
    usual, guided = np.concatenate(usual), np.concatenate(guided)
    se = math.hypot(usual.std() / math.sqrt(len(usual)), guided.std() / math.sqrt(len(guided)))
    assert abs(guided.mean() - usual.mean()) < 4 * se, (guided.mean(), usual.mean(), se)
    assert se < 0.02 * usual.mean()  # the comparison can see a bias of a few per cent
    assert usual.var() > 4 * guided.var(), (usual.var(), guided.var())


def test_learned_guide_keeps_the_ris_weights_expectation(ajar, guide_module):
    """The unbiasedness half of the slow test above at CI size, through ``sample_candidate`` (where
    RIS divides each guided candidate's weight by the mixture's density): 4096 lanes at one
    painting point learn their guides from 256 usual candidates (about 3 in 4 find the strip),
    then draw 64 candidates each, half from their guides; ``mean(p̂ / q)`` agrees with usual
    sampling's within 4 s.e. The s.e. comes from the spread of the lanes' means (the lanes are
    independent; a lane's candidates share its guide), about 3 % of the mean here, so a
    weighting off by 15 % fails."""
    from torchir.integrators._light import sample_candidate

    gm, scene, n, draws_per_lane = guide_module, ajar.mi_scene, 1 << 12, 64
    si = _at_one_point(scene, n)
    learned = _learned_guide(gm, scene, si, n, 256)
    assert (np.asarray(learned.light) != gm.NO_LIGHT).mean() > 0.5  # most lanes draw from a learned guide
    draws = gm.GuideDraws(learned, 0.5)
    sampler_u, sampler_g = _sampler(n, 7), _sampler(n, 8)
    usual, guided = np.zeros(n), np.zeros(n)
    for _ in range(draws_per_lane):
        usual += np.asarray(sample_candidate(scene, si, sampler_u, si.is_valid())[3]) / draws_per_lane
        guided += np.asarray(sample_candidate(scene, si, sampler_g, si.is_valid(), guide=draws)[3]) / draws_per_lane
        sampler_u.schedule_state(), sampler_g.schedule_state()
        dr.eval()
    se = math.hypot(usual.std(ddof=1), guided.std(ddof=1)) / math.sqrt(n)
    assert se < 0.04 * usual.mean()  # power: a bias of 16 % is 4 s.e.
    assert abs(guided.mean() - usual.mean()) < 4 * se, (guided.mean(), usual.mean(), se)


def test_guides_learn_only_non_delta_lights_and_forget_redrawn_lanes(ajar, guide_module):
    """A lane's ``u`` light is the slit's area light (the fill is a point light: never), its
    emitter histogram holds both; ``forget`` empties exactly the lanes not kept."""
    gm, scene, n = guide_module, ajar.mi_scene, 1 << 12
    si = _at_one_point(scene, n)
    learned = _learned_guide(gm, scene, si, n, 64)
    lights = np.asarray(learned.light)
    delta = [i for i, e in enumerate(scene.emitters()) if mi.has_flag(e.flags(), mi.EmitterFlags.Delta)]
    assert delta and not np.isin(lights, delta).any()
    assert (lights != gm.NO_LIGHT).any()
    keep = mi.Bool(np.arange(n) % 3 != 0)
    out = gm.forget(learned, keep)
    gone = np.arange(n) % 3 == 0
    assert np.all(np.asarray(out.light)[gone] == gm.NO_LIGHT)
    np.testing.assert_array_equal(np.asarray(out.light)[~gone], lights[~gone])
    for before, after in ((learned.mass_l, out.mass_l), (learned.mass_x, out.mass_x), (learned.mass_y, out.mass_y)):
        before, after = np.asarray(before).reshape(n, -1), np.asarray(after).reshape(n, -1)
        assert np.all(after[gone] == 0) and before[gone].any()
        np.testing.assert_array_equal(after[~gone], before[~gone])
    # the emitter histogram learned both lights, the fill's (a point light) too
    per_light = np.asarray(learned.mass_l).reshape(n, 2).sum(0)
    assert np.all(per_light > 0)


@pytest.mark.parametrize("bad", [-0.1, 1.0, float("nan")])
def test_light_guide_share_is_checked(ajar, bad):
    with pytest.raises(ValueError, match="light_guide must be a share"):
        ReSTIRSampler(ajar, preset="persistent", light_guide=bad)


@pytest.mark.parametrize("preset", ["restir", "b2"])
def test_light_guide_needs_lane_chains(ajar, preset):
    """Elsewhere a lane's shading point moves every step: a guide would do nothing, so it is refused."""
    with pytest.raises(ValueError, match="light_guide needs lane chains"):
        ReSTIRSampler(ajar, preset=preset, light_guide=0.5)
    ReSTIRSampler(ajar, preset=preset, light_guide=0.0)  # off: fine


def test_chains_with_a_light_guide_stay_unbiased(ajar):
    """Persistent chains (a quarter of the offsets redrawn a step, so lanes forget and relearn)
    drawing half their candidates from their guides: 12 chains' image means match prb's
    converged image within 4 s.e. (chains' spread and the reference's; together under 3 %)."""
    imgs = np.stack([render(ajar, {}, spp=4096, seed=10_000 + i).cpu().numpy() for i in range(4)])
    means = imgs.reshape(4, -1).mean(1)
    ref_mean, ref_se = means.mean(), means.std(ddof=1) / 2.0
    chains = []
    for c in range(12):
        r = ReSTIRSampler(ajar, preset="persistent", candidates=8, burn_in=16, offset_lifetime=4.0, light_guide=0.5,
                          seed=c + 1)
        chains.append(np.mean([render(ajar, {}, spp=2, seed=s, sampler=r).cpu().numpy().mean() for s in range(10)][2:]))
        assert r.integrator.states[0].guide is not None
    chains = np.array(chains)
    se = math.hypot(chains.std(ddof=1) / math.sqrt(len(chains)), ref_se)
    assert se < 0.03 * ref_mean
    assert abs(chains.mean() - ref_mean) < 4 * se, (chains.mean(), ref_mean, se)


def test_an_unlit_room_renders_exactly_zero_with_zero_gradients(ajar):
    """What the slow test_ajar_painting_closed_door_without_fill_is_exactly_dark
    (tests/core/test_scenes_restir.py) checks, on this file's scene with the chains test's
    options (their kernels serve both): with both lights at zero every candidate has ``p̂ = 0``,
    as behind the closed door, so reservoirs hold ``W = 0`` and the guides never learn a light.
    The image and the texture gradient must then be exactly 0, not NaN (a ``0 / 0`` in a fresh
    or combined reservoir's ``W``, or in a guide's empty histograms), over two steps of guided
    persistent chains (the second combines the first's reservoirs and draws from its guides).
    The slow test also runs prb and spatiotemporal reuse, whose gradient kernels added ~6 s to
    this file (measured, cold cache): the RIS, ``W`` and combination they run are these chains'.
    That ``door=0, fill=0`` lets no light in is checked on the geometry in
    tests/core/test_scenes_restir.py."""
    import torch

    key = "painting.bsdf.reflectance.data"
    dark = {k: torch.zeros_like(ajar.get(k)) for k in ("gap_light.emitter.radiance.value", "fill.intensity.value")}
    guided = ReSTIRSampler(ajar, preset="persistent", candidates=8, burn_in=16, offset_lifetime=4.0, light_guide=0.5)
    for step in range(2):
        texture = torch.full_like(ajar.get(key), 0.5).requires_grad_()
        image = render(ajar, {key: texture, **dark}, spp=2, seed=step, sampler=guided)
        (image * torch.linspace(1.0, 2.0, image.numel()).reshape(image.shape)).sum().backward()  # a non-zero adjoint
        assert torch.equal(image.detach(), torch.zeros_like(image)), f"not dark (NaN: {bool(image.isnan().any())})"
        assert torch.equal(texture.grad, torch.zeros_like(texture.grad)), f"not zero (NaN: {bool(texture.grad.isnan().any())})"
    guide = guided.integrator.states[0].guide
    assert guide is not None and float(dr.sum(guide.mass_l)[0]) == 0.0  # nothing learned
    lit = render(ajar, {key: torch.full_like(ajar.get(key), 0.5)}, spp=2, seed=2, sampler=guided)
    assert float(lit.mean()) > 0  # the same chains, lit: the zeros above came from the lights


def test_guides_survive_a_checkpoint(ajar):
    """``state_dict`` keeps the lanes' guides: a loaded sampler draws from what was learned.
    (The chains test's options: its kernels, compiled already, serve here too.)"""
    options = dict(preset="persistent", candidates=8, burn_in=16, offset_lifetime=4.0, light_guide=0.5)
    r = ReSTIRSampler(ajar, **options)
    for s in range(2):
        render(ajar, {}, spp=2, seed=s, sampler=r)
    saved = r.integrator.states[0].guide
    assert saved is not None and float(dr.sum(saved.mass_x)[0]) > 0
    loaded = ReSTIRSampler(ajar, **options)
    loaded.load_state_dict(r.state_dict())
    got = loaded.integrator.states[0].guide
    for k in ("light", "mass_l", "mass_x", "mass_y"):
        np.testing.assert_array_equal(np.asarray(getattr(got, k)), np.asarray(getattr(saved, k)))
