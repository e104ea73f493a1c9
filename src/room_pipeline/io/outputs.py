"""A stage replaces its whole output, and leaves no temporary file behind, whatever stops it.

:func:`stage_outputs` wraps one stage run (``room stage``, what DVC and ``room run`` call):

* at start: the temporary files of :mod:`room_pipeline.io.atomic` (``.<name>.<8 chars>.tmp<suffix>``) left
  at the stage's outputs by a killed run (SIGKILL) are removed, then the outputs themselves (files and
  folders, as DVC does before it runs a stage), and ``<output_dir>/manifest.json``, which no longer
  describes the data: a re-run never mixes generations (20 old frames beside 5 new ones);
* at exit, on success or failure: the temporary files at the outputs are removed again;
* on failure (an error, SIGINT, SIGTERM): the outputs this run wrote are removed too, so a failed stage
  leaves no output file that looks complete;
* SIGTERM raises :class:`Terminated` in the stage's main thread, so the clean-up above runs (SIGINT
  raises ``KeyboardInterrupt`` already).

The temporary files are written next to their target (a rename is atomic only within one file system),
so "the place the stage cleans" is the stage's own outputs: the files, and everything under its output
folders.  Nothing outside them is touched, so stages writing other outputs of the same patient at the
same time (DVC jobs) are safe.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
from pathlib import Path
from typing import Iterable, Iterator

#: temporary files of room_pipeline.io.atomic, and the write probes of execution.ensure_writable
TEMP_RE = re.compile(r"^\.(?P<name>.+)\.[A-Za-z0-9_]{8}\.tmp(?P<suffix>.*)$|^\.room-write-check\.[A-Za-z0-9_]{8}$")


class Terminated(BaseException):
    """SIGTERM reached a stage: unwinds like KeyboardInterrupt, so ``finally`` clean-ups run."""


def is_temp(name: str) -> bool:
    return TEMP_RE.match(name) is not None


def temp_files(outputs: Iterable[str | os.PathLike]) -> list[Path]:
    """Temporary files at ``outputs``: every one under an output folder, and ``.<name>.*.tmp*`` beside a file."""
    found: list[Path] = []
    for out in map(Path, outputs):
        if out.is_dir():
            for dirpath, _, files in os.walk(out):
                found += [Path(dirpath) / f for f in files if is_temp(f)]
        elif out.parent.is_dir():
            prefix = f".{out.name}."
            found += [p for p in out.parent.iterdir() if p.name.startswith(prefix) and is_temp(p.name)]
    return sorted(set(found))


def remove_temp_files(outputs: Iterable[str | os.PathLike]) -> list[Path]:
    removed = []
    for p in temp_files(outputs):
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
    return removed


def remove_outputs(outputs: Iterable[str | os.PathLike]) -> None:
    """Delete each output (file, link or folder tree) when present."""
    for out in map(Path, outputs):
        if out.is_dir() and not out.is_symlink():
            shutil.rmtree(out, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                out.unlink()


#: the interrupting signals this process received (SIGINT through :func:`raise_interrupt`, SIGTERM here):
#: an exception that unwinds after one (e.g. an ``ImportError`` a native module raises when Ctrl-C lands
#: inside its initialisation) is an interruption, not a failure
RECEIVED: list[int] = []


def _raise_terminated(signum, frame) -> None:
    RECEIVED.append(signum)
    raise Terminated(signum)


def raise_interrupt(signum, frame) -> None:
    """SIGINT handler: Python's own (raise ``KeyboardInterrupt``), remembering that the signal came."""
    RECEIVED.append(signum)
    raise KeyboardInterrupt


@contextlib.contextmanager
def stage_outputs(outputs: Iterable[str | os.PathLike], manifest: str | os.PathLike | None = None) -> Iterator[None]:
    """Run a stage that writes ``outputs`` (see the module docstring)."""
    outs = [Path(o) for o in outputs]
    previous = None
    with contextlib.suppress(ValueError):          # not the main thread: leave signals alone
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    ok = False
    try:
        remove_temp_files(outs)
        remove_outputs(outs)
        if manifest is not None:
            remove_outputs([manifest])
        yield
        ok = True
    finally:
        held = {}
        with contextlib.suppress(ValueError):      # a second Ctrl-C / SIGTERM must not cut the clean-up short
            held = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            if not ok:
                remove_outputs(outs)
            remove_temp_files(outs)
        finally:
            for s, h in held.items():
                signal.signal(s, h)
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
