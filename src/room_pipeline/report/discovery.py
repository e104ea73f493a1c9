"""Which patients and rendered sequences a dataset folder holds (the report's view of the layout).

Through the dataset reader: a sequence is what :func:`room_pipeline.dataset.reader.find_sequences` finds, a
*rendered* one (``metadata/render.json``, :meth:`room_pipeline.catalog.SequencePaths.is_rendered`); a folder
that is planned or simulated only is not listed (the report shows what a user of the dataset can read).
"""
from __future__ import annotations

from pathlib import Path

from ..dataset.reader import find_sequences
from .options import MARKERS


def find_patients(output_dir: Path) -> list[Path]:
    """Patient folders under ``output_dir`` (sorted): those with metrics/, anatomy/, input/,
    ground_truth/ or a rendered sequence."""
    out = []
    for d in sorted(p for p in Path(output_dir).iterdir() if p.is_dir() and not p.name.startswith(".")):
        if any((d / m).is_dir() for m in MARKERS) or find_sequence_dirs(d):
            out.append(d)
    return out


def find_sequence_dirs(patient: Path) -> list[Path]:
    """The rendered sequence folders of a patient folder (sorted; :func:`~room_pipeline.dataset.reader.find_sequences`
    keeps only its direct sub-folders here)."""
    patient = Path(patient)
    return [s for s in find_sequences(patient) if s.parent == patient]
