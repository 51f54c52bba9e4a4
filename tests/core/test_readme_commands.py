"""Every command the README or a page of docs/ shows in a code block is run by a test: the
``torchir fit`` and ``torchir export`` lines here, as written (from a fresh working directory, the
docs' own arguments), shortened to a few steps; the rest by the test named for it in
``ELSEWHERE``, or (benchmarks) by the test module of their suite; ``NOT_RUN`` lists the suites
whose quick runs take minutes each and are left to ``torchir bench all --quick``. A command added
to the README or to docs/*.md without a test fails ``test_every_readme_command_has_a_test``.
The README stays a guide (at most ``README_MAX_LINES`` lines), and every relative link in it and
in docs/ points to a file that exists."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch

from torchir import cli

ROOT = Path(__file__).resolve().parents[2]
SHORT = ["--trainer.max_steps", "2", "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]
FIT_HERE = {  # command -> extra arguments that keep it short (beside SHORT)
    "torchir fit --config configs/quickstart.yaml": ["--model.resolution", "8"],
    "torchir fit --config configs/quickstart.yaml --trainer.max_steps 50 --model.lr 0.02": ["--model.resolution", "8"],
    "torchir fit --config configs/painting.yaml --data.targets [photo.exr] --data.views [0]": ["--model.resolution", "8"],
    "torchir fit --config configs/examples/red_wall.yaml": [],
    "torchir fit --config configs/examples/texture.yaml": [],
    "torchir fit --config configs/examples/light.yaml": [],
    "torchir fit --config configs/examples/pose.yaml": [],
}
SEQUENCE = [  # run in this order, in one working directory: each needs the one before
    "torchir fit --config configs/quickstart.yaml",
    "torchir fit --config configs/quickstart.yaml --ckpt_path last",
    "torchir fit --config configs/quickstart.yaml --set red.reflectance.value.init=0.3",
    "torchir export results/quickstart/version_0/checkpoints/last.ckpt",
]
SUITE_TESTS = {  # suite -> the test module that runs it (at a smaller size), under tests/
    "restir": "bench/test_bench_restir", "restir_views": "bench/test_bench_restir",
    "restir_shadow": "bench/test_bench_restir_shadow", "restir_antithetic": "bench/test_bench_restir_antithetic",
    "restir_silhouette": "bench/test_bench_restir_silhouette", "mesh_gradients": "integrators/test_mesh_gradients",
    "combined": "bench/test_bench_combined", "stepcost": "bench/test_bench_stepcost", "scaleup": "bench/test_bench_scaleup",
    "adaptive": "bench/test_bench_adaptive",
}
NOT_RUN = {"overhead", "denoiser", "loi", "soak", "jpeg", "all",  # minutes each: `torchir bench all --quick`, not CI
           "shape_tutorial", "mesh_step", "volume_tutorial"}  # 35-75 s each at --quick; bookkeeping: bench/test_bench_shape, _volume
ELSEWHERE = {  # command -> "module::test" that runs it (the module under tests/)
    "bash scripts/install.sh && torchir fit --config configs/quickstart.yaml":
        "core/test_readme_commands::test_fit_commands_as_the_readme_writes_them",
    "torchir fit --config configs/multiview.yaml --trainer.strategy ddp --trainer.devices 2 --trainer.accelerator cpu":
        "training/test_training_ddp::test_ddp_two_processes_match_one_process",
    "torchir fit --help": "training/test_training_cli::test_fit_help_starts_with_torchir_s_own_flags",
    "torchir fit --config configs/examples/mesh_from_sphere.yaml":
        "training/test_mesh_fit::test_the_recovered_mesh_is_written_as_positions_and_gets_closer_to_the_truth",
    "python3 configs/examples/mesh_from_sphere.py": "training/test_mesh_fit::test_the_shipped_truth_mesh_is_the_factory_s_output",
    "torchir fit --config configs/examples/volume_from_views.yaml":
        "training/test_resolution::test_a_fit_through_a_resize_changes_the_latent_and_the_optimiser_state_at_the_step",
    "torchir tune configs/painting.yaml --quick":
        "training/test_tune::test_tune_command_writes_the_table_results_plot_and_a_tuned_config_that_loads",
}
CI_COMMAND = "bash scripts/install.sh --dev && python3 -m pytest -n 2 --dist loadfile"  # .ci/run runs it


README_MAX_LINES = 250
SHELL_FENCES = {"", "bash", "sh", "shell", "console"}  # fenced blocks whose lines are commands


def doc_files() -> list[Path]:
    """The README and every page of docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def doc_commands() -> list[tuple[str, str]]:
    """``(file, command)`` for the commands in the code blocks of the README and docs/*.md:
    indented blocks, and fenced blocks of a shell language (an optional ``$ `` prompt
    dropped); comments dropped, arguments unquoted."""
    out = []
    for path in doc_files():
        fence = None  # the info string of the fenced block we are in, or None
        for line in path.read_text().splitlines():
            stripped = line.strip()
            if stripped.startswith("```"):
                fence = stripped[3:].strip().lower() if fence is None else None
                continue
            if fence is None:
                match = re.match(r"^    ((torchir|python3?|bash) .*)", line)
            elif fence in SHELL_FENCES:
                match = re.match(r"^\s*(?:\$ )?((torchir|python3?|bash) .*)", line)
            else:
                match = None
            if match:
                out.append((path.relative_to(ROOT).as_posix(), " ".join(shlex.split(match.group(1), comments=True))))
    return out


