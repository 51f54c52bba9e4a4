"""The ``torchir`` command line. ``torchir info``: backend, versions and built-in scenes."""
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="torchir", description="Physics-based inverse rendering from PyTorch.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("info", help="backend, versions and built-in scenes").set_defaults(run=_info)
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except RuntimeError as error:  # e.g. LLVMError: a message, not a traceback
        print(f"torchir: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
