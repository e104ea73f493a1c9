"""Weight-free depth rows that read nothing but the image (or nothing at all): the trivial baselines and
the endoscope shading baseline.

Trivial, image-blind baselines (all ``scaling = "median"``: one scale per
sequence from the ground-truth median, like every relative row)

``constant``      the same depth everywhere.
``train_mean``    the mean ground-truth depth image of the training patient's training frames
                  (``<output_dir>/<checkpoint_patient>/depth_model/train_mean_depth.npy``, written by
                  ``train_depth``); a patient it was computed on is not scored with it (in-sample).
``tube_prior``    a straight tube of radius a seen along its axis: a ray at image radius rho (in focal
                  units) meets the wall at depth z = a / rho, so depth ~ 1 / max(rho, rho_min).

A method row that does not beat these measures the data's average layout, not the image.

``shading_sfs`` (weight-free endoscope baseline; no renderer metadata)
    The light sits at the camera (a bronchoscope's LEDs flank its lens), so the
    image radiance falls as ``L = rho cos / r^2`` (albedo x power x exposure
    ``rho`` unknown but constant).  Without ``rho`` the distance is known up to one
    scale: ``r ~ sqrt(cos / L)``.  The luma is linearised (inverse sRGB),
    blurred by ``denoise_px`` (sensor noise), started with ``cos = 1`` and refined
    ``iterations`` times by shape from shading: the cosine between the surface
    normal of the current depth map and the viewing ray (the idea LightDepth,
    ICCV 2023, builds on).  Planar depth z = r / |ray|; evaluated median-scaled.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import BackendUnavailable, ConfigError
from .base import Estimator, Frame
from .physics import _rays, camera_cos, srgb8_to_linear

TRAIN_MEAN_FILE = "train_mean_depth.npy"


class ConstantDepth(Estimator):
    scaling = "median"

    def __init__(self, name: str) -> None:
        self.name = name

    def predict(self, frame: Frame) -> np.ndarray:
        h, w = frame.rgb.shape[:2]
        return np.ones((h, w), np.float32)

    def describe(self) -> dict:
        return {"kind": "trivial image-blind baseline: constant depth"}


class TubePrior(Estimator):
    scaling = "median"

    def __init__(self, name: str, rho_min: float = 0.05) -> None:
        self.name, self.rho_min = name, float(rho_min)

    def predict(self, frame: Frame) -> np.ndarray:
        rx, ry, _ = _rays(frame.camera)
        rho = np.sqrt(rx * rx + ry * ry)
        return (1.0 / np.maximum(rho, self.rho_min)).astype(np.float32)

    def describe(self) -> dict:
        return {"kind": "trivial image-blind baseline: straight tube along the optical axis, depth ~ 1/rho",
                "rho_min": self.rho_min}


class TrainMean(Estimator):
    scaling = "median"
    resizes = True

    def __init__(self, name: str, path: Path) -> None:
        self.name, self.path = name, Path(path)
        if not self.path.is_file():
            raise BackendUnavailable(f"train_mean: {self.path} not found (run train_depth first)")
        self.mean = np.load(self.path).astype(np.float32)
        if self.mean.ndim != 2:
            raise BackendUnavailable(f"train_mean: {self.path} is not a 2-D depth image")

    def predict(self, frame: Frame) -> np.ndarray:
        return self.mean

    def describe(self) -> dict:
        return {"kind": "trivial image-blind baseline: mean ground-truth depth image of the training frames",
                "file": str(self.path)}


@dataclasses.dataclass(frozen=True)
class ShadingParams:
    """``depth.shading_sfs`` (see conf/depth/default.yaml)."""

    denoise_px: float = 2.0
    iterations: int = 2
    normal_smoothing_px: float = 3.0
    min_cos: float = 0.1
    dark_floor: float = 1e-4

    def __post_init__(self) -> None:
        if self.denoise_px < 0 or self.iterations < 0 or not 0 < self.min_cos <= 1 or self.dark_floor <= 0:
            raise ConfigError("depth.shading_sfs: denoise_px >= 0, iterations >= 0, 0 < min_cos <= 1 and "
                              "dark_floor > 0 required")
        if self.normal_smoothing_px < 0:
            raise ConfigError("depth.shading_sfs: normal_smoothing_px >= 0 required")


def shading_depth(rgb8: np.ndarray, camera, p: ShadingParams) -> np.ndarray:
    """Relative planar depth (H, W) float32 from one sRGB frame under a co-located light (module docstring)."""
    from scipy.ndimage import gaussian_filter

    lin = srgb8_to_linear(rgb8[..., :3])
    luma = (0.2126 * lin[..., 0] + 0.7152 * lin[..., 1] + 0.0722 * lin[..., 2]).astype(np.float32)
    if p.denoise_px > 0:
        luma = gaussian_filter(luma, p.denoise_px, mode="nearest")
    L = np.maximum(luma, np.float32(p.dark_floor))
    _, _, norm = _rays(camera)
    cos = np.ones_like(L)
    z = np.sqrt(cos / L) / norm
    for _ in range(p.iterations):
        cos = np.clip(camera_cos(z, camera, p.normal_smoothing_px), p.min_cos, 1.0).astype(np.float32)
        z = np.sqrt(cos / L) / norm
    return z.astype(np.float32)


class ShadingSfS(Estimator):
    scaling = "median"

    def __init__(self, name: str, params: ShadingParams) -> None:
        self.name, self.params = name, params

    def predict(self, frame: Frame) -> np.ndarray:
        return shading_depth(frame.rgb, frame.camera, self.params)

    def describe(self) -> dict:
        return {"kind": "weight-free: inverse-square fall-off of a co-located light + shape-from-shading cosine "
                        "refinement; reads only the image and the intrinsics", **dataclasses.asdict(self.params)}
