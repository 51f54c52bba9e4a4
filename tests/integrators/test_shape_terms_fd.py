"""Every term of a shape gradient, on every path that produces it, against central finite
differences of a render without gradients (Mitsuba's ``direct``, the same seed both sides).

One scene, four optical worlds. Two black planes through the pinhole (``x = 0`` and ``z = 0``),
seen edge-on and so invisible, cut space into four convex wedges: a segment between two points of
a wedge stays in it, so no light path and no camera ray crosses from one wedge to another, and
each wedge fills one quadrant of the image (16²: 8 x 8 pixels each). Each wedge holds one moving
mesh whose derivative is one term (``test_each_mesh_changes_only_its_own_quadrant`` pins the
isolation):

==================  ===========================================================================
term                the mesh, and why its derivative is that term
==================  ===========================================================================
primary silhouette  ``ball`` (top left): black, before an emitting panel, lighting and shadowing
                    nothing: only its outline moves the image. Alone.
shading band        ``sphere`` (top right): a coarse smooth UV sphere (8 x 6, as Blender writes
                    it) lit from its side; one outline vertex on the lit side moves sideways.
                    Mostly the band, not alone (measured with ``b2``: 3.45 +- 0.11 with the
                    band, 7.81 +- 0.16 without, finite differences 3.34 +- 0.21): Mitsuba,
                    which has no band term, fails (``test_mitsuba_misses_the_shading_band``).
interior            ``sheet`` (bottom left): a bumpy smooth sheet lit from the front, scored on
                    the pixels wholly on it whose neighbours are too (no silhouette there),
                    nothing shadowing it. Alone.
shadow edges        ``blocker`` (bottom right): a box outside the view, seen only through its
                    shadow on a wall. Alone.
==================  ===========================================================================

One render per step moves the four meshes (a parameter each) under one adjoint, the sum of the
quadrants' (the sign of the quadrant's finite-difference image, so the loss follows what moves
there; a ramp on the sphere), so that each path's kernels compile once for all four terms. The
reference moves them all at once too.

Terms x paths: ``test_term_agrees_with_finite_differences[path-term]`` for every cell but

* Mitsuba x shading band: not computed by Mitsuba (torchir warns); pinned as missing by
  ``test_mitsuba_misses_the_shading_band``.
* ``"auto"`` (``ReSTIRSampler(scene)`` given nothing) settles on one of the presets at its first
  render; ``restir`` runs with ``edge_temporal=True``: its shadow-edge chains are what ``"auto"``
  picks where the (edge, light) pairs outnumber the samples 4 to 1; its default here, guided
  edge samples, is ``b1``'s and ``b2``'s code (and ``persistent``'s, fresh each step).
* The material form of the interior (``_primary_forms.derivative_image``, not a render path):
  ``test_primary_forms.py::test_camera_ray_term_agrees_with_finite_differences``.

Other CI tests against finite differences: ``direct_projective``'s shadow edges on the blocker
alone (``test_shape_gradients.py``, two tests); ``silhouette_backward`` called directly
(``test_silhouettes.py``); ``b2`` and ``direct_projective`` on exported meshes, all terms
together (``test_mesh_gradients.py``, ``test_shading_bands.py``). The large versions of this
module's checks are ``test_term_agrees_with_finite_differences_large`` (slow).

Statistics: paths without state across steps (``b1``, ``b2``, ``forward_only``'s gradient,
Mitsuba's) run ``steps`` steps of one sampler, each step's error independent of the others (the
shadow-edge guide changes the sampling density, so each step is unbiased given the ones before);
``restir`` and ``persistent`` keep reservoirs (and ``restir`` edge samples) across steps, so they
run ``steps`` independent chains after a burn-in of 2 (it lowers the variance, not the mean), the
error from the chains' means. Bound: the Student-t quantile a correct estimate exceeds with
probability 1e-4 (``z_bound``), for the combined standard error of estimate and reference
(Welch's degrees of freedom); every check also asserts that the reference lies more than twice
that far from 0, so twice the derivative (a wrong measure) or its negative fails.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir
from torchir.bench.mesh_gradients import mean_and_se, welch_dof, z_bound
from torchir.functions import render
from torchir.samplers import ReSTIRSampler

# term -> the mesh whose derivative it is, and that mesh's quadrant of the image (top/bottom, left/right)
TERMS = {
    "primary_silhouette": ("ball", (0, 0)),
    "shading_band": ("sphere", (0, 1)),
    "interior": ("sheet", (1, 0)),
    "shadow_edges": ("blocker", (1, 1)),
}
BAND_VERTEX = (1.104, 0.0, 0.396)  # on the sphere's outline, on its lit side, lower right


@dataclass(frozen=True)
class RunPath:
    """A way to the gradient: a ReSTIR preset (with ``options``) or the scene's Mitsuba
    ``integrator``; ``chain_steps`` > 0: reservoirs (or edge samples) are kept across steps, so
    it runs independent chains of that many steps, and the error comes from the chains' means."""

    preset: str | None = None
    options: tuple[tuple[str, Any], ...] = ()
    integrator: str = "direct"
    chain_steps: int = 0


