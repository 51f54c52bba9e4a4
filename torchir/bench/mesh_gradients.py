#!/usr/bin/env python
"""Shape derivatives on meshes as users bring them: uv seams, split vertices, open borders.

A mesh file (OBJ or PLY, as loaded by Mitsuba: one vertex per distinct corner, so seams and
flat shading repeat positions) hangs above a floor under one area light, seen by a pinhole camera
with a box filter. For the linear image loss ``sum(adjoint * image)`` (a fixed ramp down the
image) the bench estimates, per step at ``--spp`` samples, the derivatives with respect to

* ``translation``: all vertices moving up together, and
* ``vertex``: one vertex moving up, with every copy at its position (the welded vertex whose
  derivative is largest, so that the test can resolve it),

through Mitsuba's ``direct_projective`` and ``prb_projective`` (torchir's ``render``) and through
``render(..., sampler=ReSTIRSampler(scene, preset=P))`` for each preset. The reference is the
central finite difference of the same mesh with all copies of a vertex moved together (the
motion that keeps the surface closed), with Mitsuba's ``direct`` at ``--ref-spp`` samples, the
same seeds on both sides.

The table gives, per mesh and path, the mean over ``--steps`` steps, its z-score against the
reference (``|mean - ref| / sqrt(se² + se_ref²)``, the standard error from ``--chains``
independent runs' means: a run's steps are correlated through its reservoirs), the rms error of a
step and that rms error over ``direct_projective``'s (at equal samples per step).

Usage:
    python -m torchir.bench.mesh_gradients --quick            # the exported set, 16², 2 paths
    python -m torchir.bench.mesh_gradients --meshes duck.obj teddy.obj --chains 8 --steps 8

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/mesh_gradients.png``.
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torchir  # noqa: I001  (before torch)

import mitsuba as mi
import numpy as np
import torch

from torchir.bench import write_outputs
from torchir.bench.exported_meshes import write_all
from torchir.welding import mesh_weld

PATHS = ("direct_projective", "prb_projective", "restir", "persistent", "b1", "b2", "forward_only")
KEY = "mesh.vertex_positions"
UP = np.array([0.0, 0.0, 1.0])


def scene_dict(mesh: Any, integrator: dict[str, Any], resolution: int) -> dict[str, Any]:
    """Floor, ``mesh`` (a Mitsuba mesh object or a ``{"type": "obj"|"ply", ...}`` dict) fitted
    into a unit box 0.8 above it, one area light up and to the side, the camera in front."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40, "to_world": T().look_at(origin=[0, -3.2, 2.2], target=[0, 0, 0.2], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"}},
        "floor": {"type": "rectangle", "to_world": T().scale(2.0), "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
        "mesh": mesh,
        "light": {"type": "rectangle", "to_world": T().look_at(origin=[1.2, 0.6, 3.0], target=[0, 0, 0], up=[0, 0, 1]).scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 30.0}}},
    }


def mesh_spec(path: str | Path, face_normals: bool = False) -> dict[str, Any]:
    """Mitsuba's dict of the mesh at ``path`` (OBJ or PLY) as Mitsuba loads it, scaled into a
    unit box centred 0.8 above the floor, diffuse grey; with ``face_normals`` faceted (Mitsuba's
    loader option: the faces keep sharing their vertices, shaded with the faces' normals)."""
    path = Path(path)
    kind = {".obj": "obj", ".ply": "ply"}.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"{str(path)!r}: expected an .obj or .ply mesh")
    raw = mi.load_dict({"type": kind, "filename": str(path)})
    p = np.asarray(raw.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    scale = 1.0 / max(float((hi - lo).max()), 1e-12)
    to_world = mi.ScalarTransform4f().translate([0.0, 0.0, 0.8]).scale(scale).translate((-(lo + hi) / 2).tolist())
    return {"type": kind, "filename": str(path), "to_world": to_world, "face_normals": face_normals,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.4}}}


