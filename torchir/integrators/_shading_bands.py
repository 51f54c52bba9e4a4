"""The shading-horizon term of smooth-shaded meshes: where the camera sees a surface point below
its interpolated shading normal's horizon, a one-sided BSDF returns nothing, so a smooth mesh is
black in a thin band inside its silhouettes. The band's inner edge is the curve

    G(u) = n_s(x) · (c - x) / (|n_s(x)| |c - x|) = 0,

``x`` the surface point seen at image position ``u``, ``n_s`` the interpolated vertex normal and
``c`` the pinhole. It lies inside the triangles, not on an edge, and moves when the vertex
normals turn, so neither Mitsuba's projective integrators nor the edge estimators sample it, and
a vertex beside the silhouette gets a biased derivative from both (measurements:
docs/shape-gradients.md, "Smooth-shaded meshes"). With a box filter (pixel units) its part of
the pixel derivative is

    dI_q/dθ ⊃ ∫_{G = 0, in q} (L_lit - L_band) (∂G/∂θ) / |∇G| dℓ,

``L_lit`` the radiance on the side where ``G > 0``, ``L_band`` on the other side (zero for a
diffuse BSDF). The curve is found along random image rows and columns: in a triangle,
homogeneous barycentrics are linear in the image position along a line, so the numerator of
``G`` is a quadratic whose roots are the crossings. A row ``y`` is drawn uniformly over the
triangles' clipped vertical extents (total ``Y``), a column likewise (``X``), each family half
of the time; a crossing's density per unit length of the curve is then
``(|G_x| / Y + |G_y| / X) / (2 |∇G|)`` (balance heuristic over the two families, so no crossing
at a grazing angle to its line blows up), and the estimate per crossing is
``(L_lit - L_band) ∂G/∂θ / ((|G_x| / Y + |G_y| / X) / 2)``. ``∂G/∂θ`` comes from ``G`` evaluated at
the fixed image position with the vertices and normals attached.

Triangles are candidates when the numerator changes sign along one of their edges; a closed
curve wholly inside one triangle (its normals turning away and back within it) is missed.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..welding import mesh_weld
from ._primary_forms import pinhole
# the same needs (box filter, pinhole, meshes seen whole) and the same two-sided shading
from ._silhouettes import checked_sensor, side_difference, supported

__all__ = ["band_backward", "band_objective", "smooth_shaded", "supported"]



def smooth_shaded(mesh: mi.Mesh) -> bool:
    """Whether ``mesh`` is shaded with interpolated vertex normals (so it may have a band)."""
    return isinstance(mesh, mi.Mesh) and mesh.has_vertex_normals() and not mesh_weld(mesh).flat


def band_backward(integrator, scene: mi.Scene, sensor_index: int, grad_in: mi.TensorXf, meshes: list,
                  samples: int, seed: int, candidates: int | None = None) -> None:
    """Accumulate into the meshes' grad-enabled vertex positions (and the normals computed from
    them) the shading-horizon derivative of ``sum(grad_in * image)``: :func:`band_objective`,
    back-propagated alone (Dr.Jit's default flags)."""
    objective = band_objective(integrator, scene, sensor_index, grad_in, meshes, samples, seed, candidates)
    with dr.resume_grad():
        if objective is not None and dr.grad_enabled(objective):
            dr.backward(objective)


def band_objective(integrator, scene: mi.Scene, sensor_index: int, grad_in: mi.TensorXf, meshes: list,
                   samples: int, seed: int, candidates: int | None = None) -> mi.Float | None:
    """A scalar, zero in value, whose derivative w.r.t. the meshes' grad-enabled vertex positions
    (and the normals computed from them) is the shading-horizon derivative of
    ``sum(grad_in * image)``, ``grad_in`` the image adjoint (H, W, 3) of sensor ``sensor_index``:
    ``samples`` image lines in all, split over the smooth-shaded ``meshes`` by their candidate
    triangles' extents (None where there is nothing to differentiate). The light on either side
    is resampled by ``integrator`` (a ``ReSTIRDirectIntegrator``) with ``candidates`` RIS
    candidates (default its own), without reuse. Back-propagate it together with the other terms
    that pass through the normals, in one ``dr.backward``: a first pass with default flags deletes
    the normals' edges to the vertices, and keeping them (``ClearVertices``) is what once
    corrupted a shared scene's buffers in the suite."""
    sensor = checked_sensor("band_objective", scene, sensor_index, meshes, samples)
    if not scene.emitters():
        return None
    camera = _Camera(sensor)
    found = [(m, _candidates(m, camera)) for m in meshes if smooth_shaded(m)]
    found = [(m, t) for m, t in found if t is not None]
    total = sum(float(t.extent_x.sum() + t.extent_y.sum()) for _, t in found)
    if total <= 0:
        return None
    objective = None
    for i, (mesh, tris) in enumerate(found):
        n = max(1, round(samples * float(tris.extent_x.sum() + tris.extent_y.sum()) / total))
        term = _mesh_objective(integrator, scene, sensor, grad_in, mesh, tris, camera, n, int(mi.sample_tea_32(seed, i)[0]),
                               candidates)
        with dr.resume_grad():
            objective = term if objective is None else objective + term
    return objective


class _Camera:
    """The pinhole as the band needs it: its position, and the world ray direction (unnormalised,
    linear in the image position ``s``) ``d(s) = origin_dir + s.x * dx + s.y * dy``."""

    def __init__(self, sensor: mi.Sensor) -> None:
        to_local, a, b = pinhole(sensor)
        to_world = np.linalg.inv(to_local)
        self.width, self.height = (int(v) for v in sensor.film().crop_size())
        self.position = to_world[:3, 3].copy()
        rot = to_world[:3, :3]
        self.dx = rot @ np.array([1.0 / a[0], 0.0, 0.0])
        self.dy = rot @ np.array([0.0, 1.0 / a[1], 0.0])
        self.origin_dir = rot @ np.array([-b[0] / a[0], -b[1] / a[1], 1.0])
        self.to_local, self.a, self.b = to_local, a, b

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image positions (N, 2) of world points ``p`` (N, 3), and whether each lies in front."""
        q = p @ self.to_local[:3, :3].T + self.to_local[:3, 3]
        z = np.where(q[:, 2] > 0, q[:, 2], 1.0)
        return self.a * q[:, :2] / z[:, None] + self.b, q[:, 2] > 0


class _Triangles:
    """Candidate triangles of one mesh: indices, clipped image extents (pixels) and their minima."""

    def __init__(self, index, x0, y0, extent_x, extent_y):
        self.index, self.x0, self.y0, self.extent_x, self.extent_y = index, x0, y0, extent_x, extent_y


def _candidates(mesh: mi.Mesh, camera: _Camera) -> _Triangles | None:
    """The triangles across which ``n_s · (c - x)`` changes sign along an edge, in front of the
    camera and overlapping the image, with their extents clipped to it; None if there are none."""
    p = np.asarray(dr.detach(mesh.vertex_positions_buffer()), np.float64).reshape(-1, 3)
    nrm = np.asarray(dr.detach(mesh.vertex_normals_buffer()), np.float64).reshape(-1, 3)
    faces = np.asarray(mesh.faces_buffer(), np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return None
    to_cam = camera.position - p  # (V, 3)
    crossing = np.zeros(len(faces), bool)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        vi, vj = faces[:, i], faces[:, j]
        m_ii = np.einsum("fk,fk->f", nrm[vi], to_cam[vi])
        m_jj = np.einsum("fk,fk->f", nrm[vj], to_cam[vj])
        s = np.einsum("fk,fk->f", nrm[vi], to_cam[vj]) + np.einsum("fk,fk->f", nrm[vj], to_cam[vi])
        # along the edge, (1-t)^2 m_ii + t (1-t) s + t^2 m_jj = m_ii + (s - 2 m_ii) t + (m_ii - s + m_jj) t^2
        qa, qb = m_ii - s + m_jj, s - 2 * m_ii
        change = np.sign(m_ii) != np.sign(m_jj)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(qa != 0, -qb / (2 * qa), -1.0)
        inside = (t > 0) & (t < 1)
        extremum = m_ii + qb * t + qa * t * t
        crossing |= change | (inside & (np.sign(extremum) != np.sign(m_ii)))
    idx = np.nonzero(crossing)[0]
    if len(idx) == 0:
        return None
    corners, front = camera.project(p[faces[idx]].reshape(-1, 3))
    corners = corners.reshape(-1, 3, 2)
    front = front.reshape(-1, 3).all(1)
    lo = np.clip(corners.min(1), 0.0, [camera.width, camera.height])
    hi = np.clip(corners.max(1), 0.0, [camera.width, camera.height])
    keep = front & (hi[:, 0] > lo[:, 0]) & (hi[:, 1] > lo[:, 1])
    if not keep.any():
        return None
    extent = (hi - lo)[keep]
    return _Triangles(idx[keep].astype(np.uint32), lo[keep, 0], lo[keep, 1], extent[:, 0], extent[:, 1])


def _vec(a: np.ndarray) -> mi.ScalarVector3f:
    return mi.ScalarVector3f(*(float(v) for v in a))


def _triangle(mesh: mi.Mesh, face: mi.UInt32):
    """Vertices and vertex normals (3 each) of the faces ``face``: differentiable where the
    mesh's buffers are."""
    corners = mesh.face_indices(face)
    return ([mesh.vertex_position(corners[k]) for k in range(3)], [mesh.vertex_normal(corners[k]) for k in range(3)])


def _band_function(v, nrm, camera_pos, d):
    """``(ñ, w̃, crosses)`` at ray direction ``d``: ``ñ = Σ b̃_i n_i``, ``w̃ = Σ b̃_i (c - v_i)``
    with homogeneous barycentrics ``b̃_i = (e_j × e_k) · d`` (``e = v - c``), so that
    ``G = ñ · w̃ / (|ñ| |w̃|)``; ``crosses`` the three ``e_j × e_k``."""
    e = [p - camera_pos for p in v]
    crosses = [dr.cross(e[1], e[2]), dr.cross(e[2], e[0]), dr.cross(e[0], e[1])]
    bt = [dr.dot(x, d) for x in crosses]
    n_t = bt[0] * nrm[0] + bt[1] * nrm[1] + bt[2] * nrm[2]
    w_t = -(bt[0] * e[0] + bt[1] * e[1] + bt[2] * e[2])
    return n_t, w_t, crosses, e


def _mesh_objective(integrator, scene, sensor, grad_in, mesh, tris: _Triangles, camera: _Camera, n: int, seed: int,
                    candidates) -> mi.Float:
    w, h = camera.width, camera.height
    big_y, big_x = float(tris.extent_y.sum()), float(tris.extent_x.sum())
    if big_x <= 0 or big_y <= 0:
        return mi.Float(0.0)
    c = _vec(camera.position)
    dx, dy, d_origin = _vec(camera.dx), _vec(camera.dy), _vec(camera.origin_dir)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed), n)
    with dr.suspend_grad():
        u_family, u_tri, u_line = sampler.next_1d(), sampler.next_1d(), sampler.next_1d()
        rows = u_family < 0.5  # a row (y fixed, x free), else a column
        by_y = mi.DiscreteDistribution(mi.Float(tris.extent_y.astype(np.float32)))
        by_x = mi.DiscreteDistribution(mi.Float(tris.extent_x.astype(np.float32)))
        pick = dr.select(rows, by_y.sample(u_tri), by_x.sample(u_tri))
        x0 = dr.gather(mi.Float, mi.Float(tris.x0.astype(np.float32)), pick)
        y0 = dr.gather(mi.Float, mi.Float(tris.y0.astype(np.float32)), pick)
        ex = dr.gather(mi.Float, mi.Float(tris.extent_x.astype(np.float32)), pick)
        ey = dr.gather(mi.Float, mi.Float(tris.extent_y.astype(np.float32)), pick)
        fixed = dr.select(rows, y0 + u_line * ey, x0 + u_line * ex)  # the line's fixed coordinate
        face = dr.gather(mi.UInt32, mi.UInt32(tris.index), pick)
        v, nrm = _triangle(mesh, face)
        # d(r) = base + r * along: r the free coordinate
        base = d_origin + dr.select(rows, fixed * dy, fixed * dx)
        along = dr.select(rows, mi.Vector3f(dx), mi.Vector3f(dy))
        n_a, w_a, crosses, e = _band_function(v, nrm, c, base)
        bt_b = [dr.dot(x, along) for x in crosses]
        n_b = bt_b[0] * nrm[0] + bt_b[1] * nrm[1] + bt_b[2] * nrm[2]
        w_b = -(bt_b[0] * e[0] + bt_b[1] * e[1] + bt_b[2] * e[2])
        qa, qb, qc = dr.dot(n_b, w_b), dr.dot(n_a, w_b) + dr.dot(n_b, w_a), dr.dot(n_a, w_a)
        disc = qb * qb - 4.0 * qa * qc
        root_q = -0.5 * (qb + dr.copysign(dr.safe_sqrt(disc), qb))
        scale = dr.maximum(dr.abs(qa), dr.maximum(dr.abs(qb), dr.abs(qc)))
        linear = dr.abs(qa) <= 1e-7 * scale
        roots = [dr.select(linear, -qc / qb, root_q / qa), dr.select(linear, dr.nan, qc / root_q)]
    objective = []
    for k, r in enumerate(roots):
        objective.append(_root_objective(integrator, scene, sensor, grad_in, mesh, face, v, nrm, rows, fixed, r, (disc >= 0) | linear,
                                     c, dx, dy, d_origin, big_x, big_y, n, w, h, int(mi.sample_tea_32(seed, 2 + k)[0]),
                                     candidates))
    with dr.resume_grad():
        return objective[0] + objective[1]


