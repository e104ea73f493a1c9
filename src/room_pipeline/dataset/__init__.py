"""Loaders of rendered ROOM sequences: a plain-NumPy reader and an optional PyTorch ``Dataset``.

``SequenceReader`` and ``find_sequences`` need only NumPy (and the project's image readers);
``RoomDataset`` (``room_pipeline.dataset.torch_dataset``) needs PyTorch and is imported on first
use, so ``import room_pipeline.dataset`` never imports torch.
"""
from __future__ import annotations

from typing import Any

from .reader import FOLDERS, MODALITIES, SequenceReader, find_sequences, is_sequence

__all__ = ["FOLDERS", "MODALITIES", "SequenceReader", "find_sequences", "is_sequence", "RoomDataset",
           "room_collate"]


def __getattr__(name: str) -> Any:
    if name in ("RoomDataset", "room_collate"):
        from . import torch_dataset

        return getattr(torch_dataset, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
