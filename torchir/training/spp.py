"""Samples per pixel by step: ``model.spp`` as a number or a schedule ``{spp: first step}``.

Mitsuba's volume tutorial renders with 8 spp on its 16³ grid and with 64 once the grid is
upsampled to 64³; ``spp: {8: 0, 64: 100}`` says the same (8 spp from step 0, 64 from step 100),
written like a grid's ``resolution`` schedule (``{value: first step}``).
"""
from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Union

__all__ = ["SppSchedule"]

SppSpec = Union[int, Mapping[int, int]]


@dataclass(frozen=True)
class SppSchedule:
    """Checked stages ``((first step, spp), ...)``, first steps strictly increasing from 0."""

    stages: tuple[tuple[int, int], ...]

    @classmethod
    def parse(cls, spec: SppSpec, where: str = "model.spp") -> "SppSchedule":
        """A schedule from a count (``8``) or a mapping ``{spp: first step}`` (``{8: 0, 64: 100}``)."""
        if not isinstance(spec, Mapping):
            return cls(((0, _count(spec, where)),))
        if not spec:
            raise ValueError(f"{where} must be a count >= 1 or a mapping {{spp: first step}}, e.g. {{8: 0, 64: 100}}; got {{}}")
        stages = []
        for spp, first in spec.items():
            count = _count(_as_int(spp), f"{where} (a key of {dict(spec)}: the mapping is {{spp: first step}})")
            if isinstance(first, bool) or not isinstance(first, int) or first < 0:
                raise ValueError(f"{where}: the first step of {count} spp must be an int >= 0, got {first!r} "
                                 f"(the mapping is {{spp: first step}}, e.g. {{8: 0, 64: 100}})")
            stages.append((first, count))
        if stages[0][0] != 0:
            raise ValueError(f"{where}: the first stage must start at step 0, got {dict(spec)} "
                             f"(the mapping is {{spp: first step}}, e.g. {{8: 0, 64: 100}})")
        steps = [first for first, _ in stages]
        if any(b <= a for a, b in zip(steps, steps[1:])):
            raise ValueError(f"{where}: list the stages in the order they are used, with strictly increasing first "
                             f"steps, got {dict(spec)}")
        return cls(tuple(stages))

    def at(self, step: int) -> int:
        """The samples per pixel of optimiser step ``step``."""
        index = bisect.bisect_right([first for first, _ in self.stages], step) - 1
        return self.stages[max(index, 0)][1]

    @property
    def first(self) -> int:
        """The samples per pixel of step 0."""
        return self.stages[0][1]


def _as_int(value: object) -> object:
    """A mapping key as YAML or JSON may give it (``"64"``) as an int; anything else unchanged."""
    if isinstance(value, str) and value.strip().isdigit():
        return int(value)
    return value


def _count(value: object, where: str) -> int:
    from ..functions._args import check_count

    return check_count(where, value)
