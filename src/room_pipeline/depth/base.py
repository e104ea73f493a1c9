"""The depth estimators' interface: what every estimator takes and returns.

The lowest layer of :mod:`room_pipeline.depth`: :mod:`.estimators` (the registry
and evaluation loop) and every estimator module (:mod:`.cnn`, :mod:`.hf`,
:mod:`.external`, :mod:`.baselines`) import it, and it imports none of them.
Depth maps are (H, W) float32 metres, planar z, 0 = no prediction.
"""
from __future__ import annotations

import abc
import dataclasses
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..render.camera import CameraIntrinsics

#: how an estimator's depth is put in metres: as is, or scaled by median(gt) / median(pred) per sequence
SCALINGS = ("metric", "median")


@dataclasses.dataclass(frozen=True)
class Frame:
    """One input frame: (H, W, 3) uint8 sRGB, the camera, the frame index in its sequence."""

    rgb: np.ndarray
    camera: CameraIntrinsics
    index: int = 0


@dataclasses.dataclass(frozen=True)
class SequenceInfo:
    """What an estimator may know about a sequence besides its frames (never the ground truth).

    root: the sequence folder (None for loose image sets); renderer: the
    ``metadata/render.json`` "renderer" block (None when not rendered by us).
    """

    camera: CameraIntrinsics
    root: Path | None = None
    patient: str | None = None
    sequence: str | None = None
    renderer: Mapping[str, Any] | None = None
    output_dir: Path | None = None


class Estimator(abc.ABC):
    """Base class: ``name``, ``scaling`` ('metric' | 'median'), ``resizes`` and :meth:`predict`."""

    name: str = ""
    scaling: str = "median"
    resizes: bool = False

    @abc.abstractmethod
    def predict(self, frame: Frame) -> np.ndarray:
        """(H, W) float32 depth (see the module docstring)."""

    def describe(self) -> dict:
        """Provenance written next to the numbers (model, weights, settings)."""
        return {}

    def close(self) -> None:
        """Release resources (models, processes)."""


@dataclasses.dataclass(frozen=True)
class Sample:
    """One evaluation frame, loaded lazily: ``group`` is the unit of median scaling (a sequence)."""

    group: str
    index: int
    name: str
    camera: CameraIntrinsics
    load_rgb: Callable[[], np.ndarray]
    load_gt: Callable[[], np.ndarray]