PATHS = {
    # with edge chains: what "auto" picks where the (edge, light) pairs outnumber the samples 4
    # to 1; restir's default here, guided edge samples, is b1's and b2's code
    "restir": RunPath("restir", (("burn_in", 2), ("edge_temporal", True)), chain_steps=2),
    "persistent": RunPath("persistent", (("burn_in", 2),), chain_steps=1),
    "b1": RunPath("b1"),
    "b2": RunPath("b2"),
    "forward_only": RunPath("forward_only", (("burn_in", 2),)),
    "direct_projective": RunPath(integrator="direct_projective"),
    "prb_projective": RunPath(integrator="prb_projective"),
}
MITSUBA = ("direct_projective", "prb_projective")


@dataclass(frozen=True)
class Size:
    """Image side, gradient steps per path (chains, for paths with state), samples per pixel of
    each gradient pass, and the reference's seeds and samples per pixel."""

    res: int
    steps: int
    spp: int
    ref_seeds: int
    ref_spp: int


CI = Size(res=16, steps=12, spp=64, ref_seeds=32, ref_spp=1024)
LARGE = Size(res=32, steps=32, spp=128, ref_seeds=64, ref_spp=2048)


# --------------------------------------------------------------------------------------- scene
def _diffuse(value) -> dict[str, Any]:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": value}}


def _light(center, target, side: float, radiance: float) -> dict[str, Any]:
    """A square area light of ``side`` at ``center`` facing ``target``."""
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f().look_at(origin=list(center), target=list(target), up=[0, 0, 1])
            .scale(side / 2), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}}


def _sheet(grid: int = 5) -> mi.Mesh:
    """A smooth bumpy height field (height along -y) over x, z in [-1.9, -0.02], facing the camera."""
    from torchir.scenes._common import triangle_mesh

    x, z = np.meshgrid(np.linspace(-1.9, -0.02, grid), np.linspace(-1.9, -0.02, grid))
    y = 1.0 + 0.12 * np.sin(2.6 * x + 0.3) * np.cos(2.1 * z) + 0.05 * np.sin(4.0 * z)
    i = np.arange(grid * grid).reshape(grid, grid)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return triangle_mesh("sheet", np.stack([x, y, z], -1).reshape(-1, 3), faces, _diffuse([0.7, 0.5, 0.4]), smooth=True)


