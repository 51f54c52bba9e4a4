"""The ``torchir`` command line.

``torchir fit --config run.yaml [--trainer.max_steps 50 ...]``: an inverse-rendering run
(LightningCLI, see :mod:`torchir.training.cli`); ``torchir info``: backend, versions and
built-in scenes; ``torchir bench <suite> [--quick]``: benchmarks and their report
(:mod:`torchir.bench`).
"""
from __future__ import annotations

import argparse
import sys


def _info(_: argparse.Namespace) -> int:
    import torch

    import torchir

    print(f"torchir {torchir.__version__}  torch {torch.__version__}  {torchir.backend.describe()}")
    print("built-in scenes:")
    for name, description in torchir.scenes.available().items():
        print(f"  {name:12s} {description}")
    return 0


def _bench(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .bench import run_suites

    runs = run_suites(args.suites, args.quick, Path(args.out))
    return 0 if all(r["exit_code"] == 0 for r in runs) else 1


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

    bench = sub.add_parser("bench", help="speed/accuracy benchmarks of each technique and a report (Markdown + HTML)")
    bench.add_argument("suites", nargs="+", choices=[*SUITES, "all"], metavar="suite", help=f"one or more of: {', '.join(SUITES)}, all")
    bench.add_argument("--quick", action="store_true", help="a few-minute run of each suite instead of the full one")
    bench.add_argument("--out", default="results/bench", help="report folder (default results/bench)")
    bench.set_defaults(run=_bench)
    for command in LIGHTNING_COMMANDS:
        sub.add_parser(command, help=f"Lightning {command} of an inverse-rendering run (--config run.yaml)", add_help=False)
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except RuntimeError as error:  # e.g. LLVMError: a message, not a traceback
        print(f"torchir: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
