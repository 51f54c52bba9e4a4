"""``torchir tune``: the pure parts (equal-time scaling, Pareto front, the search orders on a
synthetic cost model, the loss-change rule), which settings apply to which scene, reading and
writing configs, and two real runs on a 16x16 painting (one through the command line, one
stopped by a tiny budget)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

import torchir
from torchir import cli
from torchir.modules import LOSSES
from torchir.tune import EFFORTS, OPTIMISER_WINDOW, Setting, enumerate_space, equal_time_error, pareto_front
from torchir.tune.config import read_config, tuned_path, write_tuned
from torchir.tune.search import BudgetSpent, Clock, Search, coordinate_search, grid_search, with_loss_choice

TINY = """# a tiny painting run: no trainer.logger, no data section
model:
  scene: painting
  resolution: 16
  parameters:
    canvas.bsdf.reflectance.data: {init: 0.5, bounds: [0.0, 1.0]}
  loss: l2
  spp: 4
  lr: 0.02
trainer:
  max_steps: 50
"""


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "run.yaml"
    path.write_text(TINY)
    return path


# ------------------------------------------------------------------------------ pure parts
def test_equal_time_error_scales_with_the_square_root_of_time():
    assert equal_time_error(0.4, 1.0, 1.0) == pytest.approx(0.4)
    assert equal_time_error(0.4, 4.0, 1.0) == pytest.approx(0.8)  # 4x slower: a quarter of the steps, 2x the error
    assert equal_time_error(0.4, 1.0, 4.0) == pytest.approx(0.2)
    # twice the spp at twice the time with 1/sqrt(2) the error: the same equal-time error
    assert equal_time_error(0.4 / math.sqrt(2), 2.0, 3.0) == pytest.approx(equal_time_error(0.4, 1.0, 3.0))
    with pytest.raises(ValueError):
        equal_time_error(0.4, 0.0, 1.0)


def test_pareto_front_of_synthetic_points():
    points = [(1.0, 5.0), (2.0, 3.0), (2.0, 4.0), (3.0, 3.0), (4.0, 1.0), (0.5, 9.0), (5.0, 1.0), (math.nan, 0.1), (2.0, 3.0)]
    front = pareto_front(points)
    assert front == [True, True, False, False, True, True, False, False, True]  # equal points do not dominate each other
    assert pareto_front([]) == []
    assert pareto_front([(1.0, 1.0)]) == [True]


def _space(spp=4):
    """A space on a 16x16 painting with an L2 loss (ReSTIR applies: direct illumination)."""
    scene = torchir.Scene.builtin("painting", resolution=16)
    return enumerate_space({"spp": spp, "loss": "l2"}, scene, LOSSES["l2"](), True, quick=False)


def _synthetic(space):
    """A cost model: error falls as 1/sqrt(spp) from a per-technique constant, time grows with
    spp from a per-technique overhead; the denoiser halves the error at 1.5x the time."""
    base_error = {None: 4.0, "uniform": 5.0, "loss": 4.5, "adaptive": 3.5, "restir": 0.5}
    overhead = {None: 0.002, "uniform": 0.004, "loss": 0.004, "adaptive": 0.005, "restir": 0.01}
    calls = []

    def evaluate(setting: Setting, steps: int, deadline):
        calls.append((setting.key, steps))
        kind = None if setting.sampler is None else setting.sampler["type"]
        if kind == "restir" and setting.sampler.get("preset") == "auto":
            return {"kind": "gradient", "setting": setting.label(), "key": setting.key, "status": "unavailable", "error": "no auto"}
        preset = (setting.sampler or {}).get("preset")
        error = base_error[kind] * (0.7 if preset == "persistent" else 1.0) / math.sqrt(setting.spp)
        seconds = overhead[kind] + 0.001 * setting.spp * (0.25 if setting.pixel else 1.0)
        if setting.denoiser is not None:
            error, seconds = error * 0.5, seconds * 1.5
        return {"kind": "gradient", "setting": setting.label(), "key": setting.key, "status": "ran", "steps": steps,
                "gradient_error": error, "seconds_per_step": seconds}

    return evaluate, calls


def test_coordinate_search_finds_the_grid_best_with_few_trials():
    space = _space()
    evaluate, calls = _synthetic(space)
    grid = Search(evaluate, Clock(None))
    best = grid_search(space, grid, 12)
    evaluate2, calls2 = _synthetic(space)
    search = Search(evaluate2, Clock(None))
    chosen = coordinate_search(space, search, 4, 12, 3)
    assert chosen is not None and best is not None
    assert search.score(chosen) <= 1.3 * grid.score(best)
    assert len(calls2) < len(calls) / 3  # a fraction of the grid's trials
    assert sum(steps for _, steps in calls2) < sum(steps for _, steps in calls) / 8  # and of its steps
    assert any("auto" in k for k in search.unavailable)  # the missing preset was tried once and noted


def test_search_stops_when_the_budget_is_spent():
    space = _space()
    evaluate, calls = _synthetic(space)
    clock = Clock(1e-3)
    search = Search(evaluate, clock)
    while clock.left() > 0:
        pass
    with pytest.raises(BudgetSpent):
        coordinate_search(space, search, 4, 12, 3)
    assert calls == []


def test_a_loss_change_is_chosen_only_when_it_trains_clearly_faster():
    plain, loi = Setting(4), Setting(4, loss={"type": "loi"})
    def rows(a, b):
        return [(plain, {"status": "ran", "decrease_per_second": a}), (loi, {"status": "ran", "decrease_per_second": b})]

    assert with_loss_choice(plain, rows(1.0, 1.2))[0] is plain
    assert with_loss_choice(plain, rows(1.0, 2.0))[0] is loi
    assert with_loss_choice(plain, rows(-1.0, 2.0))[0] is plain  # the chosen run did not fall: too short to compare
    assert with_loss_choice(plain, rows(1.0, math.nan))[0] is plain


def test_the_config_s_own_setting_wins_back_where_the_chosen_one_trains_worse():
    """The training runs check the gradient score: the config's own setting replaces the chosen
    one where its run lowered the error and the chosen one's rose or stayed, or 1.5x faster; not
    where the chosen one's is within that factor, nor without a run of the config's own."""
    base, chosen = Setting(4), Setting(8, {"type": "restir", "preset": "persistent"})
    def rows(own, picked):
        return [(chosen, {"status": "ran", "decrease_per_second": picked}), (base, {"status": "ran", "decrease_per_second": own})]

    final, why = with_loss_choice(chosen, rows(0.02, -0.0099), base=base)
    assert final is base and "rose" in why
    assert with_loss_choice(chosen, rows(0.02, 0.0), base=base)[0] is base
    final, why = with_loss_choice(chosen, rows(0.031, 0.02), base=base)
    assert final is base and "1.6x faster" in why
    assert with_loss_choice(chosen, rows(0.029, 0.02), base=base)[0] is chosen
    assert with_loss_choice(chosen, rows(-0.01, -0.02), base=base)[0] is chosen  # neither fell: too short to compare
    assert with_loss_choice(chosen, rows(0.02, -0.0099))[0] is chosen  # no base given
    assert with_loss_choice(chosen, [(chosen, {"status": "ran", "decrease_per_second": -0.01})], base=base)[0] is chosen


# ------------------------------------------------------------------------------- space
def test_restir_only_for_direct_illumination_scenes():
    painting = _space()
    assert {s["preset"] for s in painting.samplers if s and s["type"] == "restir"} == {"auto", "persistent", "restir", "b2"}
    cbox = enumerate_space({"spp": 4}, torchir.Scene.builtin("cbox", resolution=16), LOSSES["l2"](), True, quick=True)
    assert not any(s and s["type"] == "restir" for s in cbox.samplers)
    assert any("ReSTIR: left out" in n and "indirect" in n for n in cbox.notes)
    assert not any(s.sampler and s.sampler["type"] == "restir" for s in cbox.grid())


def test_pixel_sampling_and_loi_follow_the_loss_and_targets():
    scene = torchir.Scene.builtin("painting", resolution=16)
    l2 = enumerate_space({"spp": 2, "loss": "l2"}, scene, LOSSES["l2"](), True, quick=True)
    assert {s["type"] for s in l2.samplers if s} >= {"uniform", "adaptive"}
    assert l2.losses and l2.losses[0]["type"] == "loi"
    assert all(not (s.pixel and s.denoiser) for s in l2.grid())  # a denoiser needs full images
    assert all(not s.pixel for s in l2.loss_variants(l2.grid()))  # LOI compares whole images
    loi = enumerate_space({"spp": 2, "loss": {"type": "loi"}}, scene, LOSSES["loi"](), True, quick=True)
    assert not any(s and s["type"] in ("uniform", "loss", "adaptive") for s in loi.samplers) and loi.losses == []
    clipped = enumerate_space({"spp": 2}, scene, LOSSES["l2"](), False, quick=True)
    assert not any(s and s["type"] == "adaptive" for s in clipped.samplers)
    own = enumerate_space({"spp": 2, "loss": object()}, scene, LOSSES["l2"](), True, quick=True)
    assert own.losses == []  # a user's own loss class is not replaced
    assert 2 in l2.spps and l2.base == Setting(2)


def test_pixel_sampling_is_left_out_for_a_projective_integrator():
    """A shape config renders through direct_projective, whose boundary terms render_pixels does not
    restrict to pixels: each pixel sampler was a failed row of the table (a TypeError) instead."""
    scene = torchir.Scene.builtin("painting", resolution=16, override_integrator={"type": "direct_projective"})
    space = enumerate_space({"spp": 2, "loss": "l2"}, scene, LOSSES["l2"](), True, quick=True)
    assert not any(s and s["type"] in ("uniform", "loss", "adaptive") for s in space.samplers)
    assert any(n.startswith("pixel sampling: left out") and "DirectProjectiveIntegrator" in n for n in space.notes), space.notes


def test_spp_grad_keeps_its_proportion():
    scene = torchir.Scene.builtin("painting", resolution=16)
    space = enumerate_space({"spp": 4, "spp_grad": 8}, scene, LOSSES["l2"](), True, quick=True)
    assert space.setting(16).spp_grad == 32 and space.base.spp_grad == 8


# ------------------------------------------------------------------------------ configs
def test_read_config_without_logger_or_data(tiny):
    user = read_config(tiny)
    assert user.data == {} and user.max_steps == 50 and user.model["spp"] == 4


def test_read_config_resolves_paths_and_class_paths(tmp_path):
    path = tmp_path / "sub" / "run.yaml"
    path.parent.mkdir()
    path.write_text("model:\n  scene: scene.xml\n  loss: {class_path: torchir.modules.L1Loss}\n"
                    "data:\n  targets: [photo.exr]\n")
    user = read_config(path)
    assert user.model["scene"] == str(path.parent.resolve() / "scene.xml")
    assert user.data["targets"] == [str(path.parent.resolve() / "photo.exr")]
    assert type(user.model["loss"]).__name__ == "L1Loss" and user.max_steps == 100


@pytest.mark.parametrize("text, message", [
    ("model: [1, 2", "not valid YAML"),
    ("trainer: {max_steps: 3}\n", "no 'model' section"),
    ("model: {scene: painting, sppp: 4}\n", "unknown model key(s) ['sppp']"),
])
def test_bad_configs_are_reported(tmp_path, capsys, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    assert cli.main(["tune", str(path)]) == 1
    assert message in capsys.readouterr().err


def test_missing_config_is_reported(tmp_path, capsys):
    assert cli.main(["tune", str(tmp_path / "nope.yaml")]) == 1
    assert "config not found" in capsys.readouterr().err


def test_write_tuned_sets_and_removes_keys(tiny):
    user = read_config(tiny)
    user.raw["model"]["denoiser"] = {"type": "target_aware"}
    path = write_tuned(user, {"spp": 16, "sampler": {"type": "restir", "preset": "restir"}, "denoiser": None}, "tuned\nhere")
    assert path == tuned_path(tiny) == tiny.with_name("run.tuned.yaml")
    text = path.read_text()
    assert text.startswith("# tuned\n# here\n# a tiny painting run")
    raw = yaml.safe_load(text)
    assert raw["model"]["spp"] == 16 and raw["model"]["sampler"] == {"type": "restir", "preset": "restir"}
    assert "denoiser" not in raw["model"] and raw["trainer"] == {"max_steps": 50} and raw["model"]["lr"] == 0.02
    with pytest.raises(ValueError):
        write_tuned(user, {"lr": 1.0}, "")


# --------------------------------------------------------------------------- real runs
def test_tune_command_writes_the_table_results_plot_and_a_tuned_config_that_loads(tiny, capsys):
    """``torchir tune CONFIG --quick`` on a 16x16 painting (no logger, no data section): the
    outputs exist, the tuned config differs from the original in the chosen keys and builds
    through the same parser as ``torchir fit``."""
    from torchir.training import InverseRenderingModule, ViewDataModule
    from torchir.training.cli import TorchirCLI, quiet_lightning

    assert cli.main(["tune", str(tiny), "--quick", "--budget", "120"]) == 0
    printed = capsys.readouterr().out
    out = tiny.with_name("run_tune")
    assert "window error" in printed and "[tune   1]" in printed
    assert {"summary.md", "results.json", "pareto.png"} <= {p.name for p in out.iterdir()}
    results = json.loads((out / "results.json").read_text())
    assert results["stopped_by_budget"] is False
    assert not any("ReSTIR: left out" in n for n in results["space"]["notes"])
    gradient = [t for t in results["trials"] if t["kind"] == "gradient" and t["status"] == "ran"]
    assert len(gradient) >= 5 and all(t["gradient_error"] >= 0 and t["seconds_per_step"] > 0 for t in gradient)
    assert any(t["kind"] == "training" and t["status"] == "ran" for t in results["trials"])
    # on this many-light canvas ReSTIR's gradient is far less noisy than plain rendering's
    rows = {r["setting"]: r for r in results["settings"]}
    assert rows["spp 4 + restir(restir)"]["gradient_error"] < 0.5 * rows["spp 4"]["gradient_error"]
    tuned = tuned_path(tiny)
    changed = {k: v for k, v in results["chosen"]["model"].items() if read_config(tiny).model.get(k) != v}
    assert changed, results["chosen"]  # the plain config is not the best here
    model = read_config(tuned).model
    for key, value in changed.items():
        assert model.get(key) == value
    with quiet_lightning():
        parsed = TorchirCLI(InverseRenderingModule, ViewDataModule, run=False, auto_configure_optimizers=False,
                            args=["--config", str(tuned), "--trainer.logger", "false"])
    assert parsed.model.spp == model["spp"]


def test_a_tiny_budget_stops_early(tiny, tmp_path, capsys):
    from torchir.tune import tune

    out = tmp_path / "out"
    results = tune(tiny, budget=1.0, out=out, quick=True, echo=lambda line: None)
    assert results["stopped_by_budget"] is True
    assert len(results["trials"]) <= 2  # the config's own setting (always measured), then nothing more
    assert results["wall_seconds"] < 1.0 + 30  # the reference, one trial, the outputs
    assert (out / "results.json").is_file() and EFFORTS["quick"].short >= 1


def test_decrease_per_second_compares_the_first_and_last_fifths():
    from torchir.tune.measure import decrease_per_second

    times = [float(t) for t in range(10)]
    assert decrease_per_second(times, [10.0 - t for t in times]) == pytest.approx(1.0)  # a straight line: its slope
    assert decrease_per_second(times, [1.0] * 10) == 0.0
    assert decrease_per_second(times, [t * 2 for t in times]) == pytest.approx(-2.0)  # rising: negative
    assert math.isnan(decrease_per_second([0.0, 1.0], [2.0, 1.0]))  # too few points


def test_rows_merge_each_settings_trials_and_mark_the_front_and_the_choice():
    from torchir.tune.report import setting_rows, table

    a, b, c, d = Setting(4), Setting(16), Setting(4, {"type": "restir", "preset": "auto"}), Setting(4, loss={"type": "loi"})
    def grad(s, steps, error, seconds):
        return {"kind": "gradient", "key": s.key, "setting": s.label(), "status": "ran", "steps": steps,
                "gradient_error": error, "seconds_per_step": seconds}

    trials = [grad(a, 4, 1.0, 0.01), grad(b, 4, 0.6, 0.04), grad(b, 12, 0.5, 0.04),  # b: the longer trial counts
              {"kind": "gradient", "key": c.key, "setting": c.label(), "status": "unavailable", "error": "no such preset"},
              {"kind": "training", "key": d.key, "setting": d.label(), "status": "ran", "metric": "param_error", "steps": 5,
               "decrease_per_second": 0.3, "times": [0.0, 0.1, 0.2, 0.3]},
              {"kind": "training", "key": a.key, "setting": a.label(), "status": "ran", "metric": "param_error", "steps": 9,
               "decrease_per_second": 0.2, "times": [0.0, 0.01]}]
    rows = {r["setting"]: r for r in setting_rows(trials, {s.key: s for s in (a, b, c, d)}, 0.01, b)}
    # rows without a persistent part: the whole error averages out over the optimiser's window of
    # OPTIMISER_WINDOW config steps (0.01 s each): error x sqrt(s/step / (window x 0.01 s))
    window = OPTIMISER_WINDOW * 0.01
    assert rows["spp 16"]["steps"] == 12 and rows["spp 16"]["window_error"] == pytest.approx(0.5 * math.sqrt(0.04 / window))
    assert rows["spp 4"]["window_error"] == pytest.approx(math.sqrt(0.01 / window)) and rows["spp 4"]["decrease_per_second"] == 0.2
    assert rows["spp 4"]["pareto"] and not rows["spp 16"]["pareto"]  # slower and no better at equal time
    assert rows["spp 16"]["chosen"] and not rows["spp 4"]["chosen"]
    assert rows["spp 4 + restir(auto)"]["status"] == "unavailable"
    assert rows["spp 4 + loss loi"]["seconds_per_step"] == pytest.approx(0.1) and "window_error" not in rows["spp 4 + loss loi"]
    text = "\n".join(table(list(rows.values())))
    assert "**spp 16**" in text and "unavailable: no such preset" in text and "training score only" in text
    assert "param RMSE decrease/s" in text and "screened only" in text
