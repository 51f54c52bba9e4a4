"""What the benchmark suites share: medians that skip missing runs, Markdown tables, timing."""
from __future__ import annotations

import math
import statistics
import time
from collections.abc import Sequence
from typing import Any

__all__ = ["median", "fmt", "markdown_table", "sync_time"]


def median(values: Sequence[float | None]) -> float:
    """The median of the values that are not None or NaN (NaN when none is left)."""
    kept = [v for v in values if v is not None and not math.isnan(v)]
    return float(statistics.median(kept)) if kept else float("nan")


def fmt(value: Any) -> str:
    """A table cell: 3 significant digits, ``-`` for None, ``n/a`` for NaN; ``|`` made safe."""
    if value is None:
        return "-"
    if isinstance(value, float):
        if math.isnan(value):
            return "n/a"
        if math.isinf(value):
            return "inf"
        return f"{value:.3g}" if abs(value) < 1e5 else f"{value:.3e}"
    return str(value).replace("|", "/")  # a "|" inside a cell would split it


def markdown_table(header: list[str], rows: list[list[Any]]) -> list[str]:
    """The lines of a Markdown table (cells through :func:`fmt`)."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]]


def sync_time() -> float:
    """``time.perf_counter()`` after Dr.Jit's queued kernels finished."""
    import drjit as dr

    dr.sync_thread()
    return time.perf_counter()
