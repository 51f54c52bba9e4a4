"""Shadow-edge derivatives of direct illumination: the secondary visibility-boundary term,
sampled on the edges of the meshes being differentiated (paper 004 R20; the multi-directional
boundary sampling of Zhang et al. 2020).

A pixel's direct light ``I_q = ∫ W_q(x1) ∫ Le f G(x0, x1) V(x0, x1) dA(x0) dA(x1)`` changes
through ``V`` when an occluder moves. For a receiver ``x1`` the lit part of a light is bounded by
the occluder's silhouette edges projected from ``x1``, so

    dI_q/dθ ⊃ ∫ W_q(x1) ∫_{C(x1)} Le f G · (n_∂ · dx0/dθ) dℓ(x0) dA(x1),

``n_∂`` the boundary's normal in the light pointing into the shadowed part, ``x0(θ)`` the light
point behind the edge point ``xB(θ)`` seen from ``x1``. Sampling ``xB`` on an edge (by length) and
``x0`` on a light (by area), and tracing on from ``xB`` away from ``x0`` to the receiver ``x1``,
changes the measure by (derived for this module; checked against finite differences)

    dA(x1) dℓ(x0) = |x1 - x0| |x1 - xB| / |xB - x0|² · sin α · |n_Π,t| / |n1 · ω| · dA(x0) dℓ(xB),

``ω`` the segment's direction, ``α`` its angle with the edge, ``n_Π`` the normal of the plane of
``x1`` and the edge and ``n_Π,t`` its part in the light's plane. The ``|n1 · ω|`` cancels the
receiver's cosine in ``G``.

The (edge, light) pair is drawn by edge length x the scene's light pmf, or, given a guide kept
across steps, mostly by what the earlier steps' samples found on each pair (paper 004 R22):
2.5x lower sd for the blocker below at 64².

The light point may be resampled: RIS over several points by area with the target ``|adjoint · F|``
(paper 004 R21). Off by default: on ``occluded_lights`` even 64 candidates lowered the variance only
1.4x at 64² (none at 128²), at 3-95x the cost; the edge and the point on it set the noise.
So may the whole sample (pair, point on the edge, light point; ``edge_candidates``), with the same
target. At a fixed adjoint, perfect importance sampling of ``|adjoint · F|`` would leave 1/6 of
the guided variance on the box blocker and 1/93 or less on the lumpy ``crown`` (3312 edges; 93x
and 270x in two runs); 16 candidates took the crown's edge variance down 33x for 12x the edge
time, the box's 2.9x (64²).

Only edges of the given meshes are sampled (the geometry that moves), and only area lights
(planar, as Mitsuba's rectangles and meshes are per triangle) are supported: the caller keeps
Mitsuba's own estimator for anything else (:func:`supported`). On ``occluded_lights`` (32², the
blocker's rotation) this gave the same derivative as finite differences and Mitsuba's
``direct_projective`` with about 1/100 of the latter's variance at equal time, since
``direct_projective`` samples the edges of every shape.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ._mesh_edges import EdgeTable, edges_of, endpoints, faces_side, seen_whole

__all__ = ["supported", "shadow_edge_backward"]

_EPS = 1e-4  # offset of the traced rays off the edge, relative to the scene's extent


def supported(scene: mi.Scene, sensor: mi.Sensor, meshes: list) -> bool:
    """Whether this estimator covers the scene's shadow edges for ``meshes``: every emitter an
    area light on a shape that is not among ``meshes``, ``meshes`` triangle meshes, and a
    perspective sensor without a crop window."""
    emitters = scene.emitters()
    return seen_whole(sensor, meshes) and bool(emitters) and all(e.get_shape() is not None for e in emitters)


GUIDE_MEMORY = 0.1  # weight of a step's estimate in a guide's running mean
GUIDE_DEFENSIVE = 0.25  # share of the (edge, light) choice that stays by length x light pmf


def shadow_edge_backward(
    scene: mi.Scene, sensor_index: int, grad_in: mi.TensorXf, meshes: list, samples: int, seed: int,
    guides: dict | None = None, candidates: int = 1, edge_candidates: int = 1,
) -> None:
    """Accumulate into the meshes' grad-enabled vertex positions the shadow-edge derivative of
    ``sum(grad_in * image)``: ``samples`` edge samples in all, split over ``meshes`` by edge
    length. ``grad_in`` is the image adjoint (H, W, 3) of sensor ``sensor_index``.

    ``guides`` (a dict kept by the caller across steps, or None): per mesh, a running estimate of
    each (edge, light) pair's share of ``sum |adjoint * contribution|`` (paper 004 R22, with the
    light in the pair). The pair is then drawn from a mixture: ``1 - GUIDE_DEFENSIVE`` by the
    guide, the rest by edge length x the scene's light pmf, so every pair keeps a
    probability and the estimate stays unbiased; each step's samples update the guide.

    ``candidates``: light points per edge sample, one kept by RIS with the target
    ``|adjoint · F|`` (paper 004 R21; 1: by area alone). ``edge_candidates``: whole edge samples
    (pair, point on the edge, light point) per sample kept, one kept by RIS with the same target
    (1: the pair's pmf alone)."""
    if candidates < 1 or edge_candidates < 1:
        raise ValueError(f"candidates and edge_candidates must be >= 1, got {candidates}, {edge_candidates}")
    sensor = scene.sensors()[sensor_index]
    tables = [edges_of(m) for m in meshes]
    with dr.suspend_grad():
        lengths = [np.asarray(_edge_lengths(m, t), np.float64) for m, t in zip(meshes, tables)]
    total = sum(float(length.sum()) for length in lengths)
    if total <= 0 or samples < 1:
        return
    extent = float(dr.max(scene.bbox().extents()))
    for i, (mesh, table, length) in enumerate(zip(meshes, tables, lengths)):
        n = max(1, round(samples * float(length.sum()) / total))
        guide = None if guides is None else guides.get(mesh.id())
        if guide is not None and guide.shape != (len(table.a), len(scene.emitters())):
            guide = None  # another mesh or light set: start afresh
        found = _mesh_backward(scene, sensor, grad_in, mesh, table, length, n, mi.sample_tea_32(seed, i)[0], _EPS * extent, guide, candidates, edge_candidates)
        if guides is not None:
            guides[mesh.id()] = found if guide is None else (1 - GUIDE_MEMORY) * guide + GUIDE_MEMORY * found


def _edge_lengths(mesh, table: EdgeTable) -> mi.Float:
    return dr.norm(mesh.vertex_position(mi.UInt32(table.b)) - mesh.vertex_position(mi.UInt32(table.a)))


def _pair_pmf(lengths: np.ndarray, light_pmf: np.ndarray, guide: np.ndarray | None) -> np.ndarray:
    """Probabilities of the (edge, light) pairs, flattened edge-major: edge length x light pmf,
    mixed with the guide (see :func:`shadow_edge_backward`)."""
    default = np.outer(lengths, light_pmf)
    default /= default.sum()
    if guide is None or not np.isfinite(guide).all() or guide.sum() <= 0:
        return default.ravel()
    return ((1 - GUIDE_DEFENSIVE) * guide / guide.sum() + GUIDE_DEFENSIVE * default).ravel()


def _mesh_backward(scene, sensor, grad_in, mesh, table: EdgeTable, lengths: np.ndarray, n: int, seed: int,
                   eps: float, guide: np.ndarray | None, candidates: int = 1, edge_candidates: int = 1) -> np.ndarray:
    """One mesh's samples (see :func:`shadow_edge_backward`); returns this step's estimate of
    ``sum |adjoint * contribution|`` per (edge, light) pair, for the guide."""
    film_w, film_h = (int(v) for v in sensor.film().crop_size())
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    n_lights = len(scene.emitters())
    with dr.suspend_grad():
        light_pmf = np.array([float(scene.pdf_emitter(j)[0]) for j in range(n_lights)])
        pmf = _pair_pmf(lengths, light_pmf, guide)
        pair_pick = mi.DiscreteDistribution(mi.Float(pmf.astype(np.float32)))
        lengths_dr = mi.Float(lengths.astype(np.float32))
        chosen, total = None, mi.Float(0.0)
        for _ in range(edge_candidates):
            # the (edge, light) pair by _pair_pmf, xB uniform along the edge
            pair, along = pair_pick.sample_reuse(sampler.next_1d())
            edge, emitter_index = pair // n_lights, pair % n_lights
            inv_pdf_edge = dr.gather(mi.Float, lengths_dr, edge) * pair_pick.sum() / pair_pick.eval_pmf(pair)
            a, b, c1, c2 = endpoints(mesh, table, edge)
            ends = _EdgePoint(xb=dr.lerp(a, b, along), tangent=dr.normalize(b - a), third1=c1, third2=c2)
            emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), emitter_index)

            # x0 on the pair's light: RIS over `candidates` points by area, target |adjoint * F|
            # (paper 004 R21); the kept one's estimate is sign(F(y)) * mean(|F_k| / p_k)
            kept, w_sum = None, mi.Float(0.0)
            for _ in range(candidates):
                cand = _light_candidate(scene, sensor, grad_in, emitter, ends, sampler.next_2d(), eps, (film_w, film_h))
                w = dr.abs(cand["weight"])
                w_sum += w
                kept = cand if kept is None else _pick(sampler.next_1d() * w_sum < w, cand, kept)
            kept["estimate"] = dr.sign(kept["weight"]) * w_sum * inv_pdf_edge / candidates
            kept["pair"], kept["along"] = pair, along

            # the whole edge sample by RIS over `edge_candidates`, the same target
            w = dr.abs(kept["estimate"])
            total += w
            chosen = kept if chosen is None else _pick(sampler.next_1d() * total < w, kept, chosen)
        weight = dr.sign(chosen["estimate"]) * total * (film_w * film_h / (n * edge_candidates))
        active = chosen["active"] & (weight != 0)
        weight = dr.select(active, weight, 0.0)
        pair, along = chosen["pair"], chosen["along"]
        edge = pair // n_lights
        found = dr.zeros(mi.Float, len(pmf))
        dr.scatter_reduce(dr.ReduceOp.Add, found, dr.abs(weight), pair)

    # attached: xB rides on its edge, x1 on the camera ray (ray-following, as the interior
    # term), x0 is where the line x1 -> xB meets the light's plane
    with dr.resume_grad():
        a_t, b_t, _, _ = endpoints(mesh, table, edge)
        xb_t = dr.lerp(a_t, b_t, along)
        x0, x1, camera, n_light = chosen["x0"], chosen["x1"], chosen["camera"], chosen["n_light"]
        cam_dir = dr.normalize(x1 - camera)
        si_cam = scene.ray_intersect(mi.Ray3f(camera, cam_dir), mi.RayFlags.All, True, active)
        x1_t = dr.select(si_cam.is_valid(), si_cam.p, x1)
        through = xb_t - x1_t
        x0_t = x1_t + through * (dr.dot(n_light, x0 - x1_t) / dr.dot(n_light, through))
        objective = dr.sum(dr.select(active, weight * dr.dot(chosen["into_shadow"], x0_t), 0.0))
        if dr.grad_enabled(objective):
            dr.backward(objective)
    return np.asarray(found, np.float64).reshape(len(table.a), n_lights)


