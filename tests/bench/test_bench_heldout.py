"""Held-out scene families (:mod:`torchir.bench.heldout`) and their use in ``torchir bench restir``:
each family builds and renders, draws its layout from its seed, ``open`` has nothing between
canvas and lights, specs parse (or fail clearly), and the bench takes held-out specs and
``--restirs auto``."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchir.bench import heldout

FAMILIES = tuple(heldout.FAMILIES)


def _layout(scene_dict: dict) -> list[tuple[str, np.ndarray]]:
    """What a seed decides: every entry's position, transform, intensity and texture, as arrays."""
    out = []
    for name, entry in sorted(scene_dict.items()):
        if not isinstance(entry, dict):
            continue
        for field in ("position", "to_world", "intensity", "emitter", "bsdf"):
            value = entry.get(field)
            if field == "emitter" and value is not None:
                value = value["radiance"]
            if field == "bsdf" and value is not None:
                value = value["reflectance"].get("data", value["reflectance"].get("value"))
            if isinstance(value, dict):
                value = value["value"]
            if value is None:
                continue
            value = value.matrix if hasattr(value, "matrix") else value
            out.append((f"{name}.{field}", np.asarray(value, dtype=np.float64)))
    return out


def _same(a: list, b: list) -> bool:
    return [k for k, _ in a] == [k for k, _ in b] and all(x.shape == y.shape and np.allclose(x, y) for (_, x), (_, y) in zip(a, b))


@pytest.mark.parametrize("family", FAMILIES)
def test_family_builds_and_renders(family):
    from torchir.functions import render

    scene, key = heldout.load(f"heldout:{family}:5", 16)
    assert key == heldout.spec(family)[1]
    texture = scene.get(key)
    assert texture.ndim == 3 and texture.shape[0] == texture.shape[1] and texture.shape[2] == 3
    assert float(texture.min()) >= 0.05 - 1e-6 and float(texture.max()) <= 0.9 + 1e-6
    image = render(scene, {}, spp=16, seed=0)
    assert image.shape == (3, 16, 16) and torch.isfinite(image).all() and float(image.sum()) > 0
    grad = torch.full_like(texture, 0.5).requires_grad_()
    render(scene, {key: grad}, spp=4, seed=1).sum().backward()  # the texture is differentiable
    assert torch.isfinite(grad.grad).all() and float(grad.grad.abs().sum()) > 0
    d = heldout.spec(family)[0](resolution=16, seed=5)
    assert d["integrator"] == {"type": "prb", "max_depth": 2} and d["sensor"]["film"]["rfilter"] == {"type": "box"}


@pytest.mark.parametrize("family", FAMILIES)
def test_seed_decides_the_layout(family):
    build, _ = heldout.spec(family)
    a, b, c = _layout(build(resolution=16, seed=7)), _layout(build(resolution=16, seed=7)), _layout(build(resolution=16, seed=8))
    assert _same(a, b) and not _same(a, c)


def test_family_parameters():
    slit = heldout.slit_lights(resolution=16, seed=3)
    lights = [k for k in slit if k.startswith("light_")]
    assert 100 <= len(lights) <= 300 and "fill" in slit and 8 <= slit["painting"]["bsdf"]["reflectance"]["data"].shape[0] <= 16
    assert "fill" not in heldout.slit_lights(resolution=16, seed=3, fill=0.0)
    fine = heldout.fine_texture(seed=2)
    assert fine["sensor"]["film"]["width"] == 96 and fine["canvas"]["bsdf"]["reflectance"]["data"].shape[0] == 256  # texels < pixels
    assert _same(_layout(heldout.holes(resolution=16, seed=2, texture=12)), _layout(heldout.holes(resolution=16, seed=2, texture=12)))
    assert [heldout.FAMILIES[f].light_bound for f in FAMILIES] == [True, True, False, True]
    with pytest.raises(ValueError, match="seed"):
        heldout.holes(seed=-1)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_open_has_nothing_between_canvas_and_lights(seed):
    """Shadow rays from a grid of canvas points to points spread over every light are never blocked."""
    import mitsuba as mi

    d = heldout.open_canvas(resolution=16, seed=seed, lights=2 if seed < 4 else None)
    shapes = {k for k, v in d.items() if isinstance(v, dict) and v.get("type") == "rectangle"}
    assert shapes == {"canvas", *[k for k in d if k.startswith("area_")]}  # the canvas and the lights, nothing else
    mi_scene = mi.load_dict(d)
    c = (np.arange(6) + 0.5) / 6 * 2 - 1
    canvas = np.array([[x, y, 1e-4] for x in c for y in c])
    g = np.array([[u, v] for u in (-0.9, 0, 0.9) for v in (-0.9, 0, 0.9)])
    for name in (k for k in d if k.startswith("area_")):
        m = np.array(d[name]["to_world"].matrix, dtype=np.float64)
        light = m[:3, 3] + g[:, :1] * m[:3, 0] + g[:, 1:] * m[:3, 1]
        p = np.repeat(canvas, len(light), 0)
        q = np.tile(light, (len(canvas), 1))
        dist = np.linalg.norm(q - p, axis=1)
        ray = mi.Ray3f(mi.Point3f(*p.T), mi.Vector3f(*((q - p) / dist[:, None]).T))
        ray.maxt = mi.Float(dist * (1 - 1e-3))
        assert not np.asarray(mi_scene.ray_test(ray)).any(), name


