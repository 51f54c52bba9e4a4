"""The automatic choices of ReSTIR and of its helpers checked against values worked out by hand:
``preset="auto"``'s predicted costs and choice (:func:`torchir.samplers._restir_auto.choose`),
the probe's variance split and timing fit (:func:`~torchir.samplers._restir_auto.probe_scene`
with a fake renderer and clock), the shadow-edge and silhouette ``"auto"`` strategies, and the
timed choice of the neighbour search (:class:`~torchir.integrators._knn.NeighbourSearch` with
fake back-ends and clock). Pure Python: no scene is rendered.

The cost model is written out here again from the module's docstring and comments (the
constants are the documented model and are used by name; every formula is recomputed), so that
a wrong burn-in charge, divisor, clamp or margin in the module disagrees with it."""
from __future__ import annotations

import dataclasses
import math
import types
from typing import Any

import torchir  # noqa: F401, I001  (before torch)

import mitsuba as mi
import numpy as np
import pytest
import torch

from torchir.integrators import _knn, _mesh_edges, _restir_boundary
from torchir.integrators._knn import NeighbourSearch, ScreenLayout
from torchir.samplers import ReSTIROptions
from torchir.samplers import _restir_auto as auto
from torchir.samplers._restir_auto import SceneProbe, choose

REL = 1e-9


def probe(light: float, camera: float = 1.0, t0: float = 0.02, t_c: float = 4e-4, **changes: Any) -> SceneProbe:
    base = SceneProbe(light_variance=light, camera_variance=camera, camera_resolved=True, step_seconds=t0,
                      candidate_seconds=t_c, missed_share=0.0, geometry=False, spp=1, seconds=0.1)
    return dataclasses.replace(base, **changes)


# ------------------------------------------------------------------------------ the model, by hand
@dataclasses.dataclass
class Expected:
    costs: dict[str, float]
    strategy: str
    plain_candidates: int
    burn_in: int | None  # the persistent chains' burn-in passes (None: not considered)
    burn_in_candidates: float | None  # x, the burn-in's candidates per lane before rounding up


def expected(p: SceneProbe, steps: int, grad_paths: str = "decorrelated") -> Expected:
    """The documented model: error² x seconds per step, the burn-in's one-off time spread over
    the ``steps`` of the run, relative to the best plain RIS."""
    v_c, v_l, t0, t_c = p.camera_variance, p.light_variance, p.step_seconds, p.candidate_seconds

    # plain RIS over m candidates: variance v_C + v_L / m, a step costs t0 + m t_c
    plain = {m: (v_c + v_l / m) * (t0 + m * t_c) for m in auto.PLAIN_CANDIDATES}
    best_m = min(auto.PLAIN_CANDIDATES, key=lambda m: plain[m])  # the first of equal costs
    base = plain[best_m]

    # spatiotemporal: 16 candidates at SPATIOTEMPORAL_STEP x a B.2 step, its light variance
    # SPATIOTEMPORAL_GAIN times lower; its burn-in is SPATIOTEMPORAL_BURN_IN extra steps once
    m = auto.SPATIOTEMPORAL_CANDIDATES
    st_step = auto.SPATIOTEMPORAL_STEP * (t0 + m * t_c)
    st_variance = v_c + v_l / (auto.SPATIOTEMPORAL_GAIN * m)
    st_run_seconds = steps * st_step + auto.SPATIOTEMPORAL_BURN_IN * st_step
    costs = {"plain": 1.0, "spatiotemporal": st_variance * (st_run_seconds / steps) / base}

    burn_in = x = None
    if not p.geometry and p.missed_share <= auto.MISSED_SHARE:
        c = auto.PERSISTENT_CANDIDATES
        step = auto.PERSISTENT_STEP * (t0 + c * t_c)
        chains = auto.CHAINS_BURNED_IN if grad_paths == "decorrelated" else 1
        # minimise f(x) = (W v_C + v_L / x) (n step + chains x t_c): f'(x) = 0 at
        # W v_C chains t_c = v_L n step / x²
        optimum = math.sqrt(v_l * steps * step / (auto.PERSISTENCE_WINDOW * v_c * chains * t_c))
        lowest = 64.0 * c
        highest = max(lowest, auto.BURN_IN_SHARE * steps * step / (chains * t_c))  # burn-in time <= its share of the run
        x = min(highest, max(lowest, optimum))
        burn_in = math.ceil(x / c)
        run_seconds = steps * step + chains * burn_in * c * t_c  # the passes that run: burn_in x c candidates per chain
        costs["persistent"] = (auto.PERSISTENCE_WINDOW * v_c + v_l / (burn_in * c)) * (run_seconds / steps) / base

    reuse = min((k for k in costs if k != "plain"), key=lambda k: costs[k])
    strategy = reuse if auto.REUSE_MARGIN * costs[reuse] < 1.0 else "plain"
    return Expected(costs, strategy, best_m, burn_in, x)


