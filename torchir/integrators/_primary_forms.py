"""Derivative images of the camera-ray term in two primary-vertex forms (Wang et al. 2023, §6).

A pixel is ``I_p = ∫_P L(s) ds`` over its unit square ``P`` (box filter, pixel units). For a
parameter ``θ`` that moves geometry, ``dI_p/dθ`` has two estimators of the camera-ray term:

* **attached** (Mitsuba's, torchir's): the camera ray through ``s`` stays fixed and its hit point
  slides over the moving surface, ``dI_p = ∫_P ∂θ L(s) ds``;
* **material** (PSDR, Zhang et al. 2020; the paper's): the surface point ``u`` stays fixed in the
  surface's own coordinates and its image position ``s(u, θ)`` moves,
  ``dI_p = ∫_P (∂θ L|u + L ∂θ J / J) ds - ∮_∂P L (v · n) dℓ``, with ``J = |det ∂s/∂u|``,
  ``v = ∂θ s(u, θ)`` and ``n`` the outward normal of the pixel's edge.

The material form's pixel-boundary term carries the flux of ``L`` through opposite edges of the
pixel: large, and nearly cancelling wherever ``L`` is smooth. Pixel-level antithetic sampling
(Yu et al. 2022) draws each point with its reflection about the pixel centre and the same
random numbers, so the two fluxes cancel in each sample; with ReSTIR the reflected points must
also combine with the same neighbouring reservoirs (Wang et al. 2023, §6, Eqs. 28-29), else reuse
decorrelates them. The attached form has no such term, hence nothing to cancel.

The forms agree in expectation wherever a pixel holds no visibility boundary; silhouettes and
shadow edges are separate terms (``direct_projective``, :mod:`._shadow_edges`), not estimated
here. Light samples come from the ReSTIR integrator's own RIS and combination; ``W`` and the
chosen sample are constants, as in its backward pass; ``θ`` is differentiated in
forward mode.
"""
from __future__ import annotations

import gc
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from ._film import develop
from ._light import FORWARD_FLAGS, eval_target, fresh_reservoirs
from ._restir_pass import combine, normal_test, streaming_ris

__all__ = ["FORMS", "derivative_image", "pinhole", "screen_projection"]

FORMS = ("attached", "material")
_EDGE_PDF = 0.25  # an edge of the four, then a uniform point on it (length 1 pixel)
_collected_for: mi.Scene | None = None  # the scene of the last call, held (see derivative_image)


def pinhole(sensor: mi.Sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(to_local, a, b)`` of a pinhole ``perspective`` sensor: its world-to-camera matrix (4, 4)
    and the film position ``s = a * (q.xy / q.z) + b`` (pixels, x right, y down, as Mitsuba's
    films) of a point ``q`` in camera coordinates; ``a`` and ``b`` are read off two of the
    sensor's own rays, so its conventions (fov axis, aspect) carry over."""
    w, h = (int(v) for v in sensor.film().crop_size())
    to_local = np.array(sensor.world_transform().inverse().matrix, dtype=np.float64).reshape(4, 4)
    ratios, films = [], []
    for f in (0.25, 0.75):
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.ScalarPoint2f(f, f), mi.ScalarPoint2f(0.5, 0.5))
        d = to_local[:3, :3] @ np.array([ray.d.x, ray.d.y, ray.d.z], dtype=np.float64).ravel()
        ratios.append(d[:2] / d[2])
        films.append(np.array([f * w, f * h]))
    a = (films[1] - films[0]) / (ratios[1] - ratios[0])
    b = films[0] - a * ratios[0]
    return to_local, a, b


