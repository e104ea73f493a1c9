"""Entry point for external depth models (UniDepth, Metric3D, EndoDAC, BREA-Depth, ...).

Two ways to plug one in, each a ``depth.external.<name>`` config entry (then
list ``<name>`` in ``depth.methods``):

Predictions folder (run the model yourself, anywhere)::

    depth:
      external:
        unidepth:
          folder: predictions/unidepth/{patient}/{sequence}   # {patient}, {sequence}, {output_dir} are filled in
          format: npy        # npy (float array) | exr (float, first channel) | png16 (uint16)
          units: m           # unit of the stored values: m | mm | cm
          png_scale: 1.0     # png16 only: depth = value * png_scale (in `units`)
          output: depth      # depth | disparity (relative inverse depth: 1/value, median-scaled)
          scaling: metric    # metric | median
          resizes: false     # true: maps of another size are resized (bilinear) to the frame; false: error

    The folder holds ``frame_NNNN.<ext>`` named like the sequence's
    ``rgb/frame_NNNN.png``.  A missing folder makes the method *unavailable*
    (reported with the reason); a missing frame inside an existing folder is
    an error naming the file.

A Python callable (the model runs inside the evaluation)::

        metric3d:
          callable: my_adapters.metric3d:predict   # module:function, importable on PYTHONPATH
          kwargs: {variant: vit_small}              # extra keyword arguments
          units: m
          scaling: metric

    called as ``predict(rgb, camera, **kwargs)`` with ``rgb`` an (H, W, 3)
    uint8 sRGB array and ``camera`` the dict of ``calibration/camera_params.json``
    (fx, fy, cx, cy, width, height, ...); it returns an (H, W) array in
    ``units`` (``output``/``scaling`` as above).  An import failure makes the
    method unavailable with the reason.
"""
from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import BackendUnavailable, ConfigError, InputError
from .base import SCALINGS, Estimator, Frame, SequenceInfo

UNITS_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}
FORMATS = {"npy": ".npy", "exr": ".exr", "png16": ".png"}
OUTPUTS = ("depth", "disparity")


@dataclasses.dataclass(frozen=True)
class ExternalSpec:
    """One ``depth.external.<name>`` entry (see the module docstring)."""

    folder: str = ""
    callable: str = ""
    format: str = "npy"
    units: str = "m"
    png_scale: float = 1.0
    output: str = "depth"
    scaling: str = "median"
    resizes: bool = False
    kwargs: Mapping[str, Any] | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, section: str = "depth.external") -> "ExternalSpec":
        p = params_from_dict(cls, d, section)
        if bool(p.folder) == bool(p.callable):
            raise ConfigError(f"{section}: give exactly one of 'folder' and 'callable'")
        if p.callable and ":" not in p.callable:
            raise ConfigError(f"{section}.callable must be 'module:function', got {p.callable!r}")
        if p.format not in FORMATS:
            raise ConfigError(f"{section}.format must be one of {sorted(FORMATS)}, got {p.format!r}")
        if p.units not in UNITS_M:
            raise ConfigError(f"{section}.units must be one of {sorted(UNITS_M)}, got {p.units!r}")
        if p.output not in OUTPUTS or p.scaling not in SCALINGS:
            raise ConfigError(f"{section}: output must be one of {OUTPUTS} and scaling one of {SCALINGS}")
        if p.output == "disparity" and p.scaling == "metric":
            raise ConfigError(f"{section}: a disparity (relative) output cannot be metric")
        if p.png_scale <= 0:
            raise ConfigError(f"{section}.png_scale must be > 0")
        return p


def _to_depth(values: np.ndarray, spec: ExternalSpec, where: str) -> np.ndarray:
    a = np.asarray(values)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"{where}: predicted depth must be (H, W), got shape {a.shape}")
    a = a.astype(np.float64)
    if spec.format == "png16" and spec.folder:
        a = a * spec.png_scale
    if spec.output == "disparity":
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(a > 0, 1.0 / a, np.nan)
        return a.astype(np.float32)
    return (a * UNITS_M[spec.units]).astype(np.float32)


class FolderEstimator(Estimator):
    """Reads ``frame_NNNN.<ext>`` predictions a user put in a folder."""

    def __init__(self, name: str, spec: ExternalSpec, folder: Path) -> None:
        self.name, self.spec, self.folder = name, spec, folder
        self.scaling, self.resizes = spec.scaling, spec.resizes

    def read(self, path: Path) -> np.ndarray:
        if not path.is_file():
            raise InputError(f"{self.name}: prediction {path} is missing (the folder has no file for this frame)")
        if self.spec.format == "npy":
            try:
                return np.load(path, allow_pickle=False)
            except ValueError as exc:
                raise InputError(f"{path}: not a plain .npy array ({exc})") from None
        if self.spec.format == "exr":
            from ..io.images import read_exr

            a = read_exr(path)[0]
            return a if a.ndim == 2 else a[..., 0]
        from ..io.images import read_png

        a = read_png(path)
        if a.dtype != np.uint16:
            raise InputError(f"{path}: png16 expected, got {a.dtype}")
        return a

    def predict(self, frame: Frame) -> np.ndarray:
        path = self.folder / f"frame_{frame.index:04d}{FORMATS[self.spec.format]}"
        return _to_depth(self.read(path), self.spec, str(path))

    def describe(self) -> dict:
        return {"kind": "folder", "folder": str(self.folder), **dataclasses.asdict(self.spec)}


class CallableEstimator(Estimator):
    """Calls ``module:function(rgb, camera, **kwargs)`` for every frame."""

    def __init__(self, name: str, spec: ExternalSpec, fn: Callable[..., Any]) -> None:
        self.name, self.spec, self.fn = name, spec, fn
        self.scaling, self.resizes = spec.scaling, spec.resizes

    def predict(self, frame: Frame) -> np.ndarray:
        out = self.fn(frame.rgb, frame.camera.to_dict(), **dict(self.spec.kwargs or {}))
        return _to_depth(out, self.spec, f"{self.name} ({self.spec.callable})")

    def describe(self) -> dict:
        return {"kind": "callable", **dataclasses.asdict(self.spec)}


def load_callable(target: str) -> Callable[..., Any]:
    """``module:function`` -> the function; BackendUnavailable when it cannot be imported."""
    module, _, attr = target.partition(":")
    try:
        obj: Any = importlib.import_module(module)
    except ImportError as exc:
        raise BackendUnavailable(f"cannot import {module!r} for {target!r}: {exc}") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise BackendUnavailable(f"{module!r} has no {attr!r} (from {target!r})")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ConfigError(f"{target!r} is not callable")
    return obj


def create_external(name: str, spec: ExternalSpec, info: SequenceInfo) -> Estimator:
    if spec.callable:
        return CallableEstimator(name, spec, load_callable(spec.callable))
    try:
        folder = Path(spec.folder.format(patient=info.patient or "", sequence=info.sequence or "",
                                         output_dir=str(info.output_dir or "")))
    except (KeyError, IndexError) as exc:
        raise ConfigError(f"depth.external.{name}.folder: unknown placeholder {exc} "
                          "(allowed: {patient}, {sequence}, {output_dir})") from None
    if not folder.is_dir():
        raise BackendUnavailable(f"{name}: prediction folder {folder} does not exist (fill it with "
                                 f"frame_NNNN{FORMATS[spec.format]} files)")
    return FolderEstimator(name, spec, folder)
