"""Progress bars for long loops (frames, sequences): shown on an interactive terminal, quiet otherwise.

``ROOM_PROGRESS=1`` forces them on, ``ROOM_PROGRESS=0`` off; by default they are shown only when
stderr is a terminal and ``CI`` is not set, so CI logs and DVC's captured output stay clean.
"""
from __future__ import annotations

import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


def enabled() -> bool:
    flag = os.environ.get("ROOM_PROGRESS", "").strip().lower()
    if flag in ("1", "true", "yes", "on"):
        return True
    if flag in ("0", "false", "no", "off"):
        return False
    return sys.stderr.isatty() and not os.environ.get("CI")


def progress(iterable: Iterable[T], total: int | None = None, desc: str = "") -> Iterator[T] | Iterable[T]:
    """``iterable`` wrapped in a tqdm bar on stderr when :func:`enabled`, else unchanged."""
    if not enabled():
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=False)