def _ball(name: str, center, radius: float, rings: int, segments: int, bsdf: dict[str, Any], poles_along_y: bool = False) -> mi.Mesh:
    """A smooth latitude-longitude sphere; ``poles_along_y``: turned so that rings of vertices
    outline it as the camera sees it."""
    from torchir.scenes._common import sphere_grid, triangle_mesh

    d, faces = sphere_grid(rings, segments)
    if poles_along_y:  # (x, y, z) -> (x, -z, y): a rotation, the faces stay outward
        d = d[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    return triangle_mesh(name, np.asarray(center) + radius * d, faces, bsdf, smooth=True)


def four_wedges(integrator: dict[str, Any], res: int) -> dict[str, Any]:
    """The scene of the module docstring: camera at (0, -4, 0) looking along +y, z up."""
    from torchir.scenes._common import perspective, triangle_mesh, welded_box

    T = mi.ScalarTransform4f
    black = _diffuse(0.0)
    quad = lambda name, corners: triangle_mesh(name, np.array(corners, np.float32), np.array([[0, 1, 2], [0, 2, 3]]), black)  # noqa: E731
    return {
        "type": "scene", "integrator": integrator,
        "sensor": perspective([0, -4, 0], [0, 0, 0], [0, 0, 1], 40, res, res),
        # the planes x = 0 and z = 0 through the pinhole, from just in front of it
        "divider_x": quad("divider_x", [(0, -3.5, -20), (0, 20, -20), (0, 20, 20), (0, -3.5, 20)]),
        "divider_z": quad("divider_z", [(-20, -3.5, 0), (20, -3.5, 0), (20, 20, 0), (-20, 20, 0)]),
        # x < 0, z > 0: a black ball before an emitting panel
        "ball": _ball("ball", (-0.75, 0.0, 0.75), 0.35, 4, 8, black),
        "panel": {"type": "rectangle", "to_world": T().translate([-1.2, 1.5, 1.2]).rotate([1, 0, 0], 90).scale(1.19),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
        # x > 0, z > 0: a coarse smooth sphere (8 x 6, as Blender writes it) lit from its side
        "sphere": _ball("sphere", (0.75, 0.0, 0.75), 0.5, 6, 8, _diffuse(0.6), poles_along_y=True),
        "side_light": _light((2.2, -0.3, 0.75), (0.75, 0.0, 0.75), 0.3, 40.0),
        # x < 0, z < 0: a bumpy sheet lit from the front
        "sheet": _sheet(),
        "front_light": _light((-1.9, -1.4, -1.9), (-1.2, 1.0, -1.2), 0.5, 20.0),
        # x > 0, z < 0: a wall with the shadow of a box outside the view
        "wall": {"type": "rectangle", "to_world": T().translate([1.2, 1.5, -1.2]).rotate([1, 0, 0], 90).scale(1.19), "bsdf": _diffuse(0.5)},
        "blocker": welded_box("blocker", T().translate([1.65, -0.4, -0.84]).rotate([0, 0, 1], 25).scale([0.2, 0.15, 0.18]), _diffuse(0.2)),
        "shadow_light": _light((2.1, -2.0, -0.7), (1.0, 1.5, -1.0), 0.6, 100.0),
    }


class FourWedges:
    """The scene (one per integrator), each term's displacement, adjoint and reference, and the
    gradients of each path, computed once, on first use."""

    def __init__(self, size: Size) -> None:
        from torchir.bench.restir_antithetic import scored_pixels

        self.size = size
        res, half = size.res, size.res // 2
        self._scenes: dict[str, torchir.Scene] = {}
        base = self.scene("direct")
        self.keys = {term: f"{mesh}.vertex_positions" for term, (mesh, _) in TERMS.items()}
        self.v0 = {term: base.get(key) for term, key in self.keys.items()}
        along = lambda term, d: torch.tensor(d, dtype=torch.float32).repeat(self.v0[term].numel() // 3)  # noqa: E731
        positions = self.v0["shading_band"].reshape(-1, 3)
        vertex = torch.zeros_like(positions)
        vertex[int((positions - torch.tensor(BAND_VERTEX)).norm(dim=1).argmin()), 0] = 1.0  # that vertex, sideways
        self.direction = {"primary_silhouette": along("primary_silhouette", [1.0, 0.0, 0.5]), "shading_band": vertex.reshape(-1),
                          "interior": along("interior", [0.0, -1.0, 0.0]), "shadow_edges": along("shadow_edges", [0.0, 0.0, 1.0])}
        self.h = {"primary_silhouette": 0.01, "shading_band": 0.01, "interior": 0.01, "shadow_edges": 0.02}
        self.quadrant = {term: (slice(half * r, half * (r + 1)), slice(half * c, half * (c + 1))) for term, (_, (r, c)) in TERMS.items()}
        self.mask = {}
        for term, quadrant in self.quadrant.items():
            self.mask[term] = torch.zeros(res, res, dtype=torch.bool)
            self.mask[term][quadrant] = True
        self.mask["interior"] &= torch.from_numpy(scored_pixels(base.mi_scene, "sheet"))
        # each quadrant's adjoint: the sign of its finite-difference image (the loss follows
        # what moves there), but a ramp on the sphere, where one vertex moves its pixels too
        # little for the signs to rise above the noise
        pilot = torch.sign(self.difference(seed=size.ref_seeds + 1, spp=size.ref_spp))
        ramp = (torch.linspace(-1.0, 1.0, res) + 0.5).expand(3, res, res)
        self.adjoint = {term: (ramp if term == "shading_band" else pilot) * self.mask[term] for term in TERMS}
        self.total_adjoint = sum(self.adjoint.values())
        fd = np.array([[float((diff * self.adjoint[term]).sum()) / (2 * self.h[term]) for term in TERMS]
                       for diff in (self.difference(s, size.ref_spp) for s in range(size.ref_seeds))])
        self.reference = {term: (float(fd[:, k].mean()), float(fd[:, k].std(ddof=1) / math.sqrt(size.ref_seeds)))
                          for k, term in enumerate(TERMS)}
        self._runs: dict[str, np.ndarray] = {}

    def scene(self, integrator: str) -> torchir.Scene:
        """The scene rendered by ``integrator`` (``"direct"``: the reference's, and ReSTIR's)."""
        if integrator not in self._scenes:
            options = {"type": integrator} if integrator == "direct" else {"type": integrator, "guiding": "none"}
            if integrator == "prb_projective":
                options["max_depth"] = 2  # direct illumination, as the others
            self._scenes[integrator] = torchir.Scene.from_dict(four_wedges(options, self.size.res))
        return self._scenes[integrator]

    def difference(self, seed: int, spp: int) -> torch.Tensor:
        """``image(+h) - image(-h)``, every mesh moved by its own step, the same seed both sides."""
        def image(sign: float) -> torch.Tensor:
            moved = {self.keys[t]: self.v0[t] + sign * self.h[t] * self.direction[t] for t in TERMS}
            return render(self.scene("direct"), moved, spp=spp, seed=seed)
        return image(1.0) - image(-1.0)

    def gradients(self, name: str) -> np.ndarray:
        """``(chains, steps, terms)`` derivatives of ``sum(total_adjoint * image)`` along each
        term's direction through path ``name``: one image sample per pixel (the gradient does
        not read it: the loss is linear), ``size.spp`` for the gradient."""
        if name not in self._runs:
            path = PATHS[name]
            scene = self.scene(path.integrator)
            chains, steps = (self.size.steps, path.chain_steps) if path.chain_steps else (1, self.size.steps)
            out = np.zeros((chains, steps, len(TERMS)))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # Mitsuba's projective integrators: the band notice
                for c in range(chains):
                    sampler = None if path.preset is None else ReSTIRSampler(scene, preset=path.preset, seed=1 + c, **dict(path.options))
                    for i in range(steps):
                        t = torch.zeros(len(TERMS), requires_grad=True)
                        moved = {self.keys[term]: self.v0[term] + t[k] * self.direction[term] for k, term in enumerate(TERMS)}
                        image = render(scene, moved, spp=1, spp_grad=self.size.spp, seed=100 + 1000 * c + i, sampler=sampler)
                        (image * self.total_adjoint).sum().backward()
                        out[c, i] = t.grad.cpu().numpy()
            self._runs[name] = out
        return self._runs[name]

    def compare(self, name: str, term: str) -> dict[str, float]:
        """The path's estimate and the reference, with their standard errors, the bound and
        ``z = |estimate - reference| / combined standard error``."""
        g = self.gradients(name)[..., list(TERMS).index(term)][..., None]
        means, ses, dof = mean_and_se(g)
        mean, se = float(means[0]), float(ses[0])
        ref, ref_se = self.reference[term]
        combined = math.hypot(se, ref_se)
        return {"estimate": mean, "se": se, "reference": ref, "reference_se": ref_se, "combined_se": combined,
                "z": abs(mean - ref) / combined, "bound": z_bound(welch_dof(se, dof, ref_se, self.size.ref_seeds - 1))}


@pytest.fixture(scope="module")
def wedges() -> FourWedges:
    return FourWedges(CI)


@pytest.fixture(scope="module")
def large_wedges() -> FourWedges:
    return FourWedges(LARGE)


CASES = [(name, term) for name in PATHS for term in TERMS if not (name in MITSUBA and term == "shading_band")]


def _agrees(wedges: FourWedges, name: str, term: str) -> None:
    f = wedges.compare(name, term)
    assert abs(f["reference"]) > 2 * f["bound"] * f["combined_se"], f  # twice the derivative, or its negative, would fail
    assert f["z"] < f["bound"], (name, term, f)


@pytest.mark.parametrize("name, term", CASES)
def test_term_agrees_with_finite_differences(wedges, name, term):
    """The term's derivative through the path agrees with the finite differences, which lie
    more than twice the bound from 0."""
    _agrees(wedges, name, term)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
@pytest.mark.parametrize("name, term", CASES)
def test_term_agrees_with_finite_differences_large(large_wedges, name, term):
    """The same checks at 32², 32 steps (or chains) of 128 samples per pixel."""
    _agrees(large_wedges, name, term)


@pytest.mark.parametrize("name", MITSUBA)
def test_mitsuba_misses_the_shading_band(wedges, name):
    """Mitsuba's projective integrators have no shading-horizon term (torchir warns when it
    renders a smooth mesh through them): on the sphere's outline vertex their derivative lies
    beyond the bound. The vertex's derivative thus needs the band term, which ReSTIR adds."""
    f = wedges.compare(name, "shading_band")
    assert f["z"] > f["bound"], f


def test_each_mesh_changes_only_its_own_quadrant(wedges):
    """The isolation the module rests on: moving one mesh (the same seed both sides) leaves
    every pixel outside its quadrant bit for bit as it was and changes its quadrant; and no
    camera ray meets the blocker (it is seen only through its shadow)."""
    import drjit as dr

    scene, res = wedges.scene("direct"), wedges.size.res
    for term, quadrant in wedges.quadrant.items():
        images = [render(scene, {wedges.keys[term]: wedges.v0[term] + s * 5 * wedges.h[term] * wedges.direction[term]}, spp=16, seed=3)
                  for s in (1.0, -1.0)]
        change = (images[0] - images[1]).abs().sum(0)
        outside = torch.ones(res, res, dtype=torch.bool)
        outside[quadrant] = False
        assert float(change[outside].max()) == 0.0, term
        assert float(change[quadrant].max()) > 0.0, term
    n = 64 * res * res
    u = dr.arange(mi.Float, n)
    with dr.suspend_grad():
        film = mi.Point2f(u * 0.61803398875 - dr.floor(u * 0.61803398875), (u + 0.5) / n)  # a Kronecker set over the film
        ray, _ = scene.mi_scene.sensors()[0].sample_ray(0.0, 0.0, film, mi.Point2f(0.5))
        si = scene.mi_scene.ray_intersect(ray)
        blocker = next(s for s in scene.mi_scene.shapes() if s.id() == "blocker")
        hits = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == dr.reinterpret_array(mi.UInt32, mi.ShapePtr(blocker)))
    assert not bool(dr.any(hits))

