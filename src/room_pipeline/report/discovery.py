"""Which patients and sequences a dataset folder holds (the report's view of the layout).

A sequence here is any folder with ``metadata/`` (planned or simulated only, too: the summary counts their
frames); the rendered frames themselves are read through :class:`room_pipeline.dataset.reader.SequenceReader`
(:mod:`.sections`), whose :func:`~room_pipeline.dataset.reader.is_sequence` needs ``metadata/render.json``.
"""
from __future__ import annotations

from pathlib import Path

from ..catalog import METADATA
from .options import MARKERS


def find_patients(output_dir: Path) -> list[Path]:
    """Patient folders under ``output_dir`` (sorted): those with metrics/, anatomy/, input/,
    ground_truth/ or a sequence folder (a sub-folder holding ``metadata/``)."""
    out = []
    for d in sorted(p for p in Path(output_dir).iterdir() if p.is_dir() and not p.name.startswith(".")):
        if any((d / m).is_dir() for m in MARKERS) or find_sequence_dirs(d):
            out.append(d)
    return out


def find_sequence_dirs(patient: Path) -> list[Path]:
    """Sequence folders of a patient (sorted): sub-folders holding ``metadata/``."""
    return sorted(p for p in Path(patient).iterdir()
                  if p.is_dir() and not p.name.startswith(".") and (p / METADATA).is_dir())