def check_choice(p: SceneProbe, steps: int, want: Expected, pinned: dict[str, Any] | None = None) -> auto.AutoChoice:
    got = choose(p, steps, pinned)
    assert got.costs.keys() == want.costs.keys()
    for k, v in want.costs.items():
        assert got.costs[k] == pytest.approx(v, rel=REL, abs=0), k
    assert got.strategy == want.strategy and got.planned_steps == steps
    pins = pinned or {}
    if want.strategy == "plain":
        assert got.options == ReSTIROptions.no_reuse(candidates=want.plain_candidates).replace(**pins)
    elif want.strategy == "spatiotemporal":
        assert got.options == ReSTIROptions.spatiotemporal(candidates=auto.SPATIOTEMPORAL_CANDIDATES,
                                                           burn_in=auto.SPATIOTEMPORAL_BURN_IN).replace(**pins)
        assert got.options.temporal and got.options.spatial
    else:
        c = auto.PERSISTENT_CANDIDATES
        assert got.options == ReSTIROptions.persistent(candidates=c, burn_in=want.burn_in, m_cap=4 * want.burn_in * c,
                                                       light_guide=0.5).replace(**pins)
        assert got.options.lane_chains and not got.options.spatial
    return got


def test_the_hand_model_puts_the_burn_in_at_the_minimum_of_its_charged_cost():
    """The closed-form burn-in of the hand model (and so of the module, which the other tests
    compare with it) is where the charged cost is lowest, as the comment in ``choose`` derives."""
    p = probe(3e3)
    c, n = auto.PERSISTENT_CANDIDATES, 300
    step = auto.PERSISTENT_STEP * (p.step_seconds + c * p.candidate_seconds)

    def f(x: float) -> float:
        return (auto.PERSISTENCE_WINDOW * p.camera_variance + p.light_variance / x) * (
            n * step + auto.CHAINS_BURNED_IN * x * p.candidate_seconds)

    x = expected(p, n).burn_in_candidates
    assert 64 * c < x < auto.BURN_IN_SHARE * n * step / (auto.CHAINS_BURNED_IN * p.candidate_seconds)  # not clamped
    assert f(x) < min(f(x * (1 - 1e-4)), f(x * (1 + 1e-4)))


