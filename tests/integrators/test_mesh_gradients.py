"""Shape derivatives on meshes as exporters write them (``torchir.bench.exported_meshes``):
through ReSTIR and Mitsuba's projective integrators, the derivative of a fixed linear image loss
w.r.t. the mesh's translation and one welded vertex's displacement (every copy at its position
moving together) agrees with central differences of that motion. Before torchir took topology from positions, ReSTIR gave
-3e2 ... -3e6 for a derivative of about -10 on a UV sphere, and ``direct_projective`` 2x on
Mitsuba's ``cube``.

Each bound is the Student-t quantile that a correct estimator exceeds with probability 1e-4 per
comparison, for the combined standard error (the estimate's and the reference's, Welch's degrees of
freedom). Paths that keep samples across steps (the ``restir`` preset's reservoirs) are run as
independent chains and their error taken from the chains' means: their steps are correlated, and the
per-step formula understated the error 3x on a duck. The boundary terms are heavy-tailed, so the
steps are many enough that each mean is near normal."""
from __future__ import annotations

import math

import pytest

from torchir.bench.exported_meshes import uv_sphere, write_obj
from torchir.bench.mesh_gradients import PATHS, Problem, mean_and_se, welch_dof, z_bound

RES = 16
REF_SEEDS = 6
STATELESS = ("direct_projective", "prb_projective", "b1", "b2")  # fresh samples each step: uncorrelated errors


@pytest.fixture(scope="module")
def problems() -> dict[str, Problem]:
    """The module's problems (their scenes), built on first use and freed with the module."""
    return {}


def _problem(exported, problems, name: str, kind: str = "obj") -> tuple[Problem, dict[str, tuple[float, float]]]:
    key = f"{name}.{kind}"
    if key not in problems:
        problem = Problem(exported[name][kind], RES)
        problems[key] = problem
        problem.ref = problem.reference(spp=1024, seeds=REF_SEEDS)
    return problems[key], problems[key].ref


def _agrees(problem: Problem, ref, path: str, steps: int, spp: int) -> None:
    """``steps`` steps of ``path`` (one chain for a stateless path, else ``steps`` chains of one
    step after each chain's burn-in) agree with the reference."""
    chains, per_chain = (1, steps) if path in STATELESS else (steps, 1)
    means, ses, dof = mean_and_se(problem.estimates(path, per_chain, spp, chains=chains))
    for k, direction in enumerate(("translation", "vertex")):
        mean, se = float(means[k]), float(ses[k])
        r_mean, r_se = ref[direction]
        assert abs(r_mean) > 4 * r_se  # the reference resolves a derivative
        bound = z_bound(welch_dof(se, dof, r_se, REF_SEEDS - 1))
        assert abs(mean - r_mean) < bound * math.sqrt(se**2 + r_se**2), (problem.name, path, direction, mean, se, r_mean, r_se, bound)


@pytest.mark.parametrize("name", ["uv_sphere", "cube", "open_cylinder"])
def test_restir_shape_derivatives_on_exported_meshes(exported, problems, name):
    """A UV sphere (seam and poles repeated), Mitsuba's 24-vertex cube (flat), an open tube seen
    inside; the boundary terms do not depend on the preset (every preset: the slow test)."""
    problem, ref = _problem(exported, problems, name)
    _agrees(problem, ref, "b2", steps=16, spp=1)


def test_a_faceted_mesh_without_normals_is_refused_by_direct_projective_and_right_through_restir(tmp_path):
    """A sphere written with positions and faces only (no uvs, no normals: the faces share every
    vertex) and loaded faceted (Mitsuba's ``face_normals``): every bent edge is a shading crease.
    Before creases came from flat shading too, this mesh had none: ``direct_projective`` was not
    refused, and ReSTIR left its primary term to Mitsuba's (measured at 32², 32 spp a step: -52.4 +-
    0.3 against -42.7 +- 0.9 for the translation, 1.32 against 1.76 for a vertex)."""
    sphere = uv_sphere()
    sphere.vt, sphere.vn = [], []
    sphere.faces = [tuple((v, None, None) for v, _, _ in face) for face in sphere.faces]
    write_obj(sphere, tmp_path / "plain_sphere.obj")
    problem = Problem(tmp_path / "plain_sphere.obj", RES, face_normals=True)
    with pytest.raises(ValueError, match="flat-shaded or hard-edged"):
        problem.estimates("direct_projective", 1, 1)
    _agrees(problem, problem.reference(spp=1024, seeds=REF_SEEDS), "b2", steps=16, spp=1)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_restir_default_preset_on_a_uv_sphere(exported, problems):
    problem, ref = _problem(exported, problems, "uv_sphere")
    _agrees(problem, ref, "restir", steps=12, spp=1)


def test_direct_projective_shape_derivatives_on_a_uv_sphere(exported, problems):
    """Welded by position for the boundary pass: without it, -3.2 against -9.8 (16², 1 spp) when the
    weld was made; rerun without it on 2026-12-03 this check passed, so the weld on a smooth mesh is
    guarded at 32² (the next test)."""
    problem, ref = _problem(exported, problems, "uv_sphere")
    _agrees(problem, ref, "direct_projective", steps=12, spp=16)


