"""Progress bars: on for a terminal or ROOM_PROGRESS=1, quiet in CI / pipes, never change what is iterated."""
from __future__ import annotations

import io
import sys

from room_pipeline import progress as pg


def test_quiet_when_not_a_terminal(monkeypatch):
    monkeypatch.delenv("ROOM_PROGRESS", raising=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not pg.enabled()
    items = [1, 2, 3]
    assert pg.progress(items, 3, "x") is items


def test_ci_and_explicit_switches(monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    monkeypatch.setenv("CI", "true")
    monkeypatch.delenv("ROOM_PROGRESS", raising=False)
    assert not pg.enabled()
    monkeypatch.setenv("ROOM_PROGRESS", "1")
    assert pg.enabled()
    monkeypatch.setenv("ROOM_PROGRESS", "off")
    assert not pg.enabled()


def test_bar_yields_the_same_items(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setenv("ROOM_PROGRESS", "1")
    assert list(pg.progress(range(5), 5, "frames")) == [0, 1, 2, 3, 4]
    assert "frames" in err.getvalue()