CASES = {
    # name: (probe, planned steps, the strategy worked out by hand)
    "light-bound, coarse texture": (probe(3e4), 300, "persistent"),  # burn-in at its optimum (x about 6971)
    "light-bound, long run": (probe(3e4), 3000, "persistent"),
    "light-bound, burn-in at its share of the run": (probe(3e5), 300, "persistent"),  # optimum 22045 > cap 16200
    "moderately light-bound": (probe(3e3), 300, "persistent"),
    "light-bound, short run": (probe(3e4), 3, "plain"),  # a run too short to pay for any burn-in
    "short run, burn-in at its floor": (probe(3e3), 3, "plain"),  # optimum 220 < 64 x 4 candidates
    "one step": (probe(3e4), 1, "plain"),
    "spatiotemporal wins": (probe(1e3), 300, "spatiotemporal"),
    "camera-bound": (probe(0.5), 300, "plain"),
    "no light noise": (probe(0.0), 300, "plain"),  # one candidate is exact
    "cheap candidates": (probe(50.0, t0=0.1, t_c=1e-5), 300, "plain"),  # the best plain RIS has many
    "geometry": (probe(3e4, geometry=True), 300, "spatiotemporal"),
    "missed share above the bound": (probe(3e4, missed_share=0.3), 300, "spatiotemporal"),
    "missed share just above the bound": (probe(3e4, missed_share=math.nextafter(auto.MISSED_SHARE, 1.0)), 300,
                                          "spatiotemporal"),
    "missed share at the bound": (probe(3e4, missed_share=auto.MISSED_SHARE), 300, "persistent"),
    "unresolved floor": (probe(3e4, camera=0.05, camera_resolved=False), 300, "persistent"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_predicted_costs_and_options_match_the_model_worked_out_by_hand(name):
    """``choice.costs`` equal the hand model's (1e-9 relative) and the strategy and its options
    (candidates, burn-in, M cap) are the model's, for light-bound, camera-bound, geometry,
    short and long runs and missed shares on either side of the bound."""
    p, steps, strategy = CASES[name]
    want = expected(p, steps)
    assert want.strategy == strategy  # the hand model agrees with the case's reasoning
    check_choice(p, steps, want)


def test_shared_gradient_paths_burn_in_one_chain():
    """With ``grad_paths="shared"`` pinned only the image's chains burn in: the charge and the
    optimum count one chain, not :data:`CHAINS_BURNED_IN`."""
    p = probe(3e4)
    shared, decorrelated = expected(p, 300, "shared"), expected(p, 300)
    assert shared.burn_in != decorrelated.burn_in
    check_choice(p, 300, shared, {"grad_paths": "shared"})


def _boundary(p: SceneProbe, steps: int) -> float:
    """The light variance where the hand model's best reuse is exactly REUSE_MARGIN times
    cheaper than plain RIS (bisection in log space)."""
    def above(v: float) -> bool:  # reuse chosen
        want = expected(dataclasses.replace(p, light_variance=v), steps)
        return auto.REUSE_MARGIN * min(c for k, c in want.costs.items() if k != "plain") < 1.0

    lo, hi = 1.0, 1e6
    assert not above(lo) and above(hi)
    for _ in range(100):
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if above(mid) else (mid, hi)
    return math.sqrt(lo * hi)


@pytest.mark.parametrize("p, steps, reuse", [
    (probe(1.0), 300, "spatiotemporal"),  # persistent costs more here: spatiotemporal decides
    (probe(1.0, geometry=True), 300, "spatiotemporal"),
    (probe(1.0), 30, "persistent"),  # a run too short for the spatiotemporal burn-in
], ids=["spatiotemporal", "spatiotemporal-geometry", "persistent"])
def test_reuse_is_chosen_exactly_where_it_beats_plain_by_its_margin(p, steps, reuse):
    """Right below and above the light variance where ``costs[reuse] x REUSE_MARGIN == 1``:
    plain RIS below, reuse above (a margin applied the other way, or not at all, moves the
    boundary far from here)."""
    v = _boundary(p, steps)
    below, above = dataclasses.replace(p, light_variance=v * (1 - 1e-6)), dataclasses.replace(p, light_variance=v * (1 + 1e-6))
    for q, strategy in ((below, "plain"), (above, reuse)):
        want = expected(q, steps)
        assert want.strategy == strategy
        assert auto.REUSE_MARGIN * want.costs[reuse] == pytest.approx(1.0, abs=1e-5)  # right at the boundary
        check_choice(q, steps, want)


# ------------------------------------------------------------------------------ the probe
class FakeClock:
    """``time.perf_counter`` that moves only when told to."""

    def __init__(self) -> None:
        self.now = 100.0

    def perf_counter(self) -> float:
        return self.now


def fake_probe(monkeypatch, grads: dict[tuple[int, int], dict[str, np.ndarray]], seconds: Any, seed: int = 5,
               names: tuple[str, ...] = ("tex.data", "unused.data"), spp: int = 2) -> tuple[SceneProbe, list]:
    """Run :func:`probe_scene` with ``torchir.functions.render`` replaced: the render with
    ``m`` candidates on camera rays ``r`` returns an image whose sum has gradient
    ``grads[m, r][key]`` for each key it uses (and whose pixels are those gradients where nothing
    is differentiated), and advances the clock by ``seconds(m, r, call)``."""
    clock = FakeClock()
    calls = []

    def render(scene, leaves, spp, seed, seed_grad, sensor, sampler):
        rays = seed - 4 * base_seed
        assert seed_grad == seed + 2**31 and sensor == 3 and spp == spp_
        calls.append((sampler.candidates, rays))
        clock.now += seconds(sampler.candidates, rays, len(calls))
        used = grads[sampler.candidates, rays]
        return torch.cat([(leaves[k] * torch.as_tensor(g, dtype=torch.float64)).reshape(-1) for k, g in used.items()])

    base_seed, spp_ = seed, spp
    monkeypatch.setattr("torchir.functions.render", render)
    monkeypatch.setattr(auto, "time", clock)
    values = {k: torch.ones(8, dtype=torch.float64) for k in ("tex.data", "unused.data", "mesh.vertex_positions", "fixed")}
    samplers = tuple(types.SimpleNamespace(candidates=m) for m in auto.PROBE_CANDIDATES)
    return auto.probe_scene(object(), values, frozenset(names), 3, spp, seed, samplers), calls


HIGH_A = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0, 0.0])
HIGH_B = np.array([2.0, 2.0, 1.0, 4.0, 7.0, 0.0, 3.0, 0.0])  # reaches 6 where a does not, misses 5
D_A = np.array([1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])  # low - high on rays a: |d|² = 6
D_B = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, -1.0])  # on rays b: |d|² = 5
# |high_a - high_b|² = 1 + 0 + 4 + 0 + 4 + 36 + 9 + 0 = 54