def screen_projection(sensor: mi.Sensor):
    """``project(p) -> (s, J)`` for a pinhole ``perspective`` sensor: ``s`` the film position of
    world points ``p`` in pixels (:func:`pinhole`), and a function ``J(p, dp_du, dp_dv)``,
    ``|det ∂s/∂(u, v)|`` of a surface parameterised by ``(u, v)``."""
    to_local, a, b = pinhole(sensor)
    rot = mi.Matrix3f(*(float(v) for v in to_local[:3, :3].ravel()))
    shift = mi.Vector3f(*(float(v) for v in to_local[:3, 3]))
    ax, ay, bx, by = (float(v) for v in (a[0], a[1], b[0], b[1]))

    def camera(p):
        return rot @ mi.Vector3f(p) + shift

    def project(p) -> mi.Point2f:
        q = camera(p)
        return mi.Point2f(ax * q.x / q.z + bx, ay * q.y / q.z + by)

    def jacobian(p, dp_du, dp_dv) -> mi.Float:
        q, e1, e2 = camera(p), rot @ mi.Vector3f(dp_du), rot @ mi.Vector3f(dp_dv)
        c1 = mi.Vector2f(e1.x * q.z - q.x * e1.z, e1.y * q.z - q.y * e1.z)
        c2 = mi.Vector2f(e2.x * q.z - q.x * e2.z, e2.y * q.z - q.y * e2.z)
        qz2 = q.z * q.z
        return dr.abs(ax * ay * (c1.x * c2.y - c2.x * c1.y)) / (qz2 * qz2)

    return project, jacobian


def derivative_image(
    integrator,
    scene: mi.Scene,
    key: str,
    velocity,
    sensor: int = 0,
    seed: int = 0,
    spp: int = 1,
    form: str = "attached",
    antithetic: bool = False,
    shared: bool = True,
    prev=None,
    radius: float | None = None,
) -> mi.TensorXf:
    """``dI/dθ`` (H, W, 3) of the camera-ray term, ``spp`` samples per pixel, in ``form``, for
    the displacement ``vertex_positions + θ velocity`` of the mesh parameter ``key`` (a
    ``*.vertex_positions``) at ``θ = 0``; ``velocity`` is one (3,) vector (a translation) or
    one per vertex (V, 3).

    ``integrator`` (a ``ReSTIRDirectIntegrator``) supplies RIS (its ``candidates``) and, with
    ``prev`` (reservoirs of an earlier step), the combination with its ``neighbors`` nearest
    of them within ``radius`` (default: the sensor state's). ``antithetic`` (material form):
    each interior and pixel-edge point comes with its reflection about the pixel centre and the
    same random numbers; ``shared``: the pair combines with the neighbours found for one of
    them, drawn at random (paper Eq. 29), else each with its own. The scene's vertices are
    bound to ``θ`` during the call and restored after it (the same Dr.Jit variable, so the
    integrator does not see the geometry move)."""
    if form not in FORMS:
        raise ValueError(f"form must be one of {FORMS}, got {form!r}")
    if antithetic and form != "material":
        raise ValueError("antithetic sampling applies to the material form (the attached one has no pixel-boundary term)")
    sensor_obj = scene.sensors()[sensor]
    if not str(sensor_obj).startswith("PerspectiveCamera"):
        raise ValueError("derivative_image needs a pinhole perspective sensor")
    params = mi.traverse(scene)
    if key not in params or not key.endswith("vertex_positions"):
        raise KeyError(f"{key!r} is not a mesh's vertex_positions in this scene")
    # a new handle on the same Dr.Jit variable: SceneParameters assigns in place, so the handle
    # params[key] returns would itself become the bound value
    old = dr.detach(params[key])
    count = dr.width(old) // 3
    v = np.asarray(velocity, dtype=np.float32)
    if v.shape == (3,):
        v = np.tile(v, (count, 1))
    if v.shape != (count, 3) or not np.isfinite(v).all():
        raise ValueError(f"velocity must be finite, of shape (3,) or ({count}, 3), got {np.shape(velocity)}")
    # scenes that died but wait for the cyclic collector still sit in Dr.Jit's registry, and the
    # forward traversal through virtual calls reaches their differentiable members: measured after
    # another test module's scenes, an abort in the collector or an isolate_grad error. Collected
    # on the first call for each scene (not every call: it would add to the timed steps). The
    # scene itself is held, not its address: a new scene at a freed one's address skipped it
    global _collected_for
    if _collected_for is not scene:
        gc.collect()
        _collected_for = scene
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    params[key] = dr.detach(old) + mi.Float(v.ravel()) * dr.gather(mi.Float, theta, dr.zeros(mi.UInt32, 3 * count))
    params.update()
    try:
        return _derivative_image(integrator, scene, theta, sensor, sensor_obj, seed, spp, form, antithetic, shared, prev, radius)
    finally:
        params[key] = old
        params.update()


