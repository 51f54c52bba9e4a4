"""Primary-silhouette derivatives of direct illumination (Wang et al. 2023, §5.1, Alg. 5): the
visibility-boundary term of the camera rays, sampled on the silhouette edges of the meshes being
differentiated, with the radiance on either side from the ReSTIR integrator's RIS, optionally
combined with an earlier step's reservoirs.

A pixel is ``I_q = ∫_q L(u) du`` (box filter, pixel units). Where a mesh's silhouette ``C``
crosses it, moving the silhouette outwards by ``δ`` covers ``δ dℓ`` more of the pixel with the
mesh, so

    dI_q/dθ ⊃ ∫_{C ∩ q} (L_in(u) - L_out(u)) (n_out · du/dθ) dℓ(u),

``L_in`` the radiance just inside the silhouette (on the mesh), ``L_out`` just outside (what lies
behind), ``n_out`` the curve's image-space normal pointing away from the mesh. A mesh edge is on
the silhouette when its faces lie on one side of the plane through it and the camera. An edge is
drawn by its projected length and a point ``xB`` uniformly along it in 3D, so in image length
``p(u) = P(edge) / |dπ(xB)/ds|``. ``u = π(xB)`` rides on the edge, so the derivative is
``∑ detach(adjoint_q (L_in - L_out) / p(u)) n_out · π(xB(θ))``.

The sides are shaded at two screen points ``SIDE_OFFSET`` pixels either side of ``u``. With
smooth normals a grazing view is below the shading horizon in a thin band along the silhouette,
black in the image. With ``grazing`` the inside is shaded as the camera sees it, and the band's
inner edge comes from its own term (:mod:`._shading_bands`); without, as if seen along its
shading normal (as ``direct_projective`` does), so that the two edges' terms add up to the
radiance inside that band minus ``L_out`` while the band moves with the silhouette (shading the
grazing view without the band's term underestimates the derivative, and so does the
along-the-normal shading where the vertex normals turn the band; measurements:
docs/shape-gradients.md, "Shading a silhouette's inside" and "Primary silhouettes"). A sample
counts only if the inside ray meets the mesh at ``xB`` (the edge is not hidden; within
``VISIBLE_TOLERANCE`` of the distance).

Light candidates are drawn in a symbolic loop, not unrolled as in the integrator's frozen step:
the loop was faster in every configuration measured (docs/shape-gradients.md, "Silhouette
candidates").
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ._primary_forms import _shade, screen_projection
from ._mesh_edges import CREASE_COSINE, EdgeTable, edges_of, endpoints, faces_side, seen_whole

__all__ = ["checked_sensor", "side_difference", "silhouette_backward", "supported"]

SIDE_OFFSET = 1e-3  # pixels between the silhouette and the two shaded points
VISIBLE_TOLERANCE = 1e-2  # the inside ray's hit must lie this close to xB, relative to its distance


def silhouette_backward(integrator, scene: mi.Scene, sensor_index: int, grad_in: mi.TensorXf, meshes: list,
                        samples: int, seed: int, prev=None, radius: float | None = None,
                        candidates: int | None = None, grazing: bool = False) -> None:
    """Accumulate into the meshes' grad-enabled vertex positions the primary-silhouette
    derivative of ``sum(grad_in * image)``, ``grad_in`` the image adjoint (H, W, 3) of sensor
    ``sensor_index`` (a pinhole ``perspective`` with a box filter): ``samples`` silhouette
    samples in all, split over ``meshes`` by projected silhouette length.

    ``integrator`` (a ``ReSTIRDirectIntegrator``) resamples the light at both sides with
    ``candidates`` (default its own); with ``prev`` (the reservoirs of an earlier step) each side then combines
    with its ``neighbors`` nearest of them within ``radius`` (default: the sensor state's).
    ``grazing``: shade the inside as the camera sees it (black where it is below the shading
    horizon), for use with the band's own term (:mod:`._shading_bands`); else as seen along the
    shading normal, which stands in for the band as long as the band moves with the silhouette."""
    if candidates is not None and candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    sensor = checked_sensor("silhouette_backward", scene, sensor_index, meshes, samples)
    if not scene.emitters():
        return  # a black image: nothing to move
    if prev is not None and radius is None:
        radius = integrator.state(scene, sensor_index).radius
    project, _ = screen_projection(sensor)
    camera = mi.Point3f(sensor.world_transform() @ mi.ScalarPoint3f(0.0))  # the pinhole
    tables = [edges_of(m) for m in meshes]
    with dr.suspend_grad():
        lengths = [np.asarray(_silhouette_lengths(m, t, camera, project), np.float64) for m, t in zip(meshes, tables)]
    total = sum(float(length.sum()) for length in lengths)
    if total <= 0:
        return
    for i, (mesh, table, length) in enumerate(zip(meshes, tables, lengths)):
        if length.sum() <= 0:
            continue
        n = max(1, round(samples * float(length.sum()) / total))
        _mesh_backward(integrator, scene, sensor, grad_in, mesh, table, length, n,
                       int(mi.sample_tea_32(seed, i)[0]), prev, radius, project, camera, candidates, grazing)


def supported(scene: mi.Scene, sensor: mi.Sensor, meshes: list) -> bool:
    """Whether :func:`silhouette_backward` covers the primary silhouettes of ``meshes``: triangle
    meshes that are not emitters, seen by a pinhole perspective sensor whose film has a box
    filter (a pixel is the mean over its square) and no crop window."""
    return seen_whole(sensor, meshes) and "BoxFilter" in str(sensor.film().rfilter())


def checked_sensor(caller: str, scene: mi.Scene, sensor_index: int, meshes: list, samples: int) -> mi.Sensor:
    """The sensor ``sensor_index`` of ``scene``, once ``samples`` and the scene are checked for a
    boundary estimator (``caller``) that needs what :func:`supported` says."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    sensor = scene.sensors()[sensor_index]
    if not supported(scene, sensor, meshes):
        raise ValueError(f"{caller} needs triangle meshes (not emitters) and a pinhole perspective sensor with a box "
                         f"filter and no crop window (see supported)")
    return sensor


def side_difference(integrator, scene: mi.Scene, sensor: mi.Sensor, u: mi.Point2f, toward: mi.Vector2f, mesh: mi.Mesh,
                    at: mi.Point3f, camera: mi.Point3f, light_seed: int, pick_seed: int, prev, radius, along_normal: bool,
                    candidates: int | None) -> tuple[mi.Bool, mi.Color3f]:
    """A boundary sample's two sides: the screen points ``SIDE_OFFSET`` pixels from ``u`` along
    ``±toward``, each shaded by ``integrator``'s RIS (see ``_primary_forms._shade``; the ``+``
    side as if seen along its shading normal with ``along_normal``). Returns whether the ``+``
    side's camera ray meets ``mesh`` at ``at`` (within ``VISIBLE_TOLERANCE`` of its distance from
    ``camera``: the boundary is not hidden) and the radiance difference ``L(+) - L(-)``, detached."""
    plus, minus = _shade(integrator, scene, sensor, [u + SIDE_OFFSET * toward, u - SIDE_OFFSET * toward], light_seed,
                         pick_seed, prev, radius, shared=False, seen_from_above=(0,) if along_normal else (),
                         candidates=candidates, unroll=False)
    target = dr.reinterpret_array(mi.UInt32, mi.ShapePtr(mesh))
    visible = (plus.si.is_valid() & (dr.reinterpret_array(mi.UInt32, plus.si.shape) == target)
               & (dr.norm(plus.si.p - at) < VISIBLE_TOLERANCE * dr.norm(at - camera)))
    return visible, dr.detach(plus.contribution(plus.si) - minus.contribution(minus.si))


def _silhouette_lengths(mesh, table: EdgeTable, camera: mi.Point3f, project) -> mi.Float:
    """Projected length (pixels) of each edge on the silhouette seen from ``camera``, else 0;
    also of each crease (``table.crease``: a flat-shaded or hard edge, where the shading jumps)
    whose faces meet at an angle, silhouette or not (where the camera does not see it, its samples
    are rejected: the inside ray must meet the mesh at the edge)."""
    a, b, c1, c2 = endpoints(mesh, table)
    _, silhouette = faces_side(dr.cross(b - a, a - camera), a, c1, c2)
    if table.crease is not None and table.crease.any():
        n1 = dr.normalize(dr.cross(b - a, c1 - a))
        bent = dr.abs(dr.dot(n1, dr.normalize(c2 - a))) > CREASE_COSINE
        silhouette |= bent & mi.Bool(table.crease)
    length = dr.norm(project(b) - project(a))
    return dr.select(silhouette & dr.isfinite(length), length, 0.0)


def _projected_tangent(project, a: mi.Point3f, b: mi.Point3f, xb: mi.Point3f) -> mi.Vector2f:
    """``dπ(lerp(a, b, s))/ds`` at ``xb`` (pixels per unit of s): a central difference over
    1e-3 of the edge (the projection along a line is a ratio of linear functions of s, so the
    error is of order 1e-6 relative)."""
    h = 1e-3
    return (project(xb + (b - a) * h) - project(xb - (b - a) * h)) / (2 * h)


def _mesh_backward(integrator, scene, sensor, grad_in, mesh, table: EdgeTable, lengths: np.ndarray, n: int,
                   seed: int, prev, radius, project, camera, candidates, grazing: bool) -> None:
    film_w, film_h = (int(v) for v in sensor.film().crop_size())
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed), n)
    with dr.suspend_grad():
        pick = mi.DiscreteDistribution(mi.Float(lengths.astype(np.float32)))
        edge, along = pick.sample_reuse(sampler.next_1d())
        a, b, c1, _ = endpoints(mesh, table, edge)
        xb = dr.lerp(a, b, along)
        u = project(xb)
        du_ds = _projected_tangent(project, a, b, xb)
        speed = dr.norm(du_ds)
        inv_pdf = speed * pick.sum() / pick.eval_pmf(edge)  # 1 / p(u) in image length
        tangent = du_ds / dr.select(speed > 0, speed, 1.0)
        n_in = mi.Vector2f(-tangent.y, tangent.x)
        n_in *= dr.sign(dr.dot(n_in, project(c1) - u))  # towards the mesh

        visible, radiance = side_difference(integrator, scene, sensor, u, n_in, mesh, xb, camera,
                                            int(mi.sample_tea_32(seed, 1)[0]), seed, prev, radius, not grazing, candidates)
        pixel = mi.Point2i(dr.floor(u))
        active = (visible & (speed > 0) & (pixel.x >= 0) & (pixel.y >= 0) & (pixel.x < film_w)
                  & (pixel.y < film_h))
        adjoint = dr.gather(mi.Color3f, grad_in.array, mi.UInt32(pixel.y * film_w + pixel.x), active)
        weight = dr.dot(adjoint, radiance) * inv_pdf / n
        weight = dr.select(active & dr.isfinite(weight), weight, 0.0)

    with dr.resume_grad():
        a_t, b_t, _, _ = endpoints(mesh, table, edge)
        u_t = project(dr.lerp(a_t, b_t, along))
        objective = dr.sum(weight * dr.dot(-n_in, u_t))
        if dr.grad_enabled(objective):
            dr.backward(objective)