def _root_objective(integrator, scene, sensor, grad_in, mesh, face, v, nrm, rows, fixed, r, real, c, dx, dy, d_origin,
                   big_x, big_y, n, w, h, seed, candidates) -> mi.Float:
    """The attached objective of one root of each line's quadratic: its derivative is the
    root's share of the band term (zero where the root is complex, off the triangle or hidden)."""
    with dr.suspend_grad():
        s = mi.Point2f(dr.select(rows, r, fixed), dr.select(rows, fixed, r))
        d = d_origin + s.x * dx + s.y * dy
        n_t, w_t, crosses, e = _band_function(v, nrm, c, d)  # v, nrm: the faces' (detached) corners
        bt = [dr.dot(x, d) for x in crosses]
        total = bt[0] + bt[1] + bt[2]
        inside = (total != 0) & dr.all(mi.Vector3f(bt[0], bt[1], bt[2]) * dr.sign(total) >= 0)
        norm = dr.norm(n_t) * dr.norm(w_t)
        grads = []
        for dd in (dx, dy):  # ∂g̃/∂s_x, ∂g̃/∂s_y
            db = [dr.dot(x, dd) for x in crosses]
            dn = db[0] * nrm[0] + db[1] * nrm[1] + db[2] * nrm[2]
            dw = -(db[0] * e[0] + db[1] * e[1] + db[2] * e[2])
            grads.append((dr.dot(dn, w_t) + dr.dot(n_t, dw)) / norm)
        g = mi.Vector2f(grads[0], grads[1])
        density = 0.5 * (dr.abs(g.x) / big_y + dr.abs(g.y) / big_x)  # per unit length, times |∇G|
        toward_lit = g / dr.norm(g)
        in_image = (s.x >= 0) & (s.y >= 0) & (s.x < w) & (s.y < h)
        active = real & dr.isfinite(r) & inside & in_image & (norm > 0) & (density > 0)
        hit = (bt[0] * v[0] + bt[1] * v[1] + bt[2] * v[2]) / total
        visible, radiance = side_difference(integrator, scene, sensor, s, toward_lit, mesh, hit, mi.Point3f(c), seed, seed,
                                            None, None, False, candidates)
        pixel = mi.Point2i(dr.floor(s))
        active &= visible
        adjoint = dr.gather(mi.Color3f, grad_in.array, mi.UInt32(pixel.y * w + pixel.x), active)
        weight = dr.dot(adjoint, radiance) / (density * n)
        weight = dr.select(active & dr.isfinite(weight), weight, 0.0)
        d = mi.Vector3f(d)

    with dr.resume_grad():
        v_t, n_t = _triangle(mesh, face)
        n_att, w_att, _, _ = _band_function(v_t, n_t, c, d)
        value = dr.dot(n_att, w_att) / (dr.norm(n_att) * dr.norm(w_att))
        return dr.sum(weight * dr.select(active, value, 0.0))