def gradients(scale: float = 1.0, key: str = "tex.data") -> dict[tuple[int, int], dict[str, np.ndarray]]:
    low, high = auto.PROBE_CANDIDATES
    return {(low, 1): {key: HIGH_A + scale * D_A}, (high, 1): {key: HIGH_A},
            (high, 2): {key: HIGH_B}, (low, 2): {key: HIGH_B + scale * D_B}, (low, 3): {key: HIGH_B}}


def step_seconds(t0: float, t_c: float, compile_seconds: float = 2.0, jitter: float = 0.01):
    """A render's fake seconds: t0 + m t_c, the first of each candidate count compiling, the
    second 4-candidate one (rays b) slower than the third (rays c)."""
    def seconds(m: int, rays: int, call: int) -> float:
        return t0 + m * t_c + (compile_seconds if rays == 1 else 0.0) + (jitter if (m, rays) == (4, 2) else 0.0)
    return seconds


def light_scale(floor_share: float) -> float:
    """The scale of D_A, D_B at which the floor left, v_C = 27 - v_L / 256, is ``floor_share``
    of its bound 27 (v_L = 11 s² / 2 / (1/4 + 1/256))."""
    return math.sqrt((1 - floor_share) * 27 * 256 / (11 / 2 / (1 / 4 + 1 / 256)))


@pytest.mark.parametrize("scale, resolved", [(1.0, True), (light_scale(0.11), True), (light_scale(0.09), False),
                                             (40.0, False)], ids=["resolved", "barely", "barely-not", "unresolved"])
