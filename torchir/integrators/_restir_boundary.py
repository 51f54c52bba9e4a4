"""The visibility-boundary terms of shape gradients through ReSTIR direct illumination.

Where a mesh being optimised moves, the image changes along shadow edges, along its silhouettes
seen from the camera, and (for smooth shading) along the shading horizon; the interior term of
the resampled estimate does not see these. :class:`BoundaryTerms` (the base of
``ReSTIRDirectIntegrator``) adds them: shadow edges sampled on the moving meshes
(:mod:`._shadow_edges`), primary silhouettes (:mod:`._silhouettes`), shading-horizon bands
(:mod:`._shading_bands`), and whatever of them does not apply from Mitsuba's
``direct_projective`` (Zhang et al. 2023, "Projective sampling for differentiable rendering of
geometry"), run on welded faces where a mesh repeats vertex positions (:mod:`torchir.welding`).
"""
from __future__ import annotations

import warnings
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba.python.ad.integrators.common import RBIntegrator

from ..scene import is_geometry_key
from ..welding import WeldedFaces, moving_meshes
from . import _shading_bands, _shadow_edges, _silhouettes
from ._mesh_edges import edges_of, mitsuba_silhouettes_wrong

__all__ = ["BoundaryTerms", "EDGE_PAIRS_PER_SAMPLE", "differentiated_meshes"]

EDGE_PAIRS_PER_SAMPLE = 4.0  # above this many (edge, light) pairs per shadow-edge sample, "auto" chains by length (edge_strategy)


