"""Light samples, reservoirs and the target function of ReSTIR direct illumination (Wang et al. 2023).

A light sample ``y`` lives in the *light-vertex measure*: the emitter index, the
position, normal and uv on it, and whether it is a delta light. Re-evaluated at any shading
point ``x`` it gives

    f(y; x) = Le(y -> x) * fs(x, w) * g(y, x) * V(x, y),   g = 1 (delta) or |n_y . w| / dist^2

and the target p̂(y; x) = lum(f) (the luminance of Wang et al. 2023, Eq. 14). Candidates come from
standard emitter sampling with ``p_c = pdf_sel * pdf_dir * (delta ? 1 : g)``, so
``p̂ / p_c = lum(NEE weight * fs * V)``, and a reservoir's ``W`` is in area (or counting) measure,
valid at every shading point.

The gradient ``df/dθ * W`` of a reservoir's sample covers only ``supp(p̂) = supp(f)``:
a black texel or a switched-off light has ``f = 0`` but ``df/dθ > 0``. The integrator estimates
that remainder from the same candidates (``inv_pc`` of :func:`sample_candidate`, and
:func:`eval_target` with ``positive_only=False``); see ``restir_di.ReSTIRDirectIntegrator``.

The Dr.Jit struct types are built lazily (they need the Mitsuba variant); :func:`fresh_reservoirs`
makes a pass's reservoirs from its RIS.
"""
from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi


@functools.cache
def _types(variant: str):
    class LightSample:
        """One light vertex: emitter index, position, normal and uv on it, delta flag."""

        DRJIT_STRUCT = {"em": mi.UInt32, "p": mi.Point3f, "n": mi.Vector3f, "uv": mi.Point2f, "delta": mi.Bool}

    class Reservoirs:
        """One reservoir per camera sample, keyed by its shading point.

        The shading point is stored as (shape index, primitive, primitive uv) plus its camera
        ray (``o``, ``d``, ``t``), so it can be rebuilt after parameters change; ``p``
        and ``n`` are the position and shading normal used for the neighbour search;
        ``offset`` is the camera sample's position in its pixel (kept by persistent offsets).
        """

        DRJIT_STRUCT = {
            "y": LightSample,
            "W": mi.Float,
            "M": mi.Float,
            "w_sum": mi.Float,
            "shape": mi.UInt32,
            "prim": mi.UInt32,
            "prim_uv": mi.Point2f,
            "o": mi.Point3f,
            "d": mi.Vector3f,
            "t": mi.Float,
            "offset": mi.Point2f,
            "p": mi.Point3f,
            "n": mi.Vector3f,
            "valid": mi.Bool,
        }

    return LightSample, Reservoirs


def LightSample():  # noqa: N802 - a type accessor
    return _types(mi.variant())[0]


def Reservoirs():  # noqa: N802
    return _types(mi.variant())[1]


def shape_pointers(scene: mi.Scene, index: mi.UInt32, active: mi.Bool) -> mi.ShapePtr:
    return dr.gather(mi.ShapePtr, scene.shapes_dr(), index, active)


# What the forward pass needs of a shading point: position, uv (textures) and shading frame;
# no surface derivatives (the backward rebuilds with RayFlags.All, differentiably).
FORWARD_FLAGS = mi.RayFlags.UV | mi.RayFlags.ShadingFrame


def rebuild_interaction(scene: mi.Scene, r, active: mi.Bool, flags=mi.RayFlags.All) -> mi.SurfaceInteraction3f:
    """Rebuild the shading points of reservoirs ``r`` from (shape, prim, prim_uv) and their
    camera ray: meshes interpolate the *current* vertices with the stored barycentrics."""
    n = dr.width(r.t)
    active = mi.Bool(active) & r.valid
    pi = dr.zeros(mi.PreliminaryIntersection3f, n)
    pi.valid = active
    pi.t = r.t
    pi.shape = shape_pointers(scene, r.shape, active)
    pi.prim_index = r.prim
    pi.prim_uv = r.prim_uv
    pi.shape_index = r.shape
    return pi.compute_surface_interaction(mi.Ray3f(r.o, r.d), flags, active)


def eval_target(scene: mi.Scene, si: mi.SurfaceInteraction3f, y, active: mi.Bool, visibility: bool = True,
                positive_only: bool = True):
    """``(f, p̂)`` of light samples ``y`` at shading points ``si`` (see the module docstring).

    ``f`` is the RGB contribution ``Le * fs * g * V`` (differentiable through Le and fs when
    called under ``dr.resume_grad``); ``p̂ = lum(f)``. Zero (never NaN) where inactive, on the
    light, or behind a one-sided emitter. ``visibility=False`` skips the shadow ray.
    ``positive_only=False`` keeps lanes whose ``lum(f)`` is 0 (their ``f`` is 0 but may have a
    gradient: a black albedo, a light switched off).
    """
    active = mi.Bool(active) & si.is_valid()
    n = dr.width(active)
    to_y = y.p - si.p
    dist = dr.norm(to_y)
    active &= dist > 0
    d = to_y / dr.select(active, dist, 1.0)
    ds = dr.zeros(mi.DirectionSample3f, n)
    ds.p, ds.n, ds.uv, ds.delta = y.p, y.n, y.uv, y.delta
    ds.time = si.time
    ds.d, ds.dist = d, dist
    ds.pdf = dr.zeros(mi.Float, n)
    ds.emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), y.em, active)
    le = scene.eval_emitter_direction(si, ds, active)
    g = dr.select(y.delta, 1.0, dr.abs(dr.dot(y.n, d)) / dr.select(active, dist * dist, 1.0))
    bsdf = si.bsdf()
    fs = bsdf.eval(mi.BSDFContext(), si, si.to_local(d), active)  # cosine included
    f = le * fs * g
    active &= dr.isfinite(mi.luminance(f))
    if positive_only:
        active &= mi.luminance(f) > 0
    if visibility:
        active &= ~scene.ray_test(si.spawn_ray_to(y.p), active)
    f = dr.select(active, f, 0.0)
    return f, dr.select(active, mi.luminance(f), 0.0)


