"""Per-lane learned light-candidate densities for ReSTIR's lane chains (``light_guide``).

Why: at a kept shading point behind a door slit, only a small share of uniform light samples
on the bright light are visible, so RIS weights ``w = p̂ / p_c`` are mostly 0 and rarely huge,
and a chain needs very many candidates to reach the camera-sampling floor (measurements:
docs/restir-measurements.md, "Young lanes and light guides"). A lane whose shading point stays
put can learn *where* its light comes from and draw candidates there.

What: each lane learns, from the weights ``w = p̂ / q`` of its candidates (importance-weighted
estimates of where ``p̂`` lives):
- ``h_l``, how its light divides among the emitters (a histogram over the emitter index; up
  to ``MAX_GUIDED_LIGHTS`` emitters, else the lane's one light below only);
- for one light ``light`` (the first non-delta light it saw lit), two marginal histograms of
  ``GUIDE_BINS`` bins, ``h_x`` and ``h_y``, over that light's primary sample ``u`` in [0, 1)²
  (the 2D sample its emitter's ``sample_direction`` maps to a point).
Each histogram gets ``GUIDE_PRIOR`` of its mass again, spread evenly. A candidate is drawn
from the guide with probability ``share`` (emitter ``l ~ h_l``; on ``light``, ``u_x ~ h_x``
and ``u_y ~ h_y``, elsewhere ``u`` uniform), else as before (emitter by ``sampling_weight``,
then the emitter's sampling). Its density against the usual ``p_c`` is

    q / p_c = (1 - share) + share * h_l(l) / p_sel(l) * (l = light ? h_x(u_x) h_y(u_y) : 1),

so RIS divides ``w`` (and ``1 / p_c``) by that factor. Unbiased whatever the histograms hold:
``q > 0`` wherever ``p_c > 0`` (the ``1 - share`` part), and the histograms are fixed during
a pass (learned mass goes to the next step). A slit seen from a point is a thin strip of the
light; when the strip runs along one axis of ``u`` (a rectangle light parallel to the door),
the product of marginals covers it tightly; otherwise it covers the strip's bounding box.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

GUIDE_BINS = 32  # per axis of u
MAX_GUIDED_LIGHTS = 1024  # more emitters: no per-lane emitter histogram (memory: lanes x emitters)
NO_LIGHT = 0xFFFFFFFF  # a lane that has not seen a lit non-delta light yet
# each histogram gets this share of its mass again, spread evenly: a strip seen through a slit
# spans one axis of u, and its first few hits would otherwise confine the guide to a few bins
# of it (measured at a point behind the slit, 1-3 hits and no prior: the variance of p̂ / q
# rose 1.7x over no guide)
GUIDE_PRIOR = 0.25
ONE_MINUS_ULP = 1.0 - 2.0**-24  # the largest float32 below 1


class LightGuide:
    """Per-lane guides of n lanes: ``light`` (n,) UInt32; ``mass_l`` (n * emitters,) Float (or
    width 0 beyond ``MAX_GUIDED_LIGHTS``); ``mass_x``, ``mass_y`` (n * GUIDE_BINS,) Float."""

    DRJIT_STRUCT = {"light": mi.UInt32, "mass_l": mi.Float, "mass_x": mi.Float, "mass_y": mi.Float}

    def __init__(self, light=None, mass_l=None, mass_x=None, mass_y=None) -> None:
        self.light, self.mass_l, self.mass_x, self.mass_y = light, mass_l, mass_x, mass_y


def guided_lights(scene: mi.Scene) -> int:
    """Bins of the per-lane emitter histogram (0: none, too many emitters)."""
    count = len(scene.emitters())
    return count if count <= MAX_GUIDED_LIGHTS else 0


def empty_guide(n: int, lights: int) -> LightGuide:
    """Guides that know nothing (every candidate drawn as without a guide); ``lights``:
    :func:`guided_lights`."""
    return LightGuide(dr.full(mi.UInt32, NO_LIGHT, n), dr.zeros(mi.Float, n * lights),
                      dr.zeros(mi.Float, n * GUIDE_BINS), dr.zeros(mi.Float, n * GUIDE_BINS))


def forget(guide: LightGuide, keep: mi.Bool) -> LightGuide:
    """``guide`` with the lanes where ``keep`` is False emptied (a redrawn camera offset: a new
    shading point, whose light comes from elsewhere)."""
    n = dr.width(guide.light)

    def kept(mass):
        bins = dr.width(mass) // n
        return dr.select(dr.gather(mi.Bool, keep, dr.arange(mi.UInt32, dr.width(mass)) // bins), mass, 0.0) if bins else mass

    return LightGuide(dr.select(keep, guide.light, NO_LIGHT), kept(guide.mass_l), kept(guide.mass_x), kept(guide.mass_y))


class _Histograms:
    """Per-lane histograms of ``bins`` bins (n * bins masses) with the prior, ready to draw
    from and to evaluate: running sums ``cdf`` (n * bins,) and totals (n,)."""

    def __init__(self, mass: mi.Float, n: int, bins: int) -> None:
        self.bins, self.n = bins, n
        self.base = dr.arange(mi.UInt32, n) * bins
        total = dr.block_sum(mass, bins)
        prior = dr.gather(mi.Float, total * (GUIDE_PRIOR / bins), dr.arange(mi.UInt32, n * bins) // bins)
        self.cdf = dr.block_prefix_sum(mass + prior, bins, exclusive=False)
        self.total = total * (1.0 + GUIDE_PRIOR)

    def _mass(self, b: mi.UInt32, active: mi.Bool) -> tuple[mi.Float, mi.Float]:
        """``(mass of bin b, running sum below it)``."""
        hi = dr.gather(mi.Float, self.cdf, self.base + b, active)
        lo = dr.select(b > 0, dr.gather(mi.Float, self.cdf, self.base + b - 1, active & (b > 0)), 0.0)
        return hi - lo, lo

    def draw_bin(self, xi: mi.Float, active: mi.Bool) -> tuple[mi.UInt32, mi.Float]:
        """``(bin, fraction within it)`` of ``xi`` in [0, 1) through the lanes' CDFs."""
        t = xi * self.total
        count = dr.zeros(mi.UInt32, self.n)  # bins whose running sum is <= t (binary lifting)
        step = 1 << (self.bins.bit_length() - 1)
        while step >= 1:
            nxt = count + step
            c = dr.gather(mi.Float, self.cdf, self.base + nxt - 1, active & (nxt <= self.bins))
            count = dr.select(active & (nxt <= self.bins) & (c <= t), nxt, count)
            step //= 2
        b = dr.minimum(count, self.bins - 1)
        m, lo = self._mass(b, active)
        return b, dr.clip((t - lo) / dr.select(m > 0, m, 1.0), 0.0, 1.0)

    def probability(self, b: mi.UInt32, active: mi.Bool) -> mi.Float:
        """Probability of bin ``b`` (0 where inactive or the lane's histogram is empty)."""
        m, _ = self._mass(b, active)
        return dr.select(active & (self.total > 0), m / dr.select(self.total > 0, self.total, 1.0), 0.0)


