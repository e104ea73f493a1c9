"""TUM RGB-D trajectory of a rendered sequence: ``groundtruth.txt`` with the ground-truth poses.

One line per rendered frame, ``timestamp tx ty tz qx qy qz qw``: time in seconds (the frame's
``timestamp`` in ``metadata/render.json``), the camera-to-world pose as the camera centre (metres,
world RAS+) and the unit quaternion of the camera-to-world rotation (Hamilton, scalar **last**,
written with ``qw >= 0``), OpenCV camera frame (x right, y down, z forward); ``#`` lines are
comments.  The text is :func:`room_pipeline.io.tum.tum_text` (the same writer as the
planned trajectory's ``metadata/trajectory_tum.txt``): 6 decimals for time, 9 for positions and
quaternion components (nanometres; rotations to about 1e-9 rad).  Tools such as ``evo``
(``evo_traj tum groundtruth.txt``) read it as is.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.atomic import write_text
from ..io.tum import parse_tum, tum_text
from ..dataset.reader import SequenceReader

FILE_NAME = "groundtruth.txt"


def write_tum(reader: SequenceReader, out_dir: Path) -> dict[str, Any]:
    """Write ``groundtruth.txt`` of ``reader``'s rendered frames into ``out_dir``."""
    write_text(Path(out_dir) / FILE_NAME, tum_text(reader.timestamps, reader.poses))
    return {"trajectory": FILE_NAME, "poses": len(reader)}


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,) s, camera-to-world poses (N, 4, 4)) of a TUM trajectory file (or its export folder)."""
    p = Path(path)
    if p.is_dir():
        p = p / FILE_NAME
    if not p.is_file():
        raise InputError(f"TUM trajectory not found: {p}")
    return parse_tum(p.read_text(encoding="utf-8"))
