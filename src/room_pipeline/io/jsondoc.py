"""JSON documents: read one, round its floats, replace NaN/inf by null (what every output file needs)."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def read_json(path: str | Path) -> Any:
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


def round_floats(obj: Any, digits: int = 6) -> Any:
    """Round every float in a nested dict (metrics files stay short and diff-able)."""
    if isinstance(obj, dict):
        return {k: round_floats(v, digits) for k, v in obj.items()}
    if isinstance(obj, float):
        return round(obj, digits)
    return obj


def finite(obj: Any) -> Any:
    """Replace NaN/inf by None (JSON has no such numbers)."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