class GuideDraws:
    """One pass's view of the guides: draws from them, their density, and the mass they learn.

    The histograms are read as they were at the start of the pass; what the pass learns is
    added to copies (``learned``), for the next pass."""

    def __init__(self, guide: LightGuide, share: float) -> None:
        n = dr.width(guide.light)
        self.n, self.share, self.light = n, float(share), guide.light
        self.lights = dr.width(guide.mass_l) // n
        self.h_l = _Histograms(guide.mass_l, n, self.lights) if self.lights else None
        self.h_x = _Histograms(guide.mass_x, n, GUIDE_BINS)
        self.h_y = _Histograms(guide.mass_y, n, GUIDE_BINS)
        self.on_u = (guide.light != NO_LIGHT) & (self.h_x.total > 0) & (self.h_y.total > 0)
        self.on = self.on_u if self.h_l is None else self.h_l.total > 0  # lanes that draw from their guide
        self.learned = LightGuide(mi.UInt32(guide.light), mi.Float(guide.mass_l), mi.Float(guide.mass_x),
                                  mi.Float(guide.mass_y))
        dr.make_opaque(self.learned.mass_x, self.learned.mass_y)  # scattered into
        if self.lights:
            dr.make_opaque(self.learned.mass_l)

    def _u(self, h: _Histograms, xi: mi.Float, active: mi.Bool) -> mi.Float:
        b, frac = h.draw_bin(xi, active)
        return dr.minimum((mi.Float(b) + frac) / GUIDE_BINS, ONE_MINUS_ULP)

    def draw(self, sampler: mi.Sampler, active: mi.Bool) -> tuple[mi.Bool, mi.UInt32, mi.Point2f]:
        """``(taken, emitter, u)``: where ``taken``, a candidate from the lane's guide."""
        pick = sampler.next_1d(active)
        xi = sampler.next_2d(active)
        taken = active & self.on & (pick < self.share)
        if self.h_l is None:
            light = self.light
        else:  # pick rescaled: the emitter and u get independent uniforms
            light, _ = self.h_l.draw_bin(pick / self.share, taken)
        on_light = taken & self.on_u & (light == self.light)
        u = mi.Point2f(self._u(self.h_x, xi.x, on_light), self._u(self.h_y, xi.y, on_light))
        return taken, light, dr.select(on_light, u, xi)

    def density_factor(self, light: mi.UInt32, u: mi.Point2f, has_u: mi.Bool, sel_weight: mi.Float,
                       active: mi.Bool) -> mi.Float:
        """``q / p_c`` of candidates on emitter ``light`` at primary sample ``u`` (module
        docstring; ``has_u`` False for delta lights, whose point ``u`` does not move;
        ``sel_weight = 1 / p_sel(light)``, as the candidate's sampling already has it); 1 where
        the lane draws nothing from its guide."""
        active = active & self.on
        if self.h_l is None:
            p_l = dr.select(active & (light == self.light), 1.0, 0.0)
        else:
            p_l = self.h_l.probability(light, active)
        on_light = active & has_u & self.on_u & (light == self.light)
        h_u = dr.select(on_light, GUIDE_BINS * self.h_x.probability(_bin(u.x), on_light)
                        * GUIDE_BINS * self.h_y.probability(_bin(u.y), on_light), 1.0)
        guided = dr.select(active, p_l * h_u * sel_weight, 0.0)
        return dr.select(self.on, (1.0 - self.share) + self.share * guided, 1.0)

    def learn(self, light_of_lane: mi.UInt32, light: mi.UInt32, u: mi.Point2f, w: mi.Float, has_u: mi.Bool,
              active: mi.Bool) -> mi.UInt32:
        """Add candidates' weights ``w = p̂ / q`` to the lanes' learned histograms: the emitter
        histogram for every candidate, the ``u`` marginals for those on the lane's light
        (``light_of_lane``, a loop variable of the caller: start from ``self.light``), which a
        lane without one adopts from its first lit candidate with ``has_u`` (non-delta).
        Returns the lanes' lights; hand the last to :meth:`finish`."""
        lane = dr.arange(mi.UInt32, self.n)
        lit = active & (w > 0)
        if self.lights:
            dr.scatter_add(self.learned.mass_l, w, lane * self.lights + light, lit, mode=dr.ReduceMode.NoConflicts)
        adopt = lit & has_u & (light_of_lane == NO_LIGHT)
        light_of_lane = dr.select(adopt, light, light_of_lane)
        add = lit & has_u & (light == light_of_lane)
        dr.scatter_add(self.learned.mass_x, w, lane * GUIDE_BINS + _bin(u.x), add, mode=dr.ReduceMode.NoConflicts)
        dr.scatter_add(self.learned.mass_y, w, lane * GUIDE_BINS + _bin(u.y), add, mode=dr.ReduceMode.NoConflicts)
        return light_of_lane

    def finish(self, light_of_lane: mi.UInt32) -> LightGuide:
        """The guides for the next pass."""
        self.learned.light = light_of_lane
        return self.learned


def _bin(u: mi.Float) -> mi.UInt32:
    return mi.UInt32(dr.clip(mi.Int32(u * GUIDE_BINS), 0, GUIDE_BINS - 1))