def welded_copy(mesh: mi.Mesh) -> mi.Mesh:
    """``mesh`` with one vertex per position (its faces through :func:`torchir.welding.weld_map`):
    smooth normals recomputed over the welded faces, or none (face normals) for a flat-shaded one."""
    weld = mesh_weld(mesh)
    keep, faces = np.unique(weld.rep, return_inverse=True)
    faces = faces.astype(np.uint32)[weld.faces]
    smooth = mesh.has_vertex_normals() and not weld.flat
    props = mi.Properties()
    props["bsdf"] = mesh.bsdf()
    out = mi.Mesh("mesh", len(keep), len(faces), props, has_vertex_normals=smooth)
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(np.asarray(mesh.vertex_positions_buffer(), np.float32).reshape(-1, 3)[keep].ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    if smooth:
        out.recompute_vertex_normals()
    return out


class Problem:
    """One mesh's gradient problem: the user's scene for each path, the welded reference, the
    adjoint and the displaced vertex (as a mask over the user's vertices and the welded ones)."""

    def __init__(self, path: str | Path, resolution: int, face_normals: bool = False, vertex: int | None = None) -> None:
        self.name = Path(path).name + (" (face_normals)" if face_normals else "")
        self.resolution = resolution
        self.spec = mesh_spec(path, face_normals)
        user_mesh = mi.load_dict(self.spec)
        weld = mesh_weld(user_mesh)
        self.repeats = weld.repeats
        self.keep = np.unique(weld.rep)
        ramp = torch.linspace(-1.0, 1.0, resolution, device=torchir.backend.device())
        self.adjoint = (ramp[None, :, None] + 0.5).expand(3, resolution, resolution).contiguous()
        self._scenes: dict[str, torchir.Scene] = {}
        # index into the welded mesh: given, or the one whose derivative is largest (a ReSTIR render)
        self.vertex = self._strongest_vertex() if vertex is None else vertex
        rep_of_welded = self.keep[self.vertex]
        self.user_vertex_mask = torch.from_numpy(weld.rep == rep_of_welded).to(torchir.backend.device())

    def scene(self, path: str) -> torchir.Scene:
        """The user's (unwelded) scene for ``path``: a Mitsuba integrator or a ReSTIR preset's."""
        integrator = path if path in ("direct_projective", "prb_projective") else "direct_projective"
        if integrator not in self._scenes:
            options = {"type": integrator, "guiding": "none"}
            if integrator == "prb_projective":
                options["max_depth"] = 2
            self._scenes[integrator] = torchir.Scene.from_dict(scene_dict(self.spec, options, self.resolution))
        return self._scenes[integrator]

    def welded_scene(self, integrator: dict[str, Any]) -> torchir.Scene:
        key = f"welded/{integrator['type']}"
        if key not in self._scenes:
            self._scenes[key] = torchir.Scene.from_dict(scene_dict(welded_copy(mi.load_dict(self.spec)), integrator, self.resolution))
        return self._scenes[key]

    def _strongest_vertex(self) -> int:
        from torchir.functions import render
        from torchir.samplers import ReSTIRSampler

        scene = self.welded_scene({"type": "direct_projective", "guiding": "none"})
        v0 = scene.get(KEY).requires_grad_(True)
        (render(scene, {KEY: v0}, spp=16, seed=7, sampler=ReSTIRSampler(scene, preset="b2")) * self.adjoint).sum().backward()
        return int(v0.grad.reshape(-1, 3)[:, 2].abs().argmax())

    def directions(self, vertex_mask: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
        up = torch.tensor(UP, dtype=torch.float32, device=vertex_mask.device)
        translation = up.repeat(count)
        vertex = (vertex_mask[:, None].float() * up).reshape(-1)
        return translation, vertex

    def reference(self, spp: int, seeds: int, h: float | None = None,
                  only: str | None = None) -> dict[str, tuple[float, float]]:
        """Central differences of the user's mesh with every copy of a vertex moved together (the
        welded motion; rendered as torchir renders it, so normals per group), Mitsuba's ``direct``
        at ``spp``, the same seed both sides: ``{direction: (mean, standard error)}`` (``only``: that direction alone). The step
        ``h`` defaults to 2 % of the median edge: on a fine sphere (edges 0.06) a step of 0.01 put
        one vertex's difference at -2.97 against -4.33 at 0.001."""
        from torchir.functions import render

        scene = self._scenes.setdefault("reference", torchir.Scene.from_dict(scene_dict(self.spec, {"type": "direct"}, self.resolution)))
        v0 = scene.get(KEY)
        if h is None:
            p = v0.reshape(-1, 3).double().cpu().numpy()
            faces = mesh_weld(mi.load_dict(self.spec)).faces.astype(np.int64)
            h = 0.02 * float(np.median(np.linalg.norm(p[faces[:, 1]] - p[faces[:, 0]], axis=1)))
        out = {}
        for name, d in zip(("translation", "vertex"), self.directions(self.user_vertex_mask, v0.numel() // 3)):
            if only is not None and name != only:
                continue
            fd = [float(((render(scene, {KEY: v0 + h * d}, spp=spp, seed=s) - render(scene, {KEY: v0 - h * d}, spp=spp, seed=s))
                         * self.adjoint).sum()) / (2 * h) for s in range(seeds)]
            out[name] = (float(np.mean(fd)), float(np.std(fd, ddof=1) / math.sqrt(seeds)))
        return out

    def estimates(self, path: str, steps: int, spp: int, seed: int = 100, chains: int = 1) -> np.ndarray:
        """``(chains, steps, 2)`` derivatives (translation, vertex) through ``path``: ``chains``
        independent runs (each its own sampler, so its own reservoirs, guides and burn-in) of
        ``steps`` steps each."""
        from torchir.functions import render
        from torchir.samplers import ReSTIRSampler

        scene = self.scene(path)
        v0 = scene.get(KEY)
        d_t, d_v = self.directions(self.user_vertex_mask, v0.numel() // 3)
        out = np.zeros((chains, steps, 2))
        for c in range(chains):
            start = seed + 1000 * c
            sampler = None if path in ("direct_projective", "prb_projective") else ReSTIRSampler(scene, preset=path, seed=start)
            for i in range(steps):
                t = torch.zeros(2, requires_grad=True)
                image = render(scene, {KEY: v0 + t[0] * d_t + t[1] * d_v}, spp=spp, seed=start + i, sampler=sampler)
                (image * self.adjoint).sum().backward()
                out[c, i] = t.grad.cpu().numpy()
        return out


def mean_and_se(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean, standard error and its degrees of freedom of ``g`` (``(chains, steps, k)``, from
    :meth:`Problem.estimates`). With several chains the error comes from the chains' means: a
    chain's steps are correlated through its reservoirs and edge chains (on a duck, ReSTIR's six
    chains of 16 steps had means from -12 to -48 with per-step errors of 2-4, and a lag-one
    autocorrelation of 0.32), so the per-step formula understated the error 3x and put z at 5.1
    where the chains' spread gives 0.4. One chain: the per-step formula, right only for paths
    without state across steps (``direct_projective``, ``prb_projective``)."""
    chains, steps = g.shape[:2]
    if chains > 1:
        means = g.mean(axis=1)
        return means.mean(axis=0), means.std(axis=0, ddof=1) / math.sqrt(chains), chains - 1
    flat = g.reshape(steps, -1)
    return flat.mean(axis=0), flat.std(axis=0, ddof=1) / math.sqrt(steps), steps - 1


def z_bound(dof: float, false_rate: float = 1e-4) -> float:
    """The two-sided Student-t quantile for ``dof`` degrees of freedom whose tail holds
    ``false_rate``: a mean within that many estimated standard errors of the truth is rejected
    with probability ``false_rate`` (the standard error itself is an estimate from ``dof + 1``
    values, so the normal 3.9 would reject far more often with few chains)."""
    from scipy.stats import t

    return float(t.ppf(1.0 - false_rate / 2.0, dof))


def welch_dof(se: float, dof: int, se_ref: float, dof_ref: int) -> float:
    """Welch-Satterthwaite degrees of freedom of ``sqrt(se² + se_ref²)``, each standard error
    estimated with its own degrees of freedom."""
    num = (se**2 + se_ref**2) ** 2
    den = se**4 / max(dof, 1) + se_ref**4 / max(dof_ref, 1)
    return float(num / den) if den > 0 else float(max(dof, dof_ref))


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--meshes", nargs="*", default=None, help="OBJ/PLY files (default: the exported set, as OBJ and PLY)")
    p.add_argument("--paths", default=None, help=f"comma-separated, from {','.join(PATHS)}")
    p.add_argument("--resolution", type=int, default=None)
    p.add_argument("--steps", type=int, default=None, help="gradient steps per chain (the per-step spread)")
    p.add_argument("--chains", type=int, default=None, help="independent runs per path (the standard error comes from their means)")
    p.add_argument("--spp", type=int, default=1)
    p.add_argument("--ref-spp", type=int, default=None)
    p.add_argument("--ref-seeds", type=int, default=8)
    p.add_argument("--face-normals", action="store_true", help="load the meshes faceted (Mitsuba's face_normals option)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path, default=Path("results/bench/mesh_gradients"))
    a = p.parse_args(argv)
    a.paths = [s.strip() for s in (a.paths or ("direct_projective,restir" if a.quick else ",".join(PATHS))).split(",") if s.strip()]
    unknown = [s for s in a.paths if s not in PATHS]
    if unknown:
        p.error(f"unknown path(s) {unknown}; choose from {', '.join(PATHS)}")
    a.resolution = a.resolution or (16 if a.quick else 32)
    a.steps = a.steps or (4 if a.quick else 8)
    a.chains = a.chains or (4 if a.quick else 6)
    if a.chains < 2:
        p.error("--chains must be >= 2: the standard error comes from the chains' means")
    a.ref_spp = a.ref_spp or (1024 if a.quick else 4096)
    return a


def run(a: argparse.Namespace) -> list[dict[str, Any]]:
    meshes = a.meshes
    if not meshes:
        folder = Path(tempfile.mkdtemp(prefix="torchir-meshes-"))
        meshes = [str(p[k]) for p in write_all(folder).values() for k in (("obj",) if a.quick else ("obj", "ply"))]
    rows = []
    for path in meshes:
        problem = Problem(path, a.resolution, a.face_normals)
        started = time.perf_counter()
        ref = problem.reference(a.ref_spp, a.ref_seeds)
        print(f"[mesh_gradients] {problem.name}: {problem.repeats} repeated vertices, reference "
              f"{ref['translation'][0]:.3g} / {ref['vertex'][0]:.3g} ({time.perf_counter() - started:.0f} s)", flush=True)
        for path_name in a.paths:
            started = time.perf_counter()
            try:
                g = problem.estimates(path_name, a.steps, a.spp, chains=a.chains)
            except ValueError as refused:  # torchir refuses what it cannot differentiate right
                print(f"[mesh_gradients]   {path_name}: refused ({refused})", flush=True)
                rows += [{"mesh": problem.name, "repeats": problem.repeats, "path": path_name, "direction": d, "refused": str(refused)}
                         for d in ("translation", "vertex")]
                continue
            seconds = (time.perf_counter() - started) / (a.steps * a.chains)
            means, ses, _ = mean_and_se(g)
            flat = g.reshape(-1, 2)
            for k, direction in enumerate(("translation", "vertex")):
                mean, se = float(means[k]), float(ses[k])
                r_mean, r_se = ref[direction]
                rows.append({"mesh": problem.name, "repeats": problem.repeats, "path": path_name, "direction": direction,
                             "mean": mean, "se": se, "reference": r_mean, "reference_se": r_se,
                             "z": abs(mean - r_mean) / math.sqrt(se**2 + r_se**2 + 1e-30),
                             "rms_error": float(np.sqrt(np.mean((flat[:, k] - r_mean) ** 2))), "sd": float(flat[:, k].std(ddof=1)),
                             "seconds_per_step": seconds, "steps": a.steps, "chains": a.chains, "spp": a.spp})
            print(f"[mesh_gradients]   {path_name}: {means.round(3).tolist()} ({seconds:.2f} s/step)", flush=True)
    for row in rows:
        base = [r for r in rows if r["mesh"] == row["mesh"] and r["direction"] == row["direction"] and r["path"] == "direct_projective"
                and "refused" not in r]
        row["rms_vs_direct_projective"] = (row["rms_error"] / base[0]["rms_error"]
                                           if base and base[0]["rms_error"] > 0 and "refused" not in row else None)
    return rows


def summarize(rows: list[dict[str, Any]], a: argparse.Namespace) -> str:
    lines = [f"## Shape derivatives on exported meshes ({a.resolution}², {a.spp} spp a step, {a.chains} chains x {a.steps} steps, "
             f"standard errors from the chains' means; "
             f"reference: central differences, copies moved together, {a.ref_spp} spp x {a.ref_seeds} seeds)", "",
             "| mesh | repeated vertices | path | direction | mean ± s.e. | reference ± s.e. | z | rms error | x direct_projective's |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "refused" in r:
            why = r["refused"].split(": ", 1)[-1].split(";")[0]
            lines.append(f"| {r['mesh']} | {r['repeats']} | {r['path']} | {r['direction']} | refused ({why}) | | | | |")
            continue
        ratio = "" if r["rms_vs_direct_projective"] is None else f"{r['rms_vs_direct_projective']:.2f}"
        lines.append(f"| {r['mesh']} | {r['repeats']} | {r['path']} | {r['direction']} | {r['mean']:.3g} ± {r['se']:.2g} | "
                     f"{r['reference']:.3g} ± {r['reference_se']:.2g} | {r['z']:.1f} | {r['rms_error']:.3g} | {ratio} |")
    measured = [r for r in rows if "refused" not in r]
    if measured:
        worst = max(measured, key=lambda r: r["z"])
        lines += ["", f"Largest z: {worst['z']:.1f} ({worst['mesh']}, {worst['path']}, {worst['direction']}); "
                  f"largest rms ratio: {max((r['rms_vs_direct_projective'] or 0) for r in measured):.2f}."]
    return "\n".join(lines) + "\n"


def draw(rows: list[dict[str, Any]]):
    def plot(ax):
        paths = sorted({r["path"] for r in rows}, key=PATHS.index)
        for k, path in enumerate(paths):
            zs = [r["z"] for r in rows if r["path"] == path and "refused" not in r]
            ax.scatter(np.full(len(zs), k) + np.linspace(-0.2, 0.2, len(zs)), zs, s=12, label=path)
        ax.axhline(4.0, color="k", lw=0.8, ls="--", label="4 s.e.")
        ax.set_xticks(range(len(paths)), paths, rotation=20, fontsize=7)
    return plot


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    a = parse_args(argv)
    torchir.backend.set_variant("auto")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = run(a)
    write_outputs(a.out, summarize(rows, a), {"args": {k: str(v) for k, v in vars(a).items()}, "rows": rows}, draw(rows),
                  "mesh_gradients.png", "path", "|mean - reference| / s.e.")
    return rows


if __name__ == "__main__":
    main()
