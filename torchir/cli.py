"""The ``torchir`` command line.

``torchir fit --config run.yaml [--trainer.max_steps 50 ...]``: an inverse-rendering run
(LightningCLI, see :mod:`torchir.training.cli`); ``torchir info``: backend, versions and
built-in scenes; ``torchir bench <suite> [--quick]``: benchmarks and their report
(:mod:`torchir.bench`); ``torchir export CKPT [--out DIR]``: a checkpoint's recovered values
(``result.yaml``, textures as EXR) and final images, as a run writes them at its end;
``torchir tune CONFIG [--budget S] [--out DIR] [--full] [--quick]``: the speed/accuracy trade of
the techniques that apply to a config, measured, and ``<stem>.tuned.yaml`` beside it
(:mod:`torchir.tune`).
"""
from __future__ import annotations

import argparse
import sys


def _info(_: argparse.Namespace) -> int:
    import torch

    import torchir

    print(f"torchir {torchir.__version__}  torch {torch.__version__}  {torchir.backend.describe()}")
    print("built-in scenes:")
    scenes = torchir.scenes.available()
    width = max(map(len, scenes))
    for name, description in scenes.items():
        print(f"  {name:{width}s}  {description}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from .training import InverseRenderingModule
    from .training.results import write_results

    path = Path(args.checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {str(path)!r}")
    step = int(torch.load(path, map_location="cpu", weights_only=False).get("global_step", 0))
    module = InverseRenderingModule.load_from_checkpoint(path, map_location="cpu", preview_spp=args.spp)
    out = Path(args.out) if args.out else path.parent.parent / "export"
    result = write_results(module, out, step, images=not args.no_images)
    print(f"[torchir] step {step}: {result}" + ("" if args.no_images else f" and {out / 'images'}"))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .bench import run_suites

    runs = run_suites(args.suites, args.quick, Path(args.out), args.suite_options)
    return 0 if all(r["exit_code"] == 0 for r in runs) else 1


def _tune(args: argparse.Namespace) -> int:
    from .tune import tune

    tune(args.config, budget=args.budget, out=args.out, full=args.full, quick=args.quick)
    return 0


LIGHTNING_COMMANDS = ("fit", "validate")


def main(argv: list[str] | None = None) -> int:
    from_command_line = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in LIGHTNING_COMMANDS:
        from .training.cli import main as lightning_main

        return lightning_main(None if from_command_line else argv)  # None: LightningCLI reads sys.argv
    parser = argparse.ArgumentParser(prog="torchir", description="Physics-based inverse rendering from PyTorch.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("info", help="backend, versions and built-in scenes").set_defaults(run=_info)
    from .bench import SUITES

    bench = sub.add_parser("bench", help="speed/accuracy benchmarks of each technique and a report (Markdown + HTML)",
                           epilog="Other options go to the one suite named (torchir bench jpeg --resolution 256; "
                                  "python -m torchir.bench.<suite> --help lists them).")
    bench.add_argument("suites", nargs="+", choices=[*SUITES, "all"], metavar="suite", help=f"one or more of: {', '.join(SUITES)}, all")
    bench.add_argument("--quick", action="store_true", help="a few-minute run of each suite instead of the full one")
    bench.add_argument("--out", default="results/bench", help="report folder (default results/bench)")
    bench.set_defaults(run=_bench)
    export = sub.add_parser("export", help="recovered values (result.yaml, textures as EXR) and final images of a checkpoint")
    export.add_argument("checkpoint", help="a .ckpt file written by torchir fit")
    export.add_argument("--out", default=None, help="output folder (default: <run folder>/export)")
    export.add_argument("--spp", type=int, default=64, help="samples per pixel of the final images (default 64)")
    export.add_argument("--no-images", action="store_true", help="write result.yaml and parameter files only")
    export.set_defaults(run=_export)
    tune = sub.add_parser("tune", help="measure the speed/accuracy trade of the techniques that apply to a config and "
                                       "write <stem>.tuned.yaml beside it")
    tune.add_argument("config", help="a torchir fit config (YAML)")
    tune.add_argument("--budget", type=float, default=600.0, help="seconds for the whole search (default 600); it stops "
                                                                  "there and keeps the best measured so far")
    tune.add_argument("--out", default=None, help="output folder (default: <config dir>/<config stem>_tune)")
    tune.add_argument("--full", action="store_true", help="measure the whole grid of settings (slow), not the default search")
    tune.add_argument("--quick", action="store_true", help="fewer options per setting and shorter trials")
    tune.set_defaults(run=_tune)
    for command in LIGHTNING_COMMANDS:
        sub.add_parser(command, help=f"Lightning {command} of an inverse-rendering run (--config run.yaml)", add_help=False)
    args, extra = parser.parse_known_args(argv)
    if extra and args.command != "bench":
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.command == "bench":  # the rest goes to the suite: torchir bench jpeg --resolution 256
        if extra and len(args.suites) != 1:
            parser.error(f"suite options ({' '.join(extra)}) need exactly one suite, got {' '.join(args.suites)}")
        args.suite_options = extra
    try:
        return args.run(args)
    except (RuntimeError, FileNotFoundError, ValueError) as error:  # e.g. LLVMError: a message, not a traceback
        print(f"torchir: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
