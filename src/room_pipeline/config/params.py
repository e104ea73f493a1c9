"""Building a parameter dataclass from a config section, with one-line errors."""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from ..errors import ConfigError


def params_from_dict(cls, d: Mapping[str, Any] | None, section: str):
    """``cls(**d)`` for a dataclass whose field names are the keys of ``conf/<section>/*.yaml``.

    Unknown keys and values of the wrong type (judged by each field's default: bool, int, float, str)
    raise :class:`ConfigError` naming ``section.key``; other fields (None defaults, lists) pass as
    given, and the dataclass's own ``__post_init__`` checks ranges.
    """
    d = dict(d or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ConfigError(f"unknown key '{section}.{unknown[0]}' (allowed: {', '.join(fields)})")
    kw = {}
    for name, value in d.items():
        default = fields[name].default
        try:
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise TypeError
                kw[name] = value
            elif isinstance(default, int):
                if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                    raise TypeError
                kw[name] = int(value)
            elif isinstance(default, float):
                if isinstance(value, bool):
                    raise TypeError
                kw[name] = float(value)
            elif isinstance(default, str):
                if not isinstance(value, str):
                    raise TypeError
                kw[name] = value
            else:
                kw[name] = tuple(value) if isinstance(value, list) else value
        except (TypeError, ValueError):
            raise ConfigError(f"{section}.{name}: expected {type(default).__name__}, got {value!r}") from None
    return cls(**kw)