def readme_commands() -> list[str]:
    """The commands in the code blocks of the README and docs/*.md (see :func:`doc_commands`)."""
    return [command for _, command in doc_commands()]


def _bench_command(command: str) -> str | None:
    """The suite a benchmark command runs (``torchir bench S``, ``python3 scripts/bench_S.py``)."""
    words = command.split()
    if words[:2] == ["torchir", "bench"]:
        return words[2]
    match = re.fullmatch(r"scripts/bench_(\w+)\.py", words[1]) if words[0].startswith("python") else None
    return match.group(1) if match else None


def test_every_readme_command_has_a_test():
    """Each command of the README and docs/*.md is run here, or by the test named for it (which
    must exist), or is a benchmark whose suite exists and has a test module (or is listed in
    ``NOT_RUN``); nothing else may appear."""
    from torchir.bench import SUITES

    commands = doc_commands()
    assert len(commands) >= 20  # the parser found the code blocks
    assert {file for file, _ in commands} >= {"README.md"}
    assert CI_COMMAND in (ROOT / ".ci" / "run").read_text()
    for file, command in commands:
        where = f"{file}: {command!r}"
        if command in FIT_HERE or command in SEQUENCE or command == CI_COMMAND:
            continue
        if command in ELSEWHERE:
            module, _, test = ELSEWHERE[command].partition("::")
            assert f"def {test}(" in (ROOT / "tests" / f"{module}.py").read_text(), (where, ELSEWHERE[command])
            continue
        if command == "python3 scripts/restir_chains.py many_lights":
            assert (ROOT / "scripts" / "restir_chains.py").is_file()
            continue
        suite = _bench_command(command)
        assert suite is not None, f"command without a test in {where}"
        assert suite == "all" or suite in SUITES, where
        assert suite in NOT_RUN or (ROOT / "tests" / f"{SUITE_TESTS[suite]}.py").is_file(), where
        if command.startswith("python"):
            assert (ROOT / command.split()[1]).is_file(), where