def test_probe_splits_the_variances_and_fits_the_timings_in_closed_form(monkeypatch, scale, resolved):
    """Known gradients: E|low - high|² = v_L (1/4 + 1/256) on the same rays, E|high_a - high_b|²
    = 2 (v_C + v_L / 256); the 4-candidate timing is the faster of its two timed renders, and the
    two counts' timings give t_c = (s_256 - s_4) / 252 and t0 = s_4 - 4 t_c. Where the floor left
    is at most 10% of its bound it does not stand out of the light noise: camera_resolved False,
    v_C kept at 10% of the bound."""
    p, calls = fake_probe(monkeypatch, gradients(scale), step_seconds(0.05, 1e-3))
    assert calls == [(4, 1), (256, 1), (256, 2), (4, 2), (4, 3)]
    light = (6.0 + 5.0) * scale**2 / 2 / (1 / 4 + 1 / 256)
    bound = 54.0 / 2
    camera = bound - light / 256
    assert (camera > 0.1 * bound) == resolved
    assert p.light_variance == pytest.approx(light, rel=1e-12)
    assert p.camera_variance == pytest.approx(camera if resolved else 0.1 * bound, rel=1e-12)
    assert p.camera_resolved is resolved
    assert p.candidate_seconds == pytest.approx(1e-3, rel=1e-9) and p.step_seconds == pytest.approx(0.05, rel=1e-9)
    assert p.missed_share == pytest.approx(2 / 7, rel=1e-12)  # entries 5 and 6 of the 7 either reaches
    assert not p.geometry and p.spp == 2
    assert p.seconds == pytest.approx(5 * 0.05 + (4 + 256 + 256 + 4 + 4) * 1e-3 + 2 * 2.0 + 0.01, rel=1e-9)


def test_probe_timing_clamps(monkeypatch):
    """No fixed cost measured: t0 is kept at 10% of the 4-candidate step; 256 candidates timed
    faster than 4: t_c is kept at 1e-9 s."""
    p, _ = fake_probe(monkeypatch, gradients(), step_seconds(0.0, 1e-3))
    assert p.candidate_seconds == pytest.approx(1e-3, rel=1e-9) and p.step_seconds == pytest.approx(0.1 * 4e-3, rel=1e-9)
    p, _ = fake_probe(monkeypatch, gradients(), lambda m, rays, call: 0.3 if m == 4 else 0.1)
    assert p.candidate_seconds == 1e-9 and p.step_seconds == pytest.approx(0.3 - 4e-9, rel=1e-12)


def test_probe_of_geometry_and_of_the_image(monkeypatch):
    """A differentiated vertex buffer marks the probe as geometry; with nothing differentiated
    the image's pixels are the vectors compared (same variances) and nothing counts as missed."""
    p, _ = fake_probe(monkeypatch, gradients(key="mesh.vertex_positions"), step_seconds(0.05, 1e-3),
                      names=("mesh.vertex_positions",))
    assert p.geometry and p.missed_share == pytest.approx(2 / 7, rel=1e-12)
    image, _ = fake_probe(monkeypatch, gradients(), step_seconds(0.05, 1e-3), names=())
    assert not image.geometry and image.missed_share == 0.0
    assert image.light_variance == pytest.approx(p.light_variance, rel=1e-12)
    assert image.camera_variance == pytest.approx(p.camera_variance, rel=1e-12)


# ------------------------------------------------------------------------------ shadow edges, silhouettes
class FakeScene:
    def __init__(self, lights: int) -> None:
        self.lights = lights

    def emitters(self) -> list:
        return [object()] * self.lights


@pytest.fixture
def edge_counts(monkeypatch) -> None:
    """``edges_of(mesh)``: a table with ``mesh.edges`` edges (no mesh is built)."""
    monkeypatch.setattr(_restir_boundary, "edges_of", lambda mesh: types.SimpleNamespace(a=np.zeros(mesh.edges)))


