#!/usr/bin/env python
"""Give Dr.Jit custom ops back their ``eval`` signature in mutmut's mutated copy of a file.

``dr.custom`` maps a ``CustomOp.eval``'s argument names from its code object; mutmut wraps every
method as ``(*args, **kwargs)``, so the op's gradients silently come back as zero and every test
of it fails. For each class of FILE (the original, under the repository) whose ``eval`` mutmut
wrapped, the mutated copy DIR/mutants/FILE gets an ``eval`` with the original's parameters that
forwards to the wrapped one (renamed ``_mutmut_eval``). Used by ``scripts/mutation.sh``.

Usage: mutmut_eval_shim.py DIR FILE
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path


def eval_signatures(source: str) -> dict[str, list[str]]:
    """Class name -> parameter names (after ``self``) of its ``eval`` method."""
    out = {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name == "eval":
                    out[node.name] = [a.arg for a in item.args.args[1:]]
    return out


def patch(mutated: str, signatures: dict[str, list[str]]) -> tuple[str, list[str]]:
    done = []
    for cls, params in signatures.items():
        deco = f"    @_mutmut_mutated(mutants_xǁ{cls}ǁeval__mutmut)\n    def eval("
        if mutated.count(deco) != 1:
            continue
        args = ", ".join(params)
        shim = (f"    def eval(self, {args}):  # mutmut_eval_shim: dr.custom reads eval's argument names\n"
                f"        return self._mutmut_eval({args})\n\n"
                f"    @_mutmut_mutated(mutants_xǁ{cls}ǁeval__mutmut)\n    def _mutmut_eval(")
        mutated = mutated.replace(deco, shim)
        done.append(cls)
    return mutated, done


def main(argv: list[str]) -> int:
    workdir, file = Path(argv[0]), argv[1]
    target = workdir / "mutants" / file
    if not target.exists():
        print(f"mutmut_eval_shim: {target} not generated", file=sys.stderr)
        return 1
    text, done = patch(target.read_text(), eval_signatures((workdir / file).read_text()))
    target.write_text(text)
    print(f"mutmut_eval_shim: {file}: {', '.join(done) or 'nothing to patch'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