def _pick(take: mi.Bool, new: dict, old: dict) -> dict:
    """Field by field, ``new`` where ``take``, else ``old``."""
    return {k: dr.select(take, v, old[k]) for k, v in new.items()}


@dataclass
class _EdgePoint:
    """An edge sample ``xB`` with its edge's unit ``tangent`` and the third vertices of the
    edge's two faces."""

    xb: mi.Point3f
    tangent: mi.Vector3f
    third1: mi.Point3f
    third2: mi.Point3f


def _light_candidate(scene, sensor, grad_in, emitter, edge: _EdgePoint, sample: mi.Point2f, eps: float,
                     film: tuple[int, int]) -> dict:
    """One light point ``x0`` for the edge samples (by area on ``emitter``), traced through
    ``xB`` to the receiver ``x1`` and on to the camera. Returns its fields for the gradient and
    ``weight``: ``adjoint · F / p(x0)``, the signed contribution without the edge's pdf (0 where
    the path does not exist)."""
    film_w, film_h = film
    ps, _ = emitter.sample_position(0.0, sample)
    x0, n_light = ps.p, mi.Vector3f(ps.n)
    inv_pdf = dr.select(ps.pdf > 0, dr.rcp(ps.pdf), 0.0)
    xb = edge.xb

    to_edge = xb - x0
    dist_0b = dr.norm(to_edge)
    omega = to_edge / dist_0b
    plane = dr.cross(edge.tangent, omega)
    sin_alpha = dr.norm(plane)
    n_plane = plane / dr.select(sin_alpha > 0, sin_alpha, 1.0)
    side, silhouette = faces_side(n_plane, xb, edge.third1, edge.third2)  # the mesh lies on `side` of the plane
    active = silhouette & (sin_alpha > 1e-6) & (dr.dot(n_light, omega) > 0) & (ps.pdf > 0)

    # xB -> x0 must reach the light unoccluded, xB -> x1 finds the receiver
    origin = xb - side * n_plane * eps  # just off the mesh, on the open side
    si0 = scene.ray_intersect(mi.Ray3f(origin, -omega), active)
    active &= si0.is_valid() & (dr.abs(si0.t - dist_0b) < 1e-3 * dist_0b + 2.0 * eps)
    le = si0.emitter(scene).eval(si0, active)
    si1 = scene.ray_intersect(mi.Ray3f(origin, omega), active)
    active &= si1.is_valid() & dr.any(le > 0)

    # x1 -> the camera: pixel and importance
    it = dr.zeros(mi.Interaction3f)
    it.p = si1.p
    ds, sensor_weight = sensor.sample_direction(it, mi.Point2f(0.5), active)
    active &= (ds.pdf > 0) & ~scene.ray_test(si1.spawn_ray_to(ds.p), active)
    si1.wi = si1.to_local(-omega)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    f_cam = si1.bsdf().eval(ctx, si1, si1.to_local(ds.d), active)  # f * |cos| towards the camera

    # the measure change (module docstring) times the light's cosine and 1 / |x1 - x0|²
    x1 = si1.p
    dist_01, dist_b1 = dr.norm(x1 - x0), dr.norm(x1 - xb)
    n_plane_t = n_plane - dr.dot(n_plane, n_light) * n_light
    tangential = dr.norm(n_plane_t)
    geometry = (dr.abs(dr.dot(n_light, omega)) * dist_b1 / (dist_0b * dist_0b * dist_01)
                * sin_alpha * tangential)
    into_shadow = side * n_plane_t / dr.select(tangential > 0, tangential, 1.0)
    value = sensor_weight * f_cam * le * geometry * inv_pdf

    pixel = mi.Point2i(dr.floor(ds.uv))
    active &= (pixel.x >= 0) & (pixel.y >= 0) & (pixel.x < film_w) & (pixel.y < film_h) & (tangential > 0)
    adjoint = dr.gather(mi.Color3f, grad_in.array, mi.UInt32(pixel.y * film_w + pixel.x), active)
    active &= dr.isfinite(value.x + value.y + value.z)
    weight = dr.select(active, dr.dot(adjoint, value), 0.0)
    return {"weight": weight, "active": active, "x0": x0, "n_light": n_light, "x1": x1, "camera": ds.p,
            "into_shadow": into_shadow}