class BoundaryTerms(RBIntegrator):
    """The base of ``ReSTIRDirectIntegrator`` that adds the boundary terms (its options: the
    ``shadow_edge_*``, ``edge_*``, ``silhouette_*`` and ``shading_bands`` ones; its image chains'
    radius). A base class rather than a mixin: Mitsuba's integrators take one base."""

    def _init_boundary_terms(self) -> None:
        self._boundary_integrators: dict[tuple[bool, bool], mi.Integrator] = {}  # direct_projective, by (secondary, primary)
        self._band_warned = False  # warned once that the shading-horizon term cannot run (see _band_objective)
        self._scene_params: tuple[mi.Scene, Any] | None = None  # (scene, mi.traverse(scene)) of _traversed
        self._edge_guides: dict[str, np.ndarray] = {}  # per mesh, see _shadow_edges.shadow_edge_backward
        self._edge_chains: dict[int, dict[str, Any]] = {}  # per sensor and mesh, likewise

    def _reset_boundary_terms(self) -> None:
        self._edge_guides.clear()
        self._edge_chains.clear()

    def _boundary_backward(self, scene: mi.Scene, params: Any, grad_in: mi.TensorXf, sensor: int, seed: int, spp: int) -> None:
        """The visibility-boundary terms. Shadow edges of the differentiated meshes, where
        :func:`_shadow_edges.supported` (area lights, a perspective sensor), come from edge
        samples on those meshes alone (``spp`` per pixel, guided by the earlier steps' samples
        unless ``edge_guiding`` is off, and with ``edge_temporal`` and temporal reuse each
        sample resampled against the one it kept at the last step, the chain's confidence capped at
        ``edge_chain_cap``, or ``moving_geometry_m_cap`` after the mesh moved; ``"auto"``: see
        :meth:`edge_strategy`); with ``silhouette_sampling``, where
        :func:`_silhouettes.supported` (also a box filter), the primary silhouettes likewise
        (``silhouette_candidates`` RIS light candidates either side, no reuse), and with
        ``shading_bands`` the shading-horizon curves of smooth meshes (:mod:`._shading_bands`;
        the silhouettes' insides are then shaded as the camera sees them); the rest from
        ``direct_projective``. The guides and the edge chains are not saved in checkpoints:
        after a resume they start afresh (the chains' first step is without reuse)."""
        meshes = differentiated_meshes(scene, params)
        sensor_obj = scene.sensors()[sensor]
        edges = self.shadow_edge_sampling and _shadow_edges.supported(scene, sensor_obj, meshes)
        bands = self.uses_shading_bands(meshes) and _shading_bands.supported(scene, sensor_obj, meshes)  # see _band_objective
        silhouettes = (bands or self.uses_silhouette_sampling(meshes)) and _silhouettes.supported(scene, sensor_obj, meshes)
        if not (edges and silhouettes):
            # Mitsuba's edges come from vertex indices: on meshes that repeat positions (uv seams,
            # flat shading) its pass runs on welded faces (torchir.welding)
            with WeldedFaces(self._traversed(scene), moving_meshes(scene, params)):
                self.boundary_integrator(secondary=not edges, primary=not silhouettes).render_backward(
                    scene, params, grad_in, sensor, seed, spp)
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        if silhouettes:
            _silhouettes.silhouette_backward(self, scene, sensor, grad_in, meshes, spp * w * h, int(mi.sample_tea_32(seed, 11)[0]),
                                             candidates=self.silhouette_candidates, grazing=bands)
        if edges:
            reuse, guided = self.edge_strategy(scene, meshes, spp * w * h)
            guides = self._edge_guides if guided else None
            chains = self._edge_chains.setdefault(sensor, {}) if reuse else None  # per sensor: its own adjoint
            _shadow_edges.shadow_edge_backward(scene, sensor, grad_in, meshes, spp * w * h, int(mi.sample_tea_32(seed, 7)[0]), guides,
                                               self.edge_light_candidates, self.edge_candidates, chains, self.edge_chain_cap,
                                               self.moving_geometry_m_cap if self.moving_geometry_m_cap > 0 else self.edge_chain_cap)

    def _band_objective(self, scene: mi.Scene, params: Any, grad_in: mi.TensorXf, sensor: int, seed: int,
                        spp: int) -> mi.Float | None:
        """The shading-horizon term of the differentiated smooth meshes (``shading_bands``,
        where :func:`_shading_bands.supported`; ``spp`` image lines a pixel) as an objective that
        the interior term's backward pass carries: both reach the vertices through the normals
        computed from them, an edge of the graph that Dr.Jit's default flags delete after one
        pass (:func:`_shading_bands.band_objective`). None where it does not apply."""
        meshes = differentiated_meshes(scene, params)
        sensor_obj = scene.sensors()[sensor]
        if not self.uses_shading_bands(meshes):
            return None
        if not _shading_bands.supported(scene, sensor_obj, meshes):
            if not self._band_warned:
                self._band_warned = True
                warnings.warn("a moving smooth-shaded mesh: the shading-horizon term needs a pinhole camera with a box "
                              "filter ('rfilter': {'type': 'box'}) and no crop window; without it a vertex beside a "
                              "silhouette gets Mitsuba's biased derivative (see torchir.integrators._shading_bands)",
                              stacklevel=2)
            return None
        w, h = (int(v) for v in sensor_obj.film().crop_size())
        return _shading_bands.band_objective(self, scene, sensor, grad_in, meshes, spp * w * h,
                                             int(mi.sample_tea_32(seed, 13)[0]), candidates=self.silhouette_candidates)

    def uses_silhouette_sampling(self, meshes: list) -> bool:
        """Whether torchir samples the primary silhouettes of ``meshes`` itself (``silhouette_sampling``;
        ``"auto"``: where one is flat-shaded or has an open border, which Mitsuba's estimator gets
        wrong (:func:`mitsuba_silhouettes_wrong`); elsewhere Mitsuba's is right and cheaper)."""
        if self.silhouette_sampling == "auto":
            return any(mitsuba_silhouettes_wrong(m) for m in meshes)
        if not isinstance(self.silhouette_sampling, (bool, np.bool_)):
            raise ValueError(f"silhouette_sampling must be True, False or 'auto', got {self.silhouette_sampling!r}")
        return bool(self.silhouette_sampling)

    def uses_shading_bands(self, meshes: list) -> bool:
        """Whether the shading-horizon term of smooth meshes is added (``shading_bands``;
        ``"auto"``: where a moving mesh is shaded with interpolated vertex normals, whose band
        along the silhouettes moves as they turn: :mod:`._shading_bands`)."""
        if self.shading_bands == "auto":
            return any(_shading_bands.smooth_shaded(m) for m in meshes)
        if not isinstance(self.shading_bands, (bool, np.bool_)):
            raise ValueError(f"shading_bands must be True, False or 'auto', got {self.shading_bands!r}")
        return bool(self.shading_bands)

    def _traversed(self, scene: mi.Scene) -> Any:
        """``mi.traverse(scene)``, kept for the last scene (traversing costs a walk of the scene)."""
        if self._scene_params is None or self._scene_params[0] is not scene:
            self._scene_params = (scene, mi.traverse(scene))
        return self._scene_params[1]

    def edge_strategy(self, scene: mi.Scene, meshes: list, samples: int) -> tuple[bool, bool]:
        """(edge chains, guide) for a step's ``samples`` shadow-edge samples on ``meshes``.

        ``edge_temporal`` / ``edge_guiding`` set them; ``"auto"`` decides by how many (edge,
        light) pairs the step's samples must cover. With few (at most ``EDGE_PAIRS_PER_SAMPLE``
        per sample), the guide learns the pairs on the shadow's outline and fresh guided samples
        are best; with many, it cannot, and chains drawn by length, which keep the outline
        samples they find, are best (docs/restir-measurements.md, "Shadow-edge strategies").
        Chains also need temporal reuse and not ``forward_only``."""
        for name in ("edge_temporal", "edge_guiding"):
            value = getattr(self, name)
            if not (value == "auto" or isinstance(value, (bool, np.bool_))):
                raise ValueError(f"{name} must be True, False or 'auto', got {value!r}")
        pairs = sum(len(edges_of(m).a) for m in meshes) * len(scene.emitters())
        many = pairs > EDGE_PAIRS_PER_SAMPLE * samples
        chains = many if self.edge_temporal == "auto" else bool(self.edge_temporal)
        guided = (not many) if self.edge_guiding == "auto" else bool(self.edge_guiding)
        return chains and self.can_chain_edges(), guided

    def can_chain_edges(self) -> bool:
        """Whether shadow-edge samples may be kept across steps at all: with temporal reuse, not
        in ``forward_only`` mode (``edge_strategy`` then decides where they are)."""
        return self.temporal and not self.forward_only

    def boundary_integrator(self, secondary: bool = True, primary: bool = True) -> mi.Integrator:
        """Mitsuba's ``direct_projective`` restricted to its boundary terms (``sppc=0``; with
        ``secondary=False`` without the secondary ones, ``sppi=0``; with ``primary=False``
        without the primary ones, ``sppp=0``), without guiding: its octree guiding costs far more
        per step for the same error x time (docs/restir-measurements.md, "Shadow-edge strategies")."""
        if (secondary, primary) not in self._boundary_integrators:
            options = {"type": "direct_projective", "sppc": 0, "guiding": "none"}
            if not secondary:
                options["sppi"] = 0
            if not primary:
                options["sppp"] = 0
            self._boundary_integrators[secondary, primary] = mi.load_dict(options)
        return self._boundary_integrators[secondary, primary]


def differentiated_meshes(scene: mi.Scene, params: Any) -> list:
    """The meshes whose vertex positions ``params`` differentiates; empty when other geometry
    moves too (a transform, a sphere's centre or radius), whose shadow edges only Mitsuba's
    estimator covers."""
    moving = [name for name, value in (params or {}).items() if dr.grad_enabled(value)]
    if any(is_geometry_key(name) and not name.endswith(".vertex_positions") for name in moving):
        return []
    names = {name[: -len(".vertex_positions")] for name in moving if name.endswith(".vertex_positions")}
    return [shape for shape in scene.shapes() if shape.id() in names]