def test_direct_projective_translation_on_a_uv_sphere_at_32px(exported):
    """At 32² a seam taken for a border biases the translation derivative: the boundary pass on the
    user's faces gave -26.8 +- 2.2 against -38.6 +- 1.3 by finite differences (64 steps at 16 spp,
    2026-12-03), which the 16² check above does not resolve; welded, -37.6 +- 1.9."""
    problem = Problem(exported["uv_sphere"]["obj"], 32, vertex=0)  # a translation: no vertex to search for
    r_mean, r_se = problem.reference(spp=1024, seeds=16, only="translation")["translation"]
    means, ses, dof = mean_and_se(problem.estimates("direct_projective", 96, 16))
    mean, se = float(means[0]), float(ses[0])
    bound = z_bound(welch_dof(se, dof, r_se, 15))
    assert abs(mean - r_mean) < bound * math.sqrt(se**2 + r_se**2), (mean, se, r_mean, r_se, bound)


REMEDIES = {"smooth": "smooth vertex normals", "two-sided": "two-sided material ('twosided' BSDF) or close its surface"}


@pytest.mark.parametrize("name, why, remedy", [("cube", "flat-shaded or hard-edged", "smooth"),
                                               ("open_cylinder", "back of its one-sided material past an open border", "two-sided")])
def test_projective_integrators_refuse_what_mitsuba_differentiates_wrong(exported, problems, name, why, remedy):
    """A flat-shaded mesh in view, or the back of a one-sided material seen past an open border:
    Mitsuba's primary silhouette term is wrong there (a cube 1.46x, a tube -5.8 against +1.8),
    so torchir refuses with what to do instead of returning a wrong number: ReSTIR, or the one
    change to the mesh that removes *its* problem (a cube is closed already: closing it is no advice)."""
    problem, _ = _problem(exported, problems, name)
    with pytest.raises(ValueError, match=rf"{why}.*ReSTIRSampler") as refused:
        problem.estimates("direct_projective", 1, 1)
    message = str(refused.value)
    assert all((text in message) == (key == remedy) for key, text in REMEDIES.items()), message


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name", ["uv_sphere", "cube", "flat_blob", "open_cylinder", "holed_sphere", "fin_box"])
def test_every_path_on_every_exported_mesh(exported, problems, name, path):
    problem, ref = _problem(exported, problems, name, "ply")
    spp = 16 if path in ("direct_projective", "prb_projective") else 1
    try:
        _agrees(problem, ref, path, steps=24, spp=spp)
    except ValueError as refused:
        assert path in ("direct_projective", "prb_projective") and "open border" in str(refused)


@pytest.mark.slow  # statistical soak / benchmark run: out of CI, `python3 -m pytest -n 2 -m slow`
def test_bench_runs_end_to_end_and_records_refusals(exported, tmp_path):
    from torchir.bench.mesh_gradients import main

    rows = main(["--quick", "--meshes", str(exported["cube"]["ply"]), "--paths", "direct_projective,b2", "--steps", "2",
                 "--ref-seeds", "2", "--ref-spp", "64", "--out", str(tmp_path)])
    assert {(r["path"], r["direction"]) for r in rows} == {(p, d) for p in ("direct_projective", "b2") for d in ("translation", "vertex")}
    assert all("refused" in r for r in rows if r["path"] == "direct_projective")  # a flat-shaded cube in view
    assert all(math.isfinite(r["mean"]) and r["rms_vs_direct_projective"] is None for r in rows if r["path"] == "b2")
    text = (tmp_path / "summary.md").read_text()
    assert "| cube.ply | 16 | direct_projective | translation | refused (the sensor sees this flat-shaded or hard-edged mesh" in text and (tmp_path / "mesh_gradients.png").is_file()


def test_standard_errors_come_from_independent_chains():
    """Steps of one ReSTIR run share reservoirs, so their errors are correlated: the spread of
    independent runs' means measures the error of the mean, the per-step formula does not. Here
    each chain carries its own offset (sd 1) for all its 16 steps, as a long-lived reservoir
    does; the true error of the grand mean over 200 chains is 1/sqrt(200)."""
    import numpy as np

    rng = np.random.default_rng(0)
    chains, steps = 200, 16
    g = rng.normal(size=(chains, 1, 1)) + 0.1 * rng.normal(size=(chains, steps, 1))
    _, se, dof = mean_and_se(g)
    assert dof == chains - 1 and abs(float(se[0]) * math.sqrt(chains) - 1.0) < 0.15  # 1/sqrt(2 x 199): 5 % of sd
    _, naive, _ = mean_and_se(g.reshape(1, chains * steps, 1))  # one "chain" of all steps: the per-step formula
    assert float(naive[0]) < 0.3 * float(se[0])  # 4x too small: what put a right duck derivative at z = 5
    assert abs(z_bound(10**9) - 3.891) < 1e-3 and abs(z_bound(5) - 11.178) < 1e-2  # normal limit; few values: wider
    assert welch_dof(1.0, 5, 0.0, 7) == 5.0 and welch_dof(0.0, 5, 1.0, 7) == 7.0 and 5.0 < welch_dof(1.0, 5, 1.0, 7) < 12.0
