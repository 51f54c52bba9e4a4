"""Shadow-edge derivatives of direct illumination: the secondary visibility-boundary term,
sampled on the edges of the meshes being differentiated (Wang et al. 2023, Eq. 21; the
multi-directional boundary sampling of Zhang et al. 2020).

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
across steps, mostly by what the earlier steps' samples found on each pair (Wang et al. 2023, Eq. 27),
which lowers the derivative's spread (measurements: docs/shape-gradients.md, "Edge guiding").

The light point may be resampled: RIS over several points by area with the target ``|adjoint · F|``
(Wang et al. 2023, Eq. 24). Off by default: it lowered the variance little, at a large cost; the
edge and the point on it set the noise (measurements: docs/shape-gradients.md, "Shape parameters"
and "Light-point resampling").
So may the whole sample (pair, point on the edge, light point; ``edge_candidates``), with the same
target: it pays on a many-edged blocker (as the lumpy ``crown``), few of whose edges lie on the
outline seen from the light, not on a simple box (measurements: docs/shape-gradients.md,
"A many-edged blocker").

Only edges of the given meshes are sampled (the geometry that moves), and only area lights
(planar, as Mitsuba's rectangles and meshes are per triangle) are supported: the caller keeps
Mitsuba's own estimator for anything else (:func:`supported`). This agrees with finite
differences and Mitsuba's ``direct_projective`` with far less variance at equal time, since
``direct_projective`` samples the edges of every shape (measurements: docs/shape-gradients.md,
"Shadow edges on the moving meshes alone").
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


CHAIN_FLOOR = 0.01  # a chain's target floor, as a share of the last step's mean |g| / p


@dataclass
class EdgeChain:
    """Temporal reuse of one mesh's shadow-edge samples: per sample slot, the sample kept so far at
    primary-sample coordinates (``pair``, ``along`` its edge, ``light`` on the pair's light), its
    contribution weight ``weight`` (W), the mesh's vertex ``positions`` it was chosen on and the
    chain's ``confidence`` (M); ``samples`` and ``pairs`` the shape it was made for, ``scale`` the
    last step's mean |g| / p. ``EdgeChain()`` starts one."""

    pair: mi.UInt32 | None = None
    along: mi.Float | None = None
    light: mi.Point2f | None = None
    weight: mi.Float | None = None
    positions: mi.Float | None = None
    confidence: float = 0.0
    samples: int = 0
    pairs: int = 0
    scale: float = 0.0


GUIDE_MEMORY = 0.1  # weight of a step's estimate in a guide's running mean
GUIDE_DEFENSIVE = 0.25  # share of the (edge, light) choice that stays by length x light pmf


def shadow_edge_backward(
    scene: mi.Scene, sensor_index: int, grad_in: mi.TensorXf, meshes: list, samples: int, seed: int,
    guides: dict | None = None, candidates: int = 1, edge_candidates: int = 1, chains: dict | None = None,
    chain_cap: float = 32.0, moving_cap: float = 4.0,
) -> None:
    """Accumulate into the meshes' grad-enabled vertex positions the shadow-edge derivative of
    ``sum(grad_in * image)``: ``samples`` edge samples in all, split over ``meshes`` by edge
    length. ``grad_in`` is the image adjoint (H, W, 3) of sensor ``sensor_index``.

    ``guides`` (a dict kept by the caller across steps, or None): per mesh, a running estimate of
    each (edge, light) pair's share of ``sum |adjoint * contribution|`` (Wang et al. 2023, Eq. 27, with the
    light in the pair). The pair is then drawn from a mixture: ``1 - GUIDE_DEFENSIVE`` by the
    guide, the rest by edge length x the scene's light pmf, so every pair keeps a
    probability and the estimate stays unbiased; each step's samples update the guide.

    ``candidates``: light points per edge sample, one kept by RIS with the target
    ``|adjoint · F|`` (Wang et al. 2023, Eq. 24; 1: by area alone). ``edge_candidates``: whole edge samples
    (pair, point on the edge, light point) per sample kept, one kept by RIS with the same target
    (1: the pair's pmf alone).

    ``chains`` (a dict kept by the caller across steps, or None): temporal reuse of the whole
    edge samples (Wang et al. 2023, Alg. 6, with the edge sample itself in the reservoir rather than
    the light point alone). Each sample slot keeps its chain's sample, re-evaluates it under the
    step's adjoint and geometry and resamples it against the ``edge_candidates`` fresh ones,
    its confidence capped at ``chain_cap``, or at ``moving_cap`` for a step after the mesh moved (a
    kept sample's error then lasts fewer steps). Unbiased: the targets carry a small floor
    (``CHAIN_FLOOR``) so that constant MIS weights cover samples whose target was 0 at an
    earlier step. Needs ``candidates == 1``."""
    if candidates < 1 or edge_candidates < 1:
        raise ValueError(f"candidates and edge_candidates must be >= 1, got {candidates}, {edge_candidates}")
    if chains is not None and candidates != 1:
        raise ValueError(f"temporal edge reuse needs one light candidate per edge sample, got {candidates}")
    if chains is not None and not min(chain_cap, moving_cap) >= 1:
        raise ValueError(f"an edge chain's cap and moving cap must be >= 1, got {chain_cap}, {moving_cap}")
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
        chain = None if chains is None else chains.get(mesh.id()) or EdgeChain()
        found, chain = _mesh_backward(scene, sensor, grad_in, mesh, table, length, n, mi.sample_tea_32(seed, i)[0], _EPS * extent, guide,
                                      candidates, edge_candidates, chain, chain_cap, moving_cap)
        if chains is not None:
            chains[mesh.id()] = chain
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
                   eps: float, guide: np.ndarray | None, candidates: int = 1, edge_candidates: int = 1,
                   chain: EdgeChain | None = None, chain_cap: float = 32.0, moving_cap: float = 4.0) -> tuple[np.ndarray, EdgeChain | None]:
    """One mesh's samples (see :func:`shadow_edge_backward`); returns this step's estimate of
    ``sum |adjoint * contribution|`` per (edge, light) pair, for the guide, and the updated
    ``chain`` (None without one), its confidence capped at ``chain_cap``, or at ``moving_cap`` where
    the mesh moved since the chain's last step."""
    film_w, film_h = (int(v) for v in sensor.film().crop_size())
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    n_lights = len(scene.emitters())
    with dr.suspend_grad():
        light_pmf = np.array([float(scene.pdf_emitter(j)[0]) for j in range(n_lights)])
        pmf = _pair_pmf(lengths, light_pmf, guide)
        pair_pick = mi.DiscreteDistribution(mi.Float(pmf.astype(np.float32)))
        lengths_dr = mi.Float(lengths.astype(np.float32))
        prior = 0.0  # the chain's confidence M: its sample counts as M candidates
        if chain is not None:  # the target's floor: a share of the last step's sum |g|, spread by length x light pmf
            default_dr = mi.Float(_pair_pmf(lengths, light_pmf, None).astype(np.float32))
            floor = dr.opaque(mi.Float, CHAIN_FLOOR * chain.scale)  # opaque: one kernel for every step
            prior = chain.confidence if (chain.samples, chain.pairs) == (n, len(pmf)) else 0.0
            positions = mi.Float(mesh.vertex_positions_buffer())
            if prior > 0 and not bool(dr.all(chain.positions == positions)):
                prior = min(prior, moving_cap)  # the geometry moved: a short memory (as the interior term's)
        share = dr.opaque(mi.Float, 1.0 / (prior + edge_candidates))  # each fresh candidate's MIS weight
        chosen, total, scale = None, mi.Float(0.0), mi.Float(0.0)
        for _ in range(edge_candidates):
            # the (edge, light) pair by _pair_pmf, xB uniform along the edge
            pair, along = pair_pick.sample_reuse(sampler.next_1d())
            pdf = pair_pick.eval_pmf(pair) / pair_pick.sum()
            inv_pdf_edge = dr.gather(mi.Float, lengths_dr, pair // n_lights) / pdf

            # x0 on the pair's light: RIS over `candidates` points by area, target |adjoint * F|
            # (Wang et al. 2023, Eq. 24); the kept one's estimate is sign(F(y)) * mean(|F_k| / p_k)
            kept, w_sum = None, mi.Float(0.0)
            for _ in range(candidates):
                cand = _edge_sample(scene, sensor, grad_in, mesh, table, pair, along, sampler.next_2d(), n_lights, eps, (film_w, film_h))
                w = dr.abs(cand["weight"])
                w_sum += w
                kept = cand if kept is None else _pick(sampler.next_1d() * w_sum < w, cand, kept)
            estimate = dr.sign(kept["weight"]) * w_sum * inv_pdf_edge / candidates  # g(y) / p(y)
            # the whole edge sample by RIS over `edge_candidates` (and the chain's sample), the
            # same target: p̂ = |g|, plus with a chain the floor; a candidate's w = share p̂ / p
            ratio = dr.abs(estimate)
            scale += ratio
            if chain is not None:
                ratio += floor * dr.gather(mi.Float, default_dr, pair) / pdf
            kept["ratio"] = dr.select(ratio > 0, estimate / ratio, 0.0)  # g / p̂
            kept["phat"] = ratio * pdf
            w = share * ratio
            total += w
            chosen = kept if chosen is None else _pick(sampler.next_1d() * total < w, kept, chosen)
        if prior > 0:
            # the chain's sample, re-evaluated under this step's adjoint and geometry. Constant
            # MIS weights (M against one per fresh candidate) stay unbiased because every
            # target has the floor, so each step's sample can land anywhere the fresh ones can.
            # (The balance heuristic against the target on the chain's geometry was tried: with
            # rays in today's scene, the moved mesh hides most old silhouette points, so it
            # kept 1.6x of the variance cut where these weights keep 7x.)
            old = _edge_sample(scene, sensor, grad_in, mesh, table, chain.pair, chain.along, chain.light, n_lights, eps, (film_w, film_h))
            g_old = old["weight"] * old["length"]
            old["phat"] = dr.abs(g_old) + floor * dr.gather(mi.Float, default_dr, chain.pair)
            old["ratio"] = dr.select(old["phat"] > 0, g_old / old["phat"], 0.0)
            w = dr.opaque(mi.Float, prior) * share * old["phat"] * chain.weight
            total += w
            chosen = _pick(sampler.next_1d() * total < w, old, chosen)
        if chain is not None:
            # the chain's confidence starts at 0: the first step's target had no floor
            chain = EdgeChain(pair=chosen["pair"], along=chosen["along"], light=chosen["light"],
                              weight=dr.select(chosen["phat"] > 0, total / chosen["phat"], 0.0), positions=positions,
                              confidence=min(prior + edge_candidates, chain_cap) if chain.scale > 0 else 0.0,
                              samples=n, pairs=len(pmf), scale=float(dr.sum(scale)[0]) / (n * edge_candidates))
            dr.eval(chain.pair, chain.along, chain.light, chain.weight, chain.positions)  # else the next step's kernel holds this one's
        weight = chosen["ratio"] * total * (film_w * film_h / n)
        active = chosen["active"] & (weight != 0)
        weight = dr.select(active, weight, 0.0)
        pair, along = chosen["pair"], chosen["along"]
        edge = pair // n_lights
        # summed on the host in sample order: Dr.Jit's atomic adds sum in thread order, and a
        # guide that differs in its last bits moves samples that sit on a pmf step to another
        # pair, so runs with the same seeds drifted apart (a test's spread ratio 2.0 alone, 1.39
        # after other tests)
        found = np.bincount(np.asarray(pair, np.int64), weights=np.abs(np.asarray(weight, np.float64)), minlength=len(pmf))

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
    return found.reshape(len(table.a), n_lights), chain


def _edge_sample(scene, sensor, grad_in, mesh, table: EdgeTable, pair: mi.UInt32, along: mi.Float, light: mi.Point2f,
                 n_lights: int, eps: float, film: tuple[int, int]) -> dict:
    """The edge sample at primary-sample coordinates (``pair``, ``along`` the edge, ``light`` on
    the pair's light): :func:`_light_candidate`'s fields plus those coordinates and the edge's
    ``length``."""
    a, b, c1, c2 = endpoints(mesh, table, pair // n_lights)
    ends = _EdgePoint(xb=dr.lerp(a, b, along), tangent=dr.normalize(b - a), third1=c1, third2=c2)
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), pair % n_lights)
    out = _light_candidate(scene, sensor, grad_in, emitter, ends, light, eps, film)
    out["pair"], out["along"], out["light"], out["length"] = mi.UInt32(pair), mi.Float(along), mi.Point2f(light), dr.norm(b - a)
    return out


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