def test_the_command_parser_reads_indented_and_shell_fenced_blocks(tmp_path, monkeypatch):
    """Indented blocks and ``bash``/``sh``/``console`` fences count; a ``python`` fence's lines
    (even indented ones) and prose do not."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("Run torchir fit --help here.\n\n    torchir fit --help   # a comment\n")
    (tmp_path / "docs" / "a.md").write_text(
        "```bash\n$ torchir bench all --quick\n```\n\n```python\nfor x in y:\n    python3 -m not_a_command\n```\n"
        "\n```console\ntorchir bench loi --quick\n```\n"
    )
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    assert doc_commands() == [
        ("README.md", "torchir fit --help"),
        ("docs/a.md", "torchir bench all --quick"),
        ("docs/a.md", "torchir bench loi --quick"),
    ]


def test_every_registered_command_is_still_shown():
    """The tables name no command that the README and docs/ no longer show (the CI command and
    the ``SEQUENCE`` steps included), so a table cannot keep testing a command nobody reads."""
    shown = set(readme_commands())
    registered = set(FIT_HERE) | set(SEQUENCE) | set(ELSEWHERE) | {CI_COMMAND}
    assert registered <= shown, sorted(registered - shown)


def test_readme_is_a_guide():
    """The README is a guide of at most ``README_MAX_LINES`` lines; the rest lives in docs/,
    whose index links every page."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, at most {README_MAX_LINES}"
    index = (ROOT / "docs" / "index.md").read_text()
    for page in sorted((ROOT / "docs").glob("*.md")):
        if page.name != "index.md":
            assert f"]({page.name})" in index, f"docs/index.md does not link {page.name}"


_LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|^\s*\[[^\]]+\]:\s*(\S+)", re.M)


def _relative_links(text: str) -> list[str]:
    """The link targets of ``[text](target)`` and ``[label]: target`` that are relative paths
    (no scheme, not a bare ``#anchor``), with any ``#anchor`` dropped; code is not searched."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # fenced code
    text = re.sub(r"`[^`\n]*`", "", text)  # inline code
    out = []
    for match in _LINK.finditer(text):
        target = match.group(1) or match.group(2)
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("#"):
            continue
        out.append(target.split("#", 1)[0])
    return out


def test_relative_links_point_to_existing_files():
    """Every relative link of the README and docs/*.md names a file (or folder) that exists."""
    checked = 0
    for path in doc_files():
        for target in _relative_links(path.read_text()):
            resolved = (path.parent / target).resolve()
            assert resolved.exists(), f"{path.relative_to(ROOT)} links {target!r}, which does not exist"
            checked += 1
    assert checked >= 10  # the parser found the links


def test_link_parser():
    text = "[a](docs/x.md) [b](https://e.org/y) [c](#top) ![img](p.png) `[d](no.md)` [e](y.md#sec)\n[f]: z.md\n"
    assert _relative_links(text) == ["docs/x.md", "y.md", "z.md"]


def _fit(tmp_path: Path, command: str, *extra: str) -> int:
    words = shlex.split(command)[1:]
    words = [str(ROOT / w) if w.startswith("configs/") else w for w in words]
    if words[0] == "fit":
        words += SHORT
    return cli.main([*words, *extra])


def test_fit_commands_as_the_readme_writes_them(tmp_path, monkeypatch):
    """The quickstart, its resume from the newest ``last.ckpt``, a ``--set`` override and
    ``torchir export`` of the first run, in one fresh working directory."""
    monkeypatch.chdir(tmp_path)
    for command in SEQUENCE:
        extra = ["--model.resolution", "8"] if "fit" in command else []
        if "--ckpt_path last" in command:
            extra += ["--trainer.max_steps", "3"]  # one step past the run it resumes
        assert _fit(tmp_path, command, *extra) == 0, command
    run = tmp_path / "results" / "quickstart"
    assert sorted(p.name for p in run.iterdir()) == ["version_0", "version_1", "version_2"]
    assert (run / "version_0" / "export" / "result.yaml").is_file()


@pytest.mark.parametrize("command", [c for c in FIT_HERE if c not in SEQUENCE])
def test_other_fit_commands_run(tmp_path, monkeypatch, command):
    """Each other ``torchir fit`` line of the README, two steps long; the painting's
    ``photo.exr`` is a stand-in written where the user would keep it."""
    monkeypatch.chdir(tmp_path)
    if "photo.exr" in command:
        from torchir.imageio import write_image

        write_image(tmp_path / "photo.exr", torch.rand(3, 8, 8))
    assert _fit(tmp_path, command, *FIT_HERE[command]) == 0
    assert list((tmp_path / "results").rglob("result.yaml"))
