"""Surface samples, Chamfer and Hausdorff distances against closed forms: concentric spheres
(Chamfer² about ``2 (r1 - r2)²``, bounded below exactly by the meshes' inradius), the sampling
floor of a mesh against itself (``2 S / (π n)`` for n area-uniform points on area S: the mean
squared distance to the nearest of n uniform points in the plane is ``S / (π n)``), a translated
convex mesh (Hausdorff = the translation's length), and area-uniform sampling by its moments."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.helpers import DEVICE, raised_message
from torchir.device_audit import device_audit
from torchir.geometry import chamfer_distance, hausdorff_distance, sample_surface
from torchir.geometry.metrics import _directed

N = 20000
FEW = 5000  # for meshes far apart: each k-d tree query then visits every sample within the gap (cost ~ samples²)


def area(v: torch.Tensor, f: torch.Tensor) -> float:
    p = v.double().cpu().numpy()[f.cpu().numpy()]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def inradius(v: torch.Tensor, f: torch.Tensor) -> float:
    """The smallest distance from the origin to a face's plane (a convex mesh about the origin
    contains the ball of that radius)."""
    p = v.double().cpu().numpy()[f.cpu().numpy()]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return float(np.min(np.abs(np.einsum("fk,fk->f", n / np.linalg.norm(n, axis=1, keepdims=True), p[:, 0]))))


def covering_radius(surface_area: float, n: int, failure: float = 1e-6) -> float:
    """A distance that none of 2n query points (both directions' samples) exceeds to the nearest
    of n uniform samples on area S but with probability ``failure``: a disc of radius r holds
    none of them with probability ``exp(-n π r² / S)``, so ``r = √(S ln(2n / failure) / (π n))``."""
    return math.sqrt(surface_area * math.log(2 * n / failure) / (math.pi * n))


def test_sampling_is_uniform_by_area_and_inside_each_triangle():
    """Two triangles of areas 1 and 3: the larger gets 3/4 of the points; inside a triangle the
    barycentric coordinates have the uniform density's moments (mean 1/3, second moment 1/6),
    each within 4 standard errors of the samples."""
    s = math.sqrt(2.0)
    v = torch.tensor([[0, 0, 0], [s, 0, 0], [0, s, 0], [0, 0, 1], [math.sqrt(6), 0, 1], [0, math.sqrt(6), 1]], device=DEVICE)
    f = torch.tensor([[0, 1, 2], [3, 4, 5]], device=DEVICE)
    p = sample_surface(v, f, N, torch.Generator(device=DEVICE).manual_seed(0))
    assert p.shape == (N, 3) and p.device == v.device and p.dtype == torch.float32
    big = (p[:, 2] == 1).double()
    assert bool(((p[:, 2] == 0) | (p[:, 2] == 1)).all())
    assert abs(float(big.mean()) - 0.75) < 4 * math.sqrt(0.75 * 0.25 / N)
    on_big = p[p[:, 2] == 1].double()
    b1, b2 = on_big[:, 0] / math.sqrt(6), on_big[:, 1] / math.sqrt(6)
    for b in (b1, b2, 1 - b1 - b2):
        assert bool((b >= -1e-6).all())
        for moment, expected in ((b, 1 / 3), (b * b, 1 / 6)):
            assert abs(float(moment.mean()) - expected) < 4 * float(moment.std()) / math.sqrt(len(moment))


def test_degenerate_triangles_are_never_sampled_and_a_mesh_without_area_is_refused():
    """A repeated corner and three collinear corners have no area: no point lands on them; all
    degenerate, or NaN positions: a clear ValueError."""
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2], [3, 3, 3], [4, 4, 4]], dtype=torch.float64, device=DEVICE)
    f = torch.tensor([[3, 3, 4], [0, 1, 2], [3, 4, 5], [5, 5, 5]], device=DEVICE)
    p = sample_surface(v, f, 5000, torch.Generator(device=DEVICE).manual_seed(1))
    assert p.dtype == torch.float64 and bool((p[:, 2] == 0).all())
    assert "has no area" in raised_message(ValueError, sample_surface, v, f[[0, 2, 3]], 10)
    bad = v.clone()
    bad[1, 0] = float("nan")
    assert "NaN/Inf" in raised_message(ValueError, sample_surface, bad, f, 10)
    assert "has no area" in raised_message(ValueError, chamfer_distance, (v, f[[0, 2]]), (v, f))


def test_same_generator_same_points_and_a_host_generator_serves_any_device(sphere):
    """Seeded draws repeat; a CPU generator serves vertices on any device; torch's own generator
    draws on the vertices' device (no factory without a device, no copy but the checks' scalars)."""
    v, f = sphere()
    with device_audit() as audit:
        on_device = sample_surface(v, f, 100)
    assert audit.factories() == [] and audit.transfers(min_elements=2) == [] and on_device.device == v.device, str(audit)
    a = sample_surface(v, f, 100, torch.Generator(device="cpu").manual_seed(5))
    b = sample_surface(v, f, 100, torch.Generator(device="cpu").manual_seed(5))
    assert a.device == v.device and bool((a == b).all())
    assert chamfer_distance((v, f), (v, f), samples=500, seed=2) == chamfer_distance((v, f), (v, f), samples=500, seed=2)


def test_concentric_spheres_give_twice_the_squared_gap(sphere):
    """Radii 1 and 0.6 (one mesh a scaled copy of the other): every sample of either is at least
    ``ρ·1 - 0.6`` from the other surface (ρ the inradius), so Chamfer² ≥ ``2 (ρ - 0.6)²``; above,
    ``2 (1 - 0.6)²`` plus the two sampling floors. The unsquared form likewise about ``2 · 0.4``."""
    a, b = sphere(1.0, 64, 32), sphere(0.6, 64, 32)
    rho = inradius(*a)
    floors = chamfer_distance(a, a, samples=FEW) + chamfer_distance(b, b, samples=FEW)
    c2 = chamfer_distance(a, b, samples=FEW)
    assert 2 * (rho - 0.6) ** 2 <= c2 <= 2 * 0.4**2 + floors
    c1 = chamfer_distance(a, b, samples=FEW, squared=False)
    assert 2 * (rho - 0.6) <= c1 <= 2 * 0.4 + floors / (rho - 0.6)


def test_a_mesh_against_itself_gives_the_sampling_floor(sphere):
    """Small and positive: ``2 S / (π n)`` within 4 standard errors (of the two means of
    squared distances, from the samples)."""
    v, f = sphere(1.0, 64, 32)
    floor = chamfer_distance((v, f), (v, f), samples=N)
    da, db = _directed((v, f), (v, f), N, 0)
    assert floor == pytest.approx(np.mean(da**2) + np.mean(db**2), rel=1e-12)
    se = math.sqrt(np.var(da**2) / N + np.var(db**2) / N)
    assert 0 < floor and abs(floor - 2 * area(v, f) / (math.pi * N)) < 4 * se


def test_hausdorff_of_a_translated_convex_mesh_is_the_translation(sphere):
    """For a convex body and its translate by t the Hausdorff distance is |t|; from samples,
    within about one covering radius of them."""
    v, f = sphere(0.5, 32, 16)
    t = torch.tensor([0.2, -0.1, 0.2], device=DEVICE)
    h = hausdorff_distance((v, f), (v + t, f), samples=FEW)
    assert abs(h - 0.3) < covering_radius(area(v, f), FEW)


def test_hausdorff_takes_the_larger_directed_distance(sphere):
    """A sphere against itself plus a triangle out at x = 2..2.3: from the sphere every sample is
    near the other mesh, from the triangle's far corner 1.8 (to the ball of radius 0.5; at most
    0.5 (1 - ρ) less to the mesh): the Hausdorff distance is the larger, not the smaller or a mean."""
    v, f = sphere(0.5, 32, 16)
    fin = torch.tensor([[2.0, 0, 0], [2.3, 0, 0], [2.0, 0.3, 0.3]], device=DEVICE)
    with_fin = (torch.cat([v, fin]), torch.cat([f, torch.tensor([[len(v), len(v) + 1, len(v) + 2]], device=DEVICE)]))
    h = hausdorff_distance((v, f), with_fin, samples=FEW)
    slack = covering_radius(area(*with_fin), FEW) + 0.5 * (1 - inradius(v, f) / 0.5)
    assert abs(h - 1.8) < slack
    assert hausdorff_distance((v, f), (v, f)) < covering_radius(area(v, f), N)


def test_chamfer_adds_both_directions(sphere):
    """A sphere against itself plus a triangle outside it: from the sphere's samples the mean is
    a sampling floor; from the other mesh's, the triangle's share of its area times the mean
    squared distance of the triangle to the sphere (between that to the ball of radius 0.5 and
    that to the ball of its inradius, by quadrature over the triangle): Chamfer² is the sum."""
    v, f = sphere(0.5, 32, 16)
    fin = torch.tensor([[1.0, 0, 0], [1.6, 0, 0], [1.0, 0.6, 0.6]], device=DEVICE)
    with_fin = (torch.cat([v, fin]), torch.cat([f, torch.tensor([[len(v), len(v) + 1, len(v) + 2]], device=DEVICE)]))
    share = area(fin, torch.tensor([[0, 1, 2]])) / area(*with_fin)
    a, b = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    inside = a + b <= 1
    corners = fin.double().cpu().numpy()
    radius = np.linalg.norm(corners[0] + a[inside, None] * (corners[1] - corners[0]) + b[inside, None] * (corners[2] - corners[0]), axis=1)
    low, high = np.mean((radius - 0.5) ** 2), np.mean((radius - inradius(v, f)) ** 2)
    floor = chamfer_distance((v, f), (v, f), samples=FEW)
    c2 = chamfer_distance((v, f), with_fin, samples=FEW)
    sigma = 4 * math.sqrt(share * (1 - share) / FEW) * high  # 4 s.e. of the triangle's share of the samples
    assert share * low - sigma <= c2 <= share * high + sigma + 2 * floor


def test_bad_mesh_arguments_are_refused(sphere):
    v, f = sphere()
    assert "(vertices, faces) pair" in raised_message(TypeError, chamfer_distance, v, (v, f))
    assert "samples must be a positive int" in raised_message(ValueError, hausdorff_distance, (v, f), (v, f), samples=0)
    assert "(V, 3) or flat (3V,)" in raised_message(ValueError, chamfer_distance, (v[:, :2], f), (v, f))


def test_chamfer_and_hausdorff_together_are_the_two_calls(sphere):
    """One draw and one query each way give both: the same floats as the two functions (the
    trainer logs both every distance row, and the separate calls cost twice)."""
    from torchir.geometry import chamfer_and_hausdorff

    v, f = sphere(0.5, 32, 16)
    moved = (v * 1.1 + torch.tensor([0.05, 0.0, -0.02], device=DEVICE), f)
    for seed in (0, 3):
        c, h = chamfer_and_hausdorff((v, f), moved, samples=FEW, seed=seed)
        assert c == chamfer_distance((v, f), moved, samples=FEW, seed=seed) and c > 0
        assert h == hausdorff_distance((v, f), moved, samples=FEW, seed=seed) and h > 0
