"""The resampling pass of ReSTIR direct illumination: one wavefront of camera samples, each with
streaming RIS over light candidates and, with reuse, the combination with reservoirs nearby.

Everything here works on Dr.Jit values and the frozen :class:`PassSettings`, so that
:class:`ResamplingPass` can be traced once and replayed (``dr.freeze``). The algorithms are those
of Bitterli et al. 2020, "Spatiotemporal reservoir resampling for real-time ray tracing with
dynamic direct lighting" (streaming RIS, Alg. 1-3; the unbiased ``1/Z`` combination, Alg. 6), with
reservoirs kept across the steps of a gradient descent as in Wang et al. 2023, "Amortizing
samples in physics-based inverse rendering using ReSTIR".
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from . import _knn, _light_guide
from ._film import develop
from ._light import FORWARD_FLAGS, LightSample, Reservoirs, eval_target, fresh_reservoirs, rebuild_interaction, sample_candidate

__all__ = ["PassSettings", "ResamplingPass", "RedrawnLanes", "combine", "footprints", "normal_test", "sample_rays",
           "streaming_ris", "visible", "young_continuation"]

GUIDE_LEARNING_PER_STEP = 4  # candidates a step's guides learn from (unrolled streams; longer ones: all)
UNROLLED_CANDIDATES = 32  # more candidates: a symbolic loop (kernel size and compile time)
# Unguided wavefronts of up to this many lanes run the candidates as a symbolic loop: there,
# unrolling saves little and doubles the compile time; on wider ones it pays
SYMBOLIC_UP_TO_LANES = 128 * 128


@dataclass(frozen=True)
class PassSettings:
    """Everything a pass does besides its Dr.Jit inputs (a frozen pass is recorded per value).

    Of this pass: ``sensor``, ``spp``; ``source``, what it reuses (``"temporal"``: the previous
    step's reservoirs, ``"spatial"``: this pass's, ``"none"``); ``k`` neighbours within
    ``radius`` (world units), searched in ``layout`` (the screen search; None: another);
    ``zero_remainder`` (draw the ``p̂ = 0`` remainder's samples); ``keep_offsets`` (the lanes
    keep their camera offsets: ``prev`` holds this pass's lanes); ``candidates`` per lane;
    ``m_cap`` of searched neighbours. Of the integrator: ``shadowed`` target; ``lane_chains`` (a
    kept lane combines with its own previous reservoir, capped at ``chain_cap``);
    ``normal_threshold``; ``offset_lifetime``; ``light_guide`` share; ``young_candidates`` (a
    redrawn lane's RIS continues over that many more candidates; 0: not); ``learn`` (the guides
    learn from this pass's candidates); ``same_point`` (a lane's own chain reuses its sample's
    visibility).
    """

    sensor: int
    spp: int
    source: str
    k: int
    radius: float
    layout: _knn.ScreenLayout | None
    zero_remainder: bool
    keep_offsets: bool
    candidates: int
    m_cap: float
    shadowed: bool = True
    lane_chains: bool = False
    chain_cap: float = 0.0
    normal_threshold: float = 0.9
    offset_lifetime: float = 0.0
    light_guide: float = 0.0
    young_candidates: int = 0
    learn: bool = True
    same_point: bool = True


def tic() -> float:
    dr.sync_thread()
    return time.perf_counter()


class ResamplingPass:
    """The pass, with the neighbour search it keeps (its backend timings and ``last`` backend)."""

    def __init__(self, search: _knn.NeighbourSearch) -> None:
        self.search = search

    def run(self, seed: mi.UInt32, scene: mi.Scene, settings: PassSettings, prev: Any, buckets: Any, guide: Any,
            timings: dict | None):
        """One pass on Dr.Jit values only (so it can be frozen): camera rays, streaming RIS, the
        neighbour search (``screen`` when frozen) and the combination with ``prev`` (the
        reservoirs reused; ``buckets``: the store's reservoirs by pixel, ``carry_over``).
        ``settings.keep_offsets``: ``prev`` has this pass's lanes; each lane keeps its camera
        offset, so its shading point, unless redrawn (probability 1 / ``offset_lifetime``), and with
        temporal reuse alone combines with its own previous reservoir (a redrawn lane starts
        afresh). ``guide``: the lanes' light guides (``light_guide``; None: none), learned on.
        ``timings`` (a dict, or None when frozen): seconds per stage, measured with syncs.

        Returns ``(ray_weight, image, reservoirs, neighbours combined per lane, p̂ = 0 remainder,
        learned guides)``."""
        s = settings
        sensor, spp, source, k, keep_offsets, candidates = s.sensor, s.spp, s.source, s.k, s.keep_offsets, s.candidates

        def stage(name=None, since=None):
            if timings is None:
                return 0.0
            now = tic()
            if name is not None:
                timings[name] = now - since
            return now

        t0 = stage()
        sensor_obj = scene.sensors()[sensor]
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        n = w * h * spp
        sampler = sensor_obj.sampler().fork()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, n)
        lane = dr.arange(mi.UInt32, n)
        redrawn = None
        if keep_offsets:
            # redrawn independently of the offset and its hit (else offsets would drift towards
            # hits); NaN: no offset stored (an older checkpoint)
            stored = dr.isfinite(prev.offset.x)
            keep = stored
            if math.isfinite(s.offset_lifetime):
                redrawn = RedrawnLanes(n, s.offset_lifetime, seed)
                redrawn_here = redrawn.mask(lane)
                keep = stored & ~redrawn_here
            ray, ray_weight, offset = sample_rays(sensor_obj, sampler, spp, w, h, prev.offset, keep)
        else:
            ray, ray_weight, offset = sample_rays(sensor_obj, sampler, spp, w, h)
        pi = scene.ray_intersect_preliminary(mi.Ray3f(ray), coherent=True)
        si = pi.compute_surface_interaction(mi.Ray3f(ray), FORWARD_FLAGS)
        valid = si.is_valid()
        le_vis = si.emitter(scene).eval(si, valid)

        draws = None
        if guide is not None:  # a lane's guide is for its shading point: a redrawn offset forgets it
            draws = _light_guide.GuideDraws(_light_guide.forget(guide, keep) if keep_offsets else guide, s.light_guide)
        # Streaming RIS over light candidates (Wang et al. 2023, Alg. 1 and Eqs. 4-6)
        # a burn-in's guided pass (kept offsets, its own count) draws from what its first pass
        # learned, without learning on (the scatters would triple its cost)
        y, f_sel, phat_sel, w_sum, zero = streaming_ris(scene, si, sampler, valid, n, candidates, shadowed=s.shadowed,
                                                        zero_remainder=s.zero_remainder, guide=draws, learn=s.learn)
        m_fresh = dr.opaque(mi.Float, candidates)  # as the loop's count: one kernel for every count
        if redrawn is not None and s.young_candidates > 0:
            # A redrawn lane starts a new chain at a new point: with this step's candidates only, its
            # estimate is far noisier than its kept neighbours' for as long as its chain is young
            # (measured on ajar_painting, 128², burn-in 512: such lanes, 1 / offset_lifetime of
            # them a step, raised the gradient error from 0.0072 to 0.0098 within 32 steps). So
            # it continues this step's RIS over the burn-in's count of candidates: same point,
            # same candidate density, plain RIS over more candidates (a burn-in pass has that
            # many of its own). Spread over helper streams (see _young_continuation).
            young = valid & redrawn_here & stored
            y2, f2, phat2, w_sum2, m2 = young_continuation(scene, sensor_obj, seed, ray, pi, young, redrawn,
                                                           s.young_candidates, s.shadowed)
            take = young & (sampler.next_1d(young) * (w_sum + w_sum2) < w_sum2)
            y, f_sel, phat_sel = dr.select(take, y2, y), dr.select(take, f2, f_sel), dr.select(take, phat2, phat_sel)
            w_sum = w_sum + dr.select(young, w_sum2, 0.0)
            m_fresh = dr.select(young, mi.Float(candidates + m2), m_fresh)
        if not s.shadowed:  # one shadow ray for the chosen candidate; W = 0 when occluded
            seen = visible(scene, si, y, valid & (phat_sel > 0))
            w_sum, f_sel = dr.select(seen, w_sum, 0.0), dr.select(seen, f_sel, 0.0)
        r = fresh_reservoirs(ray, pi, si, valid, y, w_sum, phat_sel, m_fresh, offset)
        # with the guides' learned light: evaluated later, it would draw every candidate again
        # in a kernel of its own (measured: 8 of a guided pass's 23 ms)
        dr.eval(r, f_sel, phat_sel, le_vis, ray_weight, draws.learned if draws is not None else ())
        t1 = stage("ris", t0)

        n_ok, cap = None, s.m_cap
        if source != "none":
            src = prev if source == "temporal" else r
            exclude_self = source == "spatial"
            # opaque: each sensor state's automatic radius differs (its footprints, its first seed),
            # and as a literal it compiled these kernels again for every view and every new state
            radius_v = dr.opaque(mi.Float, s.radius)
            # screen window per query: ceil(radius / its pixel footprint), at most layout.window
            footprint = pi.t * dr.norm(ray.d_x - ray.d)
            windows = mi.UInt32(dr.clip(dr.ceil(radius_v / dr.select(footprint > 0, footprint, radius_v)), 1, 3))
            own_chain = keep_offsets and s.lane_chains
            if own_chain:  # the lane's own chain (a search could pick a neighbour's)
                d = src.p - r.p
                # a redrawn lane starts afresh: reused at its new shading point, a long memory
                # counts in Z (the support count of the 1/Z weight) where its sample is hidden, darkening or brightening the lane for
                # many steps (measured: worse than a fresh start)
                nbr, ok = [lane], [keep & r.valid & src.valid & (dr.dot(d, d) < radius_v * radius_v)]
                cap = s.chain_cap
                self.search.last = "lane"
            elif buckets is not None:  # the store (multiview="carry_over"): reprojected to this film
                nbr, ok = _knn.knn_in_buckets(src.p, buckets, r.p, w, h, spp, k, s.radius, windows)
                ok = [o & r.valid for o in ok]
                self.search.last = "reprojected"
            elif timings is None:  # frozen: the screen search (pure Dr.Jit, no host copies)
                nbr, ok = _knn.knn_screen(src.p, src.valid, r.p, s.layout, k, s.radius, exclude_self, windows)
                ok = [o & r.valid for o in ok]
            else:
                nbr, ok = self.search(src.p, src.valid, r.p, r.valid, k, s.radius,
                                      exclude_self=exclude_self, layout=s.layout, windows=windows)
            ok = normal_test(src, nbr, ok, r.n, s.normal_threshold)
            dr.eval(nbr, ok)
            t2 = stage("nn", t1)
            r, f_sel, phat_sel, n_ok = combine(scene, sampler, si, r, f_sel, phat_sel, src, nbr, ok, cap, shadowed=s.shadowed,
                                               same_point=own_chain and s.same_point)
            dr.eval(r, f_sel, n_ok)
            t1 = stage("combine", t2)
        contrib = ray_weight * (le_vis + f_sel * r.W)  # emission seen plus f W
        image = develop(contrib, spp, h, w)
        guide = None if draws is None else draws.learned
        dr.eval(image, zero if zero is not None else (), guide if guide is not None else ())
        stage("develop", t1)
        return ray_weight, image, r, n_ok, zero, guide


def young_continuation(scene: mi.Scene, sensor_obj: mi.Sensor, seed: mi.UInt32, ray: Any, pi: Any, young: mi.Bool,
                       redrawn: RedrawnLanes, extra: int, shadowed: bool):
    """``(y, f, p̂, w_sum, M)`` (lane-wide; 0 but where ``young``) of plain streaming RIS over
    about ``extra`` candidates (``M`` of them) at the first hits ``pi`` of the camera rays
    ``ray`` of the redrawn lanes ``young``.

    Why helpers: looping ``extra`` times in the redrawn lanes alone (a few lanes a step) keeps
    one core's SIMD packets busy with one live lane each, which cost more than the rest of a
    guided pass (measurements: docs/restir-measurements.md, "Cheaper guided steps").
    Instead ``P`` helper streams per redrawn lane each run ``c`` candidates at its
    shading point (``P c >= extra``, about one helper per lane of the pass), and one of
    them is chosen in proportion to its ``w_sum`` (exactly streaming RIS over all ``P c``
    candidates: they are i.i.d.). The lanes' light guides were emptied where redrawn, so
    the candidates are plain ones; the guides learn at the next steps."""
    n = dr.width(young)
    slots = redrawn.slots
    per_helper = max(1, math.ceil(extra * slots / n))
    helpers_per_slot = math.ceil(extra / per_helper)
    width = slots * helpers_per_slot
    helper = dr.arange(mi.UInt32, width)
    slot = helper // helpers_per_slot
    target = redrawn.lane_of(slot)
    ray, pi = mi.Ray3f(ray), mi.PreliminaryIntersection3f(pi)
    dr.eval(ray, pi, young)  # one kernel (gathered from unevaluated, each field is one)
    active = dr.gather(mi.Bool, young, target, redrawn.active(slot))
    ray_h = dr.gather(mi.Ray3f, ray, target, active)
    si_h = dr.gather(mi.PreliminaryIntersection3f, pi, target, active).compute_surface_interaction(
        ray_h, FORWARD_FLAGS, active)
    sampler = sensor_obj.sampler().fork()
    sampler.set_sample_count(1)
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed ^ 0x9E3779B9, width)
    y, f, phat, w_sum, _ = streaming_ris(scene, si_h, sampler, active, width, per_helper, shadowed=shadowed)
    dr.eval(y, f, phat, w_sum)
    # choose one helper per slot in proportion to its w_sum: the helper whose interval
    # [running sum - w_sum, running sum) holds u * total (the last one with mass also takes
    # the total itself, should rounding put u * total there)
    below_and_own = dr.block_prefix_sum(w_sum, helpers_per_slot, exclusive=False)
    total = dr.gather(mi.Float, below_and_own, slot * helpers_per_slot + helpers_per_slot - 1)
    t = mi.sample_tea_float32(slot, seed ^ 0x7A3C1E55) * total
    chosen = active & (w_sum > 0) & (below_and_own - w_sum <= t) & ((t < below_and_own) | (below_and_own >= total))
    y_out, f_out = dr.zeros(LightSample(), n), dr.zeros(mi.Color3f, n)
    phat_out, w_out = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
    dr.scatter(y_out, y, target, chosen)
    dr.scatter(f_out, f, target, chosen)
    dr.scatter(phat_out, phat, target, chosen)
    dr.scatter(w_out, total, target, chosen)  # where no helper has mass: w_sum 0, no sample
    return y_out, f_out, phat_out, w_out, helpers_per_slot * per_helper


def streaming_ris(scene: mi.Scene, si: mi.SurfaceInteraction3f, sampler: mi.Sampler, valid: mi.Bool, n: int,
                  candidates: int, *, shadowed: bool, zero_remainder: bool = False, unroll: bool | None = None,
                  guide: _light_guide.GuideDraws | None = None, learn: bool = True):
    """``(y, f, p̂, w_sum, (y0, w0))`` of streaming RIS over ``candidates`` light candidates
    (Wang et al. 2023, Alg. 1), with ``y0`` the first candidate whose ``p̂`` is 0 and ``w0 = n0 / (M p_c(y0))``
    (0 where none, or where ``y0`` is occluded): the gradient's ``p̂ = 0`` remainder (None
    without ``zero_remainder``). ``guide``: candidates partly from the lanes' light guides,
    which learn from them unless not ``learn`` (``guide.finish`` is called): from all of a
    symbolic loop's, from the first ``GUIDE_LEARNING_PER_STEP`` of an unrolled one (the
    learning's scatters cost more than the draws; measurements: docs/restir-measurements.md,
    "Young lanes and light guides").
    Up to ``UNROLLED_CANDIDATES`` the loop is unrolled into the kernel where that pays: with
    guides, or beyond ``SYMBOLIC_UP_TO_LANES`` lanes (``unroll`` forces either way); else a
    symbolic loop keeps the kernel small, since unrolled candidates lengthen the compilation
    (measurements: docs/restir-measurements.md, "Unrolled candidate loops"). Both draw the same
    random numbers."""
    y, y0 = dr.zeros(LightSample(), n), dr.zeros(LightSample(), n)
    f_sel, phat_sel = dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)
    w_sum, inv_pc0, n0 = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
    # continues what an earlier stream of this pass learned (its light)
    light_of_lane = mi.UInt32(guide.learned.light) if guide is not None else mi.UInt32(_light_guide.NO_LIGHT)

    def candidate(y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane, learn_here=True):
        y_m, f_m, phat_m, w_m, inv_pc, *u = sample_candidate(scene, si, sampler, valid, visibility=shadowed,
                                                             with_inv_pc=True, guide=guide)
        if guide is not None and learn and learn_here:
            light_of_lane = guide.learn(light_of_lane, y_m.em, u[0], w_m, ~y_m.delta, valid)
        w_sum = w_sum + w_m
        take = valid & (sampler.next_1d(valid) * w_sum < w_m)  # no division (A1)
        zero = valid & (inv_pc > 0) & (phat_m == 0) if zero_remainder else mi.Bool(False)
        first = zero & (n0 == 0)
        return (dr.select(take, y_m, y), dr.select(take, f_m, f_sel), dr.select(take, phat_m, phat_sel), w_sum,
                dr.select(first, y_m, y0), dr.select(first, inv_pc, inv_pc0), dr.select(zero, n0 + 1.0, n0),
                light_of_lane)

    state = (y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane)
    if unroll is None:
        unroll = candidates <= UNROLLED_CANDIDATES and (n > SYMBOLIC_UP_TO_LANES or guide is not None)
    if unroll:
        for i in range(candidates):  # a step's guides learn from a few (their scatters cost)
            state = candidate(*state, learn_here=i < GUIDE_LEARNING_PER_STEP)
    else:
        def body(i, sampler_, *rest):
            return (i + 1, sampler_, *candidate(*rest))

        # lanes without a shading point, or not asked for, exit at once; an opaque count: one
        # kernel for every number of candidates (a burn-in pass, a step, another sampler)
        count = dr.select(valid, dr.opaque(mi.UInt32, candidates), 0)
        _, _, *state = dr.while_loop(
            (dr.zeros(mi.UInt32, n), sampler, *state), lambda i, *rest: i < count, body,
            labels=("i", "sampler", "y", "f", "phat", "w_sum", "y0", "inv_pc0", "n0", "light"),
        )
    y, f_sel, phat_sel, w_sum, y0, inv_pc0, n0, light_of_lane = state
    if guide is not None:
        guide.finish(light_of_lane)
    if not zero_remainder:
        return y, f_sel, phat_sel, w_sum, None
    w0 = n0 * inv_pc0 / dr.opaque(mi.Float, candidates)
    w0 = dr.select(visible(scene, si, y0, valid & (w0 > 0)), w0, 0.0)  # V = 0: no gradient
    return y, f_sel, phat_sel, w_sum, (y0, w0)


def normal_test(source: Any, nbr: list, ok: list, n: mi.Vector3f, threshold: float) -> list:
    """``ok`` without the neighbours ``source[nbr]`` whose normal ``n'`` has ``n . n' < threshold``
    with the query normal ``n``."""
    return [o & (dr.dot(dr.gather(mi.Vector3f, source.n, j, o), n) >= threshold) for j, o in zip(nbr, ok)]


def combine(scene: mi.Scene, sampler: mi.Sampler, si: mi.SurfaceInteraction3f, r: Any, f_sel: mi.Color3f,
            phat_sel: mi.Float, source: Any, nbr: list, ok: list, m_cap: float, *, shadowed: bool,
            same_point: bool = False):
    """Bitterli et al.'s unbiased 1/Z combination (Bitterli et al. 2020, Alg. 6; Wang et al. 2023,
    Alg. 2-3, with the fresh reservoir counted in ``M`` and ``Z``) with ``M`` capped at ``m_cap``.
    ``same_point``: each neighbour is the lane's own previous reservoir at the
    same shading point in the same geometry (kept offsets), with the shadowed target: its
    sample, if ``W > 0``, was visible from this very point, so neither its shadow ray nor
    the rebuilt point of the support test is traced again (the same answers, 2 rays fewer)."""
    valid = r.valid  # si: the lanes' own shading points (the pass's first hits)
    cap = dr.opaque(mi.Float, m_cap)  # a literal compiled again for every cap (moving geometry lowers it)
    # w_0 = p̂(y_0) W_0 M_0: r_0.w_sum for a fresh RIS reservoir, and also right for an
    # already combined one, whose w_sum is not M p̂ W (measured: reusing w_sum there made W
    # grow without bound)
    y, m_sum = r.y, mi.Float(r.M)
    w_sum = phat_sel * r.W * m_sum
    neighbours, m_caps = [], []
    n_ok = dr.zeros(mi.UInt32, dr.width(valid))
    from_neighbour = dr.zeros(mi.Bool, dr.width(valid))
    for j, ok_i in zip(nbr, ok):
        ok_i = ok_i & valid
        r_i = dr.gather(Reservoirs(), source, j, ok_i)
        ok_i &= r_i.valid
        m_i = dr.minimum(r_i.M, cap)
        f_i, phat_i = eval_target(scene, si, r_i.y, ok_i & (r_i.W > 0), visibility=shadowed and not same_point)
        w_i = phat_i * r_i.W * m_i  # p̂(y_i) W_i M_i
        w_sum += w_i
        take = ok_i & (sampler.next_1d(valid) * w_sum < w_i)  # the streaming choice
        y = dr.select(take, r_i.y, y)
        f_sel, phat_sel = dr.select(take, f_i, f_sel), dr.select(take, phat_i, phat_sel)
        from_neighbour |= take
        m_sum += dr.select(ok_i, m_i, 0.0)
        neighbours.append((r_i, ok_i))
        m_caps.append(m_i)
        n_ok += dr.select(ok_i, 1, 0)
    if not shadowed:  # the chosen neighbour sample must be visible here (else W = 0)
        seen = ~from_neighbour | visible(scene, si, y, from_neighbour & (phat_sel > 0))
        f_sel, phat_sel = dr.select(seen, f_sel, 0.0), dr.select(seen, phat_sel, 0.0)
    # Support test: a neighbour counts where its reservoirs could hold y. Reservoirs hold
    # visible samples only (shadowed target, or W = 0 when occluded), so V is tested too.
    z = mi.Float(r.M)  # the fresh reservoir always counts
    for (r_i, ok_i), m_i in zip(neighbours, m_caps):
        if same_point:  # the neighbour's point is this one: p̂ there is phat_sel (visibility included)
            z += dr.select(ok_i & (phat_sel > 0), m_i, 0.0)
            continue
        si_i = rebuild_interaction(scene, r_i, ok_i, FORWARD_FLAGS)  # the neighbour's surface point (§6.2)
        _, phat_at_i = eval_target(scene, si_i, y, ok_i & (phat_sel > 0))
        z += dr.select(ok_i & (phat_at_i > 0), m_i, 0.0)
    good = (phat_sel > 0) & (z > 0)
    out = copy.copy(r)  # shallow: new attributes, the fresh reservoirs stay intact
    out.y, out.w_sum = y, w_sum
    out.W = dr.select(good, w_sum / dr.select(good, phat_sel * z, 1.0), 0.0)  # W = w_sum / (p̂ Z)
    out.M = dr.minimum(m_sum, cap)
    return out, f_sel, phat_sel, n_ok


def visible(scene: mi.Scene, si: mi.SurfaceInteraction3f, y, active: mi.Bool) -> mi.Bool:
    """True where light vertex ``y`` is unoccluded from ``si`` (False where inactive)."""
    return active & ~scene.ray_test(si.spawn_ray_to(y.p), active)


class RedrawnLanes:
    """Which of a pass's ``n`` lanes redraw their camera offset this step: ``n / lifetime`` of
    them on average, chosen by the seed alone (never by their offsets or hits), so each lane
    is redrawn with probability ``1 / lifetime``. Exactly ``floor(n / lifetime)`` or one more
    lanes, evenly strided from a random start: a fixed count of slots, so the redrawn lanes'
    work has a fixed shape (frozen passes; see ``_young_continuation``)."""

    def __init__(self, n: int, lifetime: float, seed: mi.UInt32) -> None:
        expected = n / lifetime
        self.n, self.slots = n, max(1, math.ceil(expected))
        self.stride = n // self.slots
        whole = math.floor(expected)
        self.count = whole + mi.UInt32(mi.sample_tea_float32(seed, 0x0FF5E7D0) < expected - whole)
        self.start = mi.sample_tea_32(seed, 0x51EDB0A7)[0] % n

    def lane_of(self, slot: mi.UInt32) -> mi.UInt32:
        return (self.start + slot * self.stride) % self.n

    def active(self, slot: mi.UInt32) -> mi.Bool:
        return slot < self.count

    def mask(self, lane: mi.UInt32) -> mi.Bool:
        """Lane-wide: whether each lane is redrawn."""
        d = (lane + self.n - self.start) % self.n
        return (d % self.stride == 0) & self.active(d // self.stride)


def sample_rays(sensor: mi.Sensor, sampler: mi.Sampler, spp: int, w: int, h: int, kept: mi.Point2f | None = None,
                keep: mi.Bool | None = None):
    """``(rays, weights, offsets)``: camera rays, ``spp`` consecutive lanes per pixel, row-major
    (as Mitsuba's ``sample_rays`` with a box filter); ``offsets`` are their positions in the
    pixel, fresh from ``sampler`` except ``kept`` where ``keep``."""
    idx = dr.arange(mi.UInt32, w * h * spp) // spp
    pos = mi.Vector2u(idx % w, idx // w)
    offset = sampler.next_2d()
    if kept is not None:
        offset = dr.select(keep, kept, offset)
    # sample2 of sample_ray is relative to the film crop (as in Mitsuba's sample_rays)
    pos_adj = (mi.Vector2f(pos) + offset) * dr.rcp(mi.ScalarVector2f(w, h))
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    t = sensor.shutter_open()
    if sensor.shutter_open_time() > 0:
        t += sampler.next_1d() * sensor.shutter_open_time()
    ray, weight = sensor.sample_ray_differential(time=t, sample1=0.0, sample2=pos_adj, sample3=aperture)
    return ray, mi.Color3f(weight), offset


def footprints(scene: mi.Scene, sensor: mi.Sensor, seed: int, spp: int, w: int, h: int) -> tuple[float, float]:
    """``(radius, small footprint)``: 2x the median pixel footprint ``t * |d_x - d|`` of the
    hit lanes (the default neighbour radius), and its 5th percentile (sizes the screen-space search window)."""
    with dr.suspend_grad():
        sampler = sensor.sampler().fork()
        sampler.set_sample_count(spp)
        sampler.set_samples_per_wavefront(spp)
        sampler.seed(seed, w * h * spp)
        ray, _, _ = sample_rays(sensor, sampler, spp, w, h)
        pi = scene.ray_intersect_preliminary(mi.Ray3f(ray), coherent=True)
        fp = pi.t * dr.norm(ray.d_x - ray.d)
        vals = np.asarray(dr.gather(mi.Float, fp, dr.compress(pi.is_valid() & dr.isfinite(fp))))
    vals = vals[vals > 0]
    if len(vals) == 0:
        return 1e-2, 5e-3
    return float(2.0 * np.median(vals)), float(np.percentile(vals, 5))