def test_spec_parsing_and_errors():
    assert heldout.parse_spec("heldout:slit_lights:7") == ("slit_lights", 7) and heldout.parse_spec(" heldout:open:03 ") == ("open", 3)
    assert heldout.is_spec("heldout:nope") and not heldout.is_spec("many_lights")
    for bad, match in (("heldout:nope:1", "unknown held-out family 'nope'.*slit_lights, holes, open, fine_texture"),
                       ("heldout:open", "heldout:<family>:<seed>"), ("heldout:open:1:2", "heldout:<family>:<seed>"),
                       ("heldout:open:x", "seed"), ("heldout:open:-1", "seed"), ("other:open:1", "heldout:<family>:<seed>")):
        with pytest.raises(ValueError, match=match):
            heldout.parse_spec(bad)
    with pytest.raises(KeyError, match="families"):
        heldout.spec("nope")
    assert heldout.factory("heldout:open:3") == ("torchir.bench.heldout:open_canvas", {"seed": 3})
    drawn = heldout.draw_specs(2, clock=11)
    assert drawn == heldout.draw_specs(2, clock=11) != heldout.draw_specs(2, clock=12)
    assert [heldout.parse_spec(s)[0] for s in drawn] == [f for f in FAMILIES for _ in range(2)]
    assert len(set(drawn)) == len(drawn)


def test_restir_bench_takes_heldout_specs_and_auto():
    from torchir.bench import restir
    from torchir.bench.restir_report import file_stem

    a = restir.parse_args(["--scenes", "heldout:slit_lights:7,heldout:open:3", "--restirs", "auto"])
    assert a.restir_methods == (restir.AUTO,) and a.methods == (*restir.BASELINES, restir.AUTO)
    assert restir.sampler_options(restir.AUTO, a) == {"preset": "auto"}
    both = restir.parse_args(["--restirs", "persistent,auto", "--heldout", "2"])
    assert both.restir_methods == ("ReSTIR (persistent)", restir.AUTO) and both.heldout == 2
    assert restir.parse_args([]).restir_methods == restir.restir_variants(restir.DEFAULT_RESTIRS)  # auto: only when asked
    for bad in (["--heldout", "-1"], ["--restirs", "automatic"]):
        with pytest.raises(SystemExit):
            restir.parse_args(bad)
    assert restir.resolve_scenes(a.scenes) == (["heldout:slit_lights:7", "heldout:open:3"], [])
    assert restir.resolve_scenes("cbox, heldout:holes:04,heldout:holes:4")[0] == ["cbox", "heldout:holes:4"]
    with pytest.raises(ValueError, match="unknown held-out family 'slits'.*families: slit_lights"):
        restir.resolve_scenes("heldout:slits:1")
    with pytest.raises(ValueError, match="unknown scene 'nope'.*heldout:<family>:<seed>"):
        restir.resolve_scenes("nope")
    with pytest.raises(SystemExit, match="unknown held-out family"):
        restir.main(["--scenes", "heldout:slits:1", "--out", "/nonexistent/never-written"])
    assert restir.trainer_scene("cbox") == {"scene": "cbox"}
    assert restir.trainer_scene("heldout:open:3") == {"scene": "torchir.bench.heldout:open_canvas", "scene_options": {"seed": 3}}
    assert file_stem("heldout:open:3") == "heldout_open_3" and file_stem("cbox") == "cbox"


def test_trainer_builds_a_heldout_scene():
    """The trainer's factory path gives the same scene as the bench's gradient problem."""
    from torchir.bench import restir
    from torchir.training import InverseRenderingModule

    spec = "heldout:fine_texture:2"
    scene, key = restir.load_scene(spec, 16)
    module = InverseRenderingModule(**restir.trainer_scene(spec), resolution=16, parameters={key: {"init": 0.5, "bounds": [1e-3, 1.0]}})
    assert torch.equal(module.ground_truth()[key], scene.get(key))


def test_tables_give_the_auto_row_its_gain_and_bound():
    """A held-out scene's table: its note, and the auto row's gain against the best baseline with the floor bound."""
    from torchir.bench.restir_report import ORACLE, summarize_scene, tables

    def run(method: str, spp: int, error: float, seconds: float = 0.1) -> dict:
        return {"method": method, "spp": spp, "relerr_steps": [error] * 2, "relerr": error, "relerr_sq_se": 0.0, "seconds_per_step": seconds,
                "burn_in_seconds": 0.0, "charged_seconds_per_step": seconds, "stages": {}}

    auto = "ReSTIR (auto)"
    spp_eq = {"direct": 2, "B.1": 2, "B.2": 2, auto: 1}
    runs = [run(m, s, e / math.sqrt(s), 0.1 * s) for m, e in (("direct", 0.5), ("B.1", 0.6), ("B.2", 0.3)) for s in (1, 2)]
    runs += [run(auto, 1, 0.05, 0.2), run(ORACLE, 1, 0.04)]
    s = summarize_scene(runs, 1, spp_eq, budget=0.2)
    assert s["best_baseline"] == "B.2" and s["rows"][auto]["gain"] == pytest.approx(0.3 / math.sqrt(2) / 0.05)
    assert s["rows"][auto]["bound"] == pytest.approx(0.3 / math.sqrt(2) / 0.04)
    scene = {**s, "reference": {"relative_se": 0.001}, "calibration": {"budget_seconds": 0.2, "budget_method": auto},
             "heldout": {"family": "open", "seed": 3, "light_bound": False}}
    text = tables({"config": {"spp": 1, "resolution": 16, "candidates": 16, "burn_in": 8, "oracle_candidates": 256, "grad_steps": 2,
                              "ref_spp": 64, "lr": 0.02, "recon_steps": 3, "recon_seeds": 1, "grad_paths": ["decorrelated"]},
                   "scenes": {"heldout:open:3": scene}})
    assert "#### heldout:open:3" in text and "Held-out scene (family open, seed 3" in text and "not light-bound" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {auto} |"))
    assert "gain 4.2x of possible 5.3x" in row
