"""Stage modules stay thin (issue #14): load -> call domain code -> save, each at most 120 lines.

Parameters, labels, renderer combinations, training loops and table building live in the domain
packages (render/, robot/, evaluate/, depth/); a stage module that grows past the bound has taken
domain logic back in.
"""
from __future__ import annotations

from pathlib import Path

import pytest

STAGES = Path(__file__).resolve().parents[1] / "src" / "room_pipeline" / "stages"
MAX_LINES = 120


@pytest.mark.parametrize("path", sorted(STAGES.glob("*.py")), ids=lambda p: p.name)
def test_stage_module_is_at_most_120_lines(path):
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_LINES, f"stages/{path.name}: {n} lines > {MAX_LINES}: move its logic to a domain module"


def test_every_stage_has_a_module():
    from room_pipeline.stages import STAGES as NAMES

    assert {p.stem for p in STAGES.glob("*.py")} >= set(NAMES)