def _derivative_image(integrator, scene, theta, sensor, sensor_obj, seed, spp, form, antithetic, shared, prev, radius):
    w, h = (int(v) for v in sensor_obj.film().crop_size())
    n = w * h * spp
    if radius is None:
        radius = integrator.state(scene, sensor).radius
    project, jacobian = screen_projection(sensor_obj)
    with dr.suspend_grad():
        pixel = dr.arange(mi.UInt32, n) // spp
        corner = mi.Point2f(mi.Float(pixel % w), mi.Float(pixel // w))
        positions = mi.load_dict({"type": "independent"})
        positions.seed(dr.opaque(mi.UInt32, seed), n)  # opaque: one kernel for every seed
        offset, edge_u = positions.next_2d(), positions.next_2d()
    light_seeds = [int(mi.sample_tea_32(seed, i)[0]) for i in (1, 2)]
    members = 2 if antithetic else 1
    total = dr.zeros(mi.Color3f, n)
    with dr.suspend_grad():
        interior = [corner + (offset if t == 0 else 1.0 - offset) for t in range(members)]
    for m in _shade(integrator, scene, sensor_obj, interior, light_seeds[0], seed, prev, radius, shared):
        if form == "attached":
            total += m.contribution(m.point(attached=True))
        else:
            si = m.point(attached=False)
            j = jacobian(si.p, si.dp_du, si.dp_dv)
            total += m.contribution(si) * j / dr.detach(dr.select(j > 0, j, 1.0))
    if form == "material":
        with dr.suspend_grad():
            side = mi.UInt32(dr.minimum(edge_u.x * 4.0, 3.0))  # 0 left, 1 right, 2 top, 3 bottom
            edges = [(side, edge_u.y)]
            if antithetic:  # the point reflection: the opposite edge, the mirrored position
                edges.append((side ^ 1, 1.0 - edge_u.y))
            points, normals = [], []
            for k, t in edges:
                vertical = k < 2
                far = mi.Float(k & 1)
                points.append(corner + dr.select(vertical, mi.Vector2f(far, t), mi.Vector2f(t, far)))
                sign = 2.0 * far - 1.0
                normals.append(dr.select(vertical, mi.Vector2f(sign, 0.0), mi.Vector2f(0.0, sign)))
        for m, normal in zip(_shade(integrator, scene, sensor_obj, points, light_seeds[1], seed, prev, radius, shared), normals):
            si = m.point(attached=False)
            flux = dr.detach(m.contribution(si))
            total += -flux * dr.dot(project(si.p), normal) / _EDGE_PDF  # d/dθ: -L (v . n) / pdf
    total /= members
    dr.forward_from(theta)
    return develop(dr.grad(total), spp, h, w)


@dataclass
class _Member:
    """One member of an antithetic group: its camera ray and first hit, and the reservoir (the
    chosen light sample ``r.y`` and its weight ``r.W``) resampled there."""

    scene: mi.Scene
    ray: mi.Ray3f
    hit: mi.PreliminaryIntersection3f
    si: mi.SurfaceInteraction3f  # detached, for resampling
    sampler: mi.Sampler
    r: Any  # Reservoirs
    f: mi.Color3f
    phat: mi.Float

    def point(self, attached: bool) -> mi.SurfaceInteraction3f:
        """The differentiable shading point: sliding along the ray, or fixed on the surface."""
        flags = mi.RayFlags.All if attached else mi.RayFlags.All | mi.RayFlags.FollowShape
        with dr.resume_grad():
            return self.hit.compute_surface_interaction(self.ray, flags, self.r.valid)

    def contribution(self, si: mi.SurfaceInteraction3f) -> mi.Color3f:
        """``Le + f(y) W`` at ``si``, with the sample and ``W`` held constant."""
        with dr.resume_grad():
            f, _ = eval_target(self.scene, si, self.r.y, self.r.valid & (self.r.W > 0), visibility=False)
            return si.emitter(self.scene).eval(si, self.r.valid) + f * self.r.W


def _shade(integrator, scene, sensor_obj, screen_points, light_seed, pick_seed, prev, radius, shared,
           seen_from_above=(), candidates: int | None = None, unroll: bool | None = None) -> list[_Member]:
    """Resample a light sample at each member's shading point (screen positions in pixels).
    The members draw the same random numbers; with ``prev`` each combines with its own nearest
    reservoirs, or (``shared``) all with those found for one member drawn at random (Eq. 29).
    Members whose index is in ``seen_from_above`` are shaded as if seen along the shading normal
    (``si.wi = (0, 0, 1)``; for a silhouette's inside, see :mod:`._silhouettes`) where the camera
    sees the front of the face (a one-sided material's back, seen past an open border, stays black). ``candidates``:
    RIS candidates per point (default the integrator's); ``unroll``: see :func:`._restir_pass.streaming_ris`."""
    w, h = (int(v) for v in sensor_obj.film().crop_size())
    n = dr.width(screen_points[0].x)
    members = []
    with dr.suspend_grad():
        for s in screen_points:
            ray, _ = sensor_obj.sample_ray(0.0, 0.0, s * dr.rcp(mi.ScalarVector2f(w, h)), mi.Point2f(0.5))
            hit = scene.ray_intersect_preliminary(ray, coherent=True)
            si = hit.compute_surface_interaction(ray, FORWARD_FLAGS)
            if len(members) in seen_from_above:  # not a back face seen past an open border: it stays unlit
                si.wi = dr.select(dr.dot(si.n, ray.d) < 0, mi.Vector3f(0.0, 0.0, 1.0), si.wi)
            valid = si.is_valid()
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(dr.opaque(mi.UInt32, light_seed), n)  # the same numbers for every member
            m_count = integrator.candidates if candidates is None else candidates
            y, f, phat, w_sum, _ = streaming_ris(scene, si, sampler, valid, n, m_count, shadowed=integrator.shadowed,
                                                 unroll=unroll)
            r = fresh_reservoirs(ray, hit, si, valid, y, w_sum, phat, m_count)
            members.append(_Member(scene, ray, hit, si, sampler, r, f, phat))
        if prev is not None and integrator.reuse:
            k = integrator.neighbors
            found = [integrator._neighbour_search(prev.p, prev.valid, m.r.p, m.r.valid, k, radius) for m in members]
            if shared and len(members) > 1:
                pick = mi.sample_tea_32(dr.arange(mi.UInt32, n), dr.opaque(mi.UInt32, pick_seed))[0] % len(members)
                nbr, ok = found[0]
                for t in range(1, len(members)):
                    nbr = [dr.select(pick == t, a, b) for a, b in zip(found[t][0], nbr)]
                    ok = [dr.select(pick == t, a, b) for a, b in zip(found[t][1], ok)]
                found = [(nbr, ok)] * len(members)
            for m, (nbr, ok) in zip(members, found):
                ok = normal_test(prev, nbr, [o & m.r.valid for o in ok], m.r.n, integrator.normal_threshold)  # at each member's own point
                m.r, m.f, m.phat, _ = combine(scene, m.sampler, m.si, m.r, m.f, m.phat, prev, nbr, ok, integrator.m_cap,
                                              shadowed=integrator.shadowed)
    return members