def meshes(*edges: int) -> list:
    return [types.SimpleNamespace(edges=e) for e in edges]


@pytest.mark.parametrize("samples, many", [(1000, False), (999, True), (1, True), (10**6, False)])
def test_edge_strategy_threshold_on_pairs_per_sample(edge_counts, samples, many):
    """(edge, light) pairs: (1500 + 500) edges x 2 lights = 4000. At most EDGE_PAIRS_PER_SAMPLE
    (4) per sample (1000 samples: exactly 4) the guide, beyond it chains; explicit settings win;
    no chains without temporal reuse or with forward_only."""
    from torchir.integrators.restir_di import ReSTIRDirectIntegrator

    assert _restir_boundary.EDGE_PAIRS_PER_SAMPLE == 4.0
    scene, ms = FakeScene(2), meshes(1500, 500)  # (1500 + 500) x 2 = 4000 pairs
    integrator = ReSTIRDirectIntegrator()
    assert integrator.edge_strategy(scene, ms, samples) == (many, not many)
    for temporal, guiding in ((True, True), (True, False), (False, True), (False, False)):
        fixed = ReSTIRDirectIntegrator(edge_temporal=temporal, edge_guiding=guiding)
        assert fixed.edge_strategy(scene, ms, samples) == (temporal, guiding)
    half = ReSTIRDirectIntegrator(edge_guiding=True)  # chains still "auto"
    assert half.edge_strategy(scene, ms, samples) == (many, True)
    for off in ({"temporal": False}, {"forward_only": True}):
        assert ReSTIRDirectIntegrator(**off).edge_strategy(scene, ms, samples) == (False, not many)


def test_silhouette_sampling_auto_follows_where_mitsuba_is_wrong(monkeypatch):
    """``silhouette_sampling="auto"``: torchir's silhouettes exactly where a moving mesh is one
    that Mitsuba's primary term gets wrong: with a crease or an open border (an edge whose two
    third vertices are one)."""
    from torchir.integrators.restir_di import ReSTIRDirectIntegrator

    def table(crease: list[bool], open_border: bool) -> _mesh_edges.EdgeTable:
        c1 = np.array([2, 3], np.uint32)
        c2 = np.array([2 if open_border else 4, 5], np.uint32)
        return _mesh_edges.EdgeTable(np.zeros(2, np.uint32), np.ones(2, np.uint32), c1, c2, np.array(crease))

    tables = {"smooth": table([False, False], False), "crease": table([False, True], False),
              "open": table([False, False], True)}
    monkeypatch.setattr(_mesh_edges, "edges_of", lambda mesh: tables[mesh])
    assert [_mesh_edges.mitsuba_silhouettes_wrong(m) for m in ("smooth", "crease", "open")] == [False, True, True]
    integrator = ReSTIRDirectIntegrator()
    assert integrator.silhouette_sampling == "auto"
    assert not integrator.uses_silhouette_sampling(["smooth", "smooth"])
    assert integrator.uses_silhouette_sampling(["smooth", "crease"]) and integrator.uses_silhouette_sampling(["open"])
    assert ReSTIRDirectIntegrator(silhouette_sampling=True).uses_silhouette_sampling(["smooth"])
    assert not ReSTIRDirectIntegrator(silhouette_sampling=False).uses_silhouette_sampling(["crease"])


# ------------------------------------------------------------------------------ the neighbour search
class FakeBackends:
    """Back-ends of known speed: each call advances the fake clock by the back-end's next time
    (its first call: compilation, ``compile_seconds``)."""

    def __init__(self, times: dict[str, list[float]], compile_seconds: float = 50.0) -> None:
        self.times, self.compile_seconds = times, compile_seconds
        self.clock = FakeClock()
        self.calls: list[str] = []

    def search(self, backend, points, valid, queries, q_valid, k, radius, exclude_self, layout, windows=None):
        earlier = self.calls.count(backend)
        self.calls.append(backend)
        self.clock.now += self.compile_seconds if earlier == 0 else self.times[backend][(earlier - 1) % len(self.times[backend])]
        return [mi.UInt32(0)], [mi.Bool(True)]


