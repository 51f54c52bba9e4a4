"""Config mappings of the form ``{type: kind, **options}`` (a rig, a derived parameter, a
parametrization), split with one set of error messages."""
from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any


def split_typed(spec: Any, kinds: Collection[str], where: str, form: str,
                not_mapping: type[Exception] = ValueError, mapping: type = Mapping) -> tuple[str, dict[str, Any]]:
    """``(kind, options)`` of ``spec``, a ``mapping`` whose ``type`` is one of ``kinds``.

    ``where`` names the config entry and ``form`` shows its expected shape in the messages; a
    ``spec`` that is not a ``mapping`` raises ``not_mapping``, an unknown type ``ValueError``."""
    if not isinstance(spec, mapping):
        raise not_mapping(f"{where} must be a mapping {form}, got {spec!r}")
    options = dict(spec)
    kind = options.pop("type", None)
    if kind not in kinds:
        raise ValueError(f"{where}.type must be one of {sorted(kinds)}, got {kind!r}")
    return kind, options
