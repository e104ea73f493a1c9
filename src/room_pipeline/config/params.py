"""Building a parameter dataclass from a config section, with one-line errors."""
from __future__ import annotations

import dataclasses
import functools
import numbers
import types
import typing
from typing import Any, Mapping

from ..errors import ConfigError

_SCALARS = (bool, int, float, str)


@functools.lru_cache(maxsize=None)
def _hints(cls) -> dict:
    """The resolved field annotations of ``cls`` (``{}`` when one of them cannot be resolved)."""
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 (a name only imported for type checking: judge by defaults alone)
        return {}


def field_kind(cls, f: dataclasses.Field) -> tuple[type | None, bool]:
    """(scalar type the value is checked and coerced to, or None: passed as given; whether null is allowed).

    The scalar type is the default's type (bool, int, float, str); for a ``None`` default it is ``X`` of an
    ``X | None`` (``Optional[X]``) annotation with ``X`` one of those.  Null is allowed when the default is
    ``None`` or the annotation is ``X | None`` (e.g. ``refine_hu: float | None = -500.0``).
    """
    hint = _hints(cls).get(f.name)
    nullable, inner = False, hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        rest = [a for a in args if a is not type(None)]
        if len(rest) < len(args):
            nullable, inner = True, (rest[0] if len(rest) == 1 else None)
    default = f.default
    if default is None:
        return (inner if inner in _SCALARS else None), True
    for kind in _SCALARS:                 # bool before int: a bool is an int
        if isinstance(default, kind):
            return kind, nullable
    return None, nullable


def _coerce(kind: type, value: Any) -> Any:
    if kind is bool or kind is str:
        if not isinstance(value, kind):
            raise TypeError
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError
    if kind is int:
        if float(value) != int(value):
            raise TypeError
        return int(value)
    return float(value)


def params_from_dict(cls, d: Mapping[str, Any] | None, section: str):
    """``cls(**d)`` for a dataclass whose field names are the keys of ``conf/<section>/*.yaml``.

    Unknown keys and values of the wrong type raise :class:`ConfigError` naming ``section.key``: a field
    whose default is a bool, int, float or str (or whose default is None and annotation ``X | None`` with X
    one of those) takes only that type (a real number for int and float fields, an integral one for int; a
    number is converted to the field's type, an int to float); ``None`` only where the default is None or
    the annotation allows it (:func:`field_kind`).  Other fields (lists, mappings, None) pass as given, a list
    as a tuple; the dataclass's own ``__post_init__`` checks ranges.
    """
    d = dict(d or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields), key=str)
    if unknown:
        raise ConfigError(f"unknown key '{section}.{unknown[0]}' (allowed: {', '.join(fields)})")
    kw = {}
    for name, value in d.items():
        kind, nullable = field_kind(cls, fields[name])
        try:
            if value is None:
                if kind is not None and not nullable:
                    raise TypeError
                kw[name] = None
            elif kind is not None:
                kw[name] = _coerce(kind, value)
            else:
                kw[name] = tuple(value) if isinstance(value, list) else value
        except (TypeError, ValueError, OverflowError):
            want = (kind.__name__ if kind is not None else "a value") + (" or null" if nullable else "")
            raise ConfigError(f"{section}.{name}: expected {want}, got {value!r}") from None
    return cls(**kw)