def timed_search(monkeypatch, times: dict[str, list[float]], timed: int) -> tuple[NeighbourSearch, FakeBackends]:
    fake = FakeBackends(times)
    monkeypatch.setattr(_knn, "time", fake.clock)
    monkeypatch.setattr(_knn, "_default_backend", lambda: "kdtree")  # the kd-tree a candidate (CPU, scipy)
    s = NeighbourSearch("auto", timed=timed)
    monkeypatch.setattr(s, "_search", fake.search)
    return s, fake


def args() -> tuple:
    """Points, validity, queries, their validity, k, radius (the fake back-ends ignore them)."""
    return mi.Point3f(0, 0, 0), mi.Bool(True), mi.Point3f(0, 0, 0), mi.Bool(True), 2, 1.0


@pytest.mark.parametrize("timed", [1, 3, 4])
def test_auto_neighbour_search_times_each_backend_then_keeps_the_fastest(monkeypatch, timed):
    """With back-ends of known speed (screen fastest by median, though one of its calls is slow,
    and its compilation slowest of all): one untimed call each, then ``timed`` timed calls each,
    round robin; then the lowest median is kept and no back-end is timed again."""
    times = {"kdtree": [3.0], "grid": [2.0], "screen": [1.0, 1.0, 1.0, 30.0]}  # screen's mean (8.25) the highest
    s, fake = timed_search(monkeypatch, times, timed)
    layout = ScreenLayout(1, 1, 1)
    trials = 3 * (1 + timed)
    for call in range(trials):
        assert True not in s.chosen
        s(*args(), layout=layout)
    assert fake.calls == ["kdtree", "grid", "screen"] * (1 + timed)
    assert {b: s.seconds[b] for b in s.BACKENDS} == {b: [times[b][i % len(times[b])] for i in range(timed)]
                                                      for b in s.BACKENDS}
    want = min(s.BACKENDS, key=lambda b: float(np.median([times[b][i % len(times[b])] for i in range(timed)])))
    assert want == "screen" and s.chosen == {True: "screen"}
    for _ in range(3):
        s(*args(), layout=layout)
    assert fake.calls[trials:] == ["screen"] * 3
    assert all(len(v) == timed for v in s.seconds.values())  # kept: no more timing


def test_auto_neighbour_search_choices_with_and_without_a_layout_are_separate(monkeypatch):
    """The calls without a layout (a moving sensor) choose between kd-tree and grid on their own
    timings, those with a layout among all three; a chain layout leaves the screen search only."""
    s, fake = timed_search(monkeypatch, {"kdtree": [1.0], "grid": [2.0], "screen": [0.5]}, 2)
    for _ in range(2 * 3):
        s(*args())
    assert fake.calls == ["kdtree", "grid"] * 3 and s.chosen == {False: "kdtree"}
    assert s.seconds == {"kdtree": [1.0, 1.0], "grid": [2.0, 2.0], "screen": []}
    s(*args(), layout=ScreenLayout(1, 1, 1))  # kd-tree and grid are timed already: the screen search's untimed call
    s(*args(), layout=ScreenLayout(1, 1, 1))
    assert fake.calls[6:] == ["screen", "screen"] and True not in s.chosen
    s(*args(), layout=ScreenLayout(1, 1, 1))
    assert s.chosen == {False: "kdtree", True: "screen"} and s.seconds["screen"] == [0.5, 0.5]
    s(*args())
    assert fake.calls[-1] == "kdtree"
    chains, fake = timed_search(monkeypatch, {"screen": [4.0]}, 2)
    for _ in range(3):
        chains(*args(), layout=ScreenLayout(1, 1, 2, chains=True))
    assert fake.calls == ["screen"] * 3 and chains.chosen == {True: "screen"}