def sample_candidate(scene: mi.Scene, si: mi.SurfaceInteraction3f, sampler: mi.Sampler, active: mi.Bool,
                     visibility: bool = True, with_inv_pc: bool = False, guide=None):
    """One light candidate: emitter by ``sampling_weight``, then the emitter's own
    sampling. Returns ``(y, f, p̂, w)`` with the RIS weight ``w = p̂ / p_c`` (Wang et al. 2023, Eq. 5);
    ``visibility=False`` skips the shadow ray (the unshadowed target). ``with_inv_pc`` appends ``1 / p_c`` wherever
    ``y`` is a valid sample, also where ``p̂ = 0`` (0 elsewhere).
    ``guide`` (``_light_guide.GuideDraws``): some candidates come from the lanes' learned
    guides instead, and ``p_c`` is the mixture's density; the emitter's primary sample ``u``
    is appended (what the guides learn from)."""
    active = mi.Bool(active)  # the &= below must not modify the caller's mask
    n = dr.width(active)
    u = sampler.next_2d(active)
    idx, sel_weight, u_x = scene.sample_emitter(u.x, active)
    u_light = mi.Point2f(u_x, u.y)
    if guide is not None:
        taken, g_light, g_u = guide.draw(sampler, active)
        idx, u_light = dr.select(taken, g_light, idx), dr.select(taken, g_u, u_light)
        p_sel = scene.pdf_emitter(idx, taken)
        sel_weight = dr.select(taken, dr.select(p_sel > 0, 1.0 / p_sel, 0.0), sel_weight)
    em = dr.gather(mi.EmitterPtr, scene.emitters_dr(), idx, active)
    ds, weight = em.sample_direction(si, u_light, active)  # weight = Le / pdf_dir
    active &= ds.pdf > 0
    wo = si.to_local(ds.d)
    fs = si.bsdf().eval(mi.BSDFContext(), si, wo, active)
    g = dr.select(ds.delta, 1.0, dr.abs(dr.dot(ds.n, ds.d)) / dr.select(active, ds.dist * ds.dist, 1.0))
    f = weight * ds.pdf * fs * dr.select(ds.delta, 1.0, g)  # = Le fs g
    nee = weight * sel_weight * fs  # = f / p_c
    inv_pc = sel_weight / dr.select(active, ds.pdf * dr.select(ds.delta, 1.0, g), 1.0)
    if guide is not None:  # p_c of the mixture
        factor = guide.density_factor(idx, u_light, ~ds.delta, sel_weight, active)
        nee, inv_pc = nee / factor, inv_pc / factor
    sampled = active & dr.isfinite(inv_pc) & dr.isfinite(mi.luminance(nee))
    active = sampled & (mi.luminance(f) > 0)
    if visibility:
        active &= ~scene.ray_test(si.spawn_ray_to(ds.p), active)
    y = dr.zeros(LightSample(), n)
    y.em, y.p, y.n, y.uv, y.delta = idx, ds.p, mi.Vector3f(ds.n), ds.uv, ds.delta
    f = dr.select(active, f, 0.0)
    out = (y, f, dr.select(active, mi.luminance(f), 0.0), dr.select(active, mi.luminance(nee), 0.0))
    if with_inv_pc:
        out = (*out, dr.select(sampled, inv_pc, 0.0))
    return (*out, u_light) if guide is not None else out


def fresh_reservoirs(ray, pi, si, valid: mi.Bool, y, w_sum: mi.Float, phat: mi.Float, candidates: int | mi.Float,
                     offset: mi.Point2f | None = None):
    """The reservoirs of streaming RIS over ``candidates`` (a count, or one per lane) at the
    first hits ``(pi, si)`` of camera rays ``ray``: the chosen sample ``y`` with
    ``W = w_sum / (M p̂(y))`` (Wang et al. 2023, Alg. 1), and the shading point stored to be found and rebuilt
    (``offset``: its position in the pixel)."""
    m0 = dr.select(valid, mi.Float(candidates), 0.0)
    r = dr.zeros(Reservoirs(), dr.width(valid))
    r.y, r.w_sum, r.M = y, w_sum, m0
    r.W = dr.select(phat > 0, w_sum / (m0 * dr.select(phat > 0, phat, 1.0)), 0.0)  # W := 0 where p̂ = 0
    r.shape, r.prim, r.prim_uv = pi.shape_index, pi.prim_index, pi.prim_uv
    r.o, r.d, r.t = ray.o, ray.d, pi.t
    if offset is not None:
        r.offset = offset
    r.p, r.n, r.valid = si.p, mi.Vector3f(si.sh_frame.n), valid
    return r
