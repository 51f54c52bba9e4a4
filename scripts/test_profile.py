"""Where the test suite's time goes: compilation, execution and the rest, per file and per test.

Record a run with ``TORCHIR_TEST_PROFILE=DIR`` (tests/conftest.py writes one JSON line per test),
on an empty kernel cache to see what a fresh machine pays::

    rm -rf ~/.drjit && TORCHIR_TEST_PROFILE=/tmp/prof python3 -m pytest -n 2 --dist loadfile
    python3 scripts/test_profile.py /tmp/prof

Kernels whose IR differs only in literal constants are counted as "literal repeats": each is
a value that could be an opaque variable (``dr.opaque``) so that one kernel serves all.
"""
from __future__ import annotations

import argparse
import collections
import glob
import json
import os


def load(folder: str) -> list[dict]:
    rows = []
    for path in sorted(glob.glob(os.path.join(folder, "*.jsonl"))):
        with open(path) as f:
            rows += [json.loads(line) for line in f if line.strip()]
    return rows


def summary(rows: list[dict], top: int = 20) -> str:
    """A text report: totals, files by wall time, the slowest tests, literal repeats."""
    seen: set[int] = set()
    per_file: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0.0, 0.0])
    for row in rows:  # in the order the workers ran them: a shape counts as repeated after its first compile
        entry = per_file[row["test"].split("::")[0]]
        entry[0] += row["wall_s"]
        entry[1] += row["compile_s"]
        entry[2] += row["execution_s"]
        for shape, seconds in row.get("kernels", []):
            if shape in seen:
                entry[3] += seconds
            seen.add(shape)
    total = [sum(v[i] for v in per_file.values()) for i in range(4)]
    lines = [f"{len(rows)} tests: {total[0]:.0f} worker-s, compiling {total[1]:.0f} s (literal repeats {total[3]:.0f} s), "
             f"executing kernels {total[2]:.0f} s", "", f"{'file':<48} {'wall':>7} {'compile':>8} {'repeats':>8} {'exec':>6}"]
    for name, (wall, comp, exe, rep) in sorted(per_file.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"{name:<48} {wall:7.1f} {comp:8.1f} {rep:8.1f} {exe:6.1f}")
    lines += ["", f"{'test':<90} {'wall':>7} {'compile':>8}"]
    for row in sorted(rows, key=lambda r: -r["wall_s"])[:top]:
        lines.append(f"{row['test'][:90]:<90} {row['wall_s']:7.1f} {row['compile_s']:8.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="the TORCHIR_TEST_PROFILE folder of a run")
    parser.add_argument("--top", type=int, default=20, help="rows per table")
    args = parser.parse_args(argv)
    report = summary(load(args.folder), args.top)
    print(report)
    return report


if __name__ == "__main__":
    main()
