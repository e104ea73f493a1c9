"""What every camera-pose method of :mod:`~room_pipeline.evaluate.pose_methods` shares: the parameters of
each (``evaluate.pose`` config), the result record (camera-to-world poses, NaN where unregistered), the
interface, the input checks and the grey-image preprocessing (CLAHE, median denoise)."""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Protocol

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError


@dataclasses.dataclass(frozen=True)
class ColmapParams:
    """``evaluate.pose.colmap`` (see conf/evaluate/default.yaml for units)."""

    overlap: int = 5
    quadratic_overlap: bool = False
    max_num_features: int = 4096
    peak_threshold: float = 0.004
    min_keypoints: int = 300
    peak_threshold_min: float = 0.0005
    max_ratio: float = 0.8
    min_num_matches: int = 15
    init_min_tri_angle_deg: float = 4.0
    init_max_forward_motion: float = 0.99
    init_min_num_inliers: int = 50
    min_model_size: int = 3
    num_threads: int = 1
    log_level: int = 3
    preprocess: str = "clahe"        # none | clahe: median-denoise + CLAHE-equalise every frame before SIFT
    clahe_clip: float = 2.0
    clahe_tiles: int = 8
    denoise_px: int = 3              # median filter aperture before CLAHE (odd >= 3; 0 or 1: off)
    threshold_by: str = "matches"    # matches: pick the SIFT threshold with the most verified matches | keypoints
    probe_pairs: int = 6             # consecutive frame pairs (evenly spaced) probed to choose the threshold
    vocab_tree_path: str | None = None   # COLMAP vocabulary tree (.bin) for loop detection; null: no loop detection

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "ColmapParams":
        p = params_from_dict(cls, d, "evaluate.pose.colmap")
        if p.overlap < 1 or p.max_num_features < 8 or p.min_model_size < 2 or p.num_threads < 1:
            raise ConfigError("evaluate.pose.colmap: overlap >= 1, max_num_features >= 8, min_model_size >= 2 "
                              "and num_threads >= 1 required")
        if not 0 <= p.log_level <= 3:
            raise ConfigError("evaluate.pose.colmap.log_level must be 0 (info) .. 3 (fatal only)")
        if p.min_keypoints < 0 or not 0.0 < p.peak_threshold_min <= p.peak_threshold:
            raise ConfigError("evaluate.pose.colmap: min_keypoints >= 0 and 0 < peak_threshold_min <= "
                              "peak_threshold required")
        if not 0.0 < p.max_ratio <= 1.0 or not 0.0 < p.init_max_forward_motion <= 1.0:
            raise ConfigError("evaluate.pose.colmap: max_ratio and init_max_forward_motion must be in (0, 1]")
        _check_pre(p, "evaluate.pose.colmap")
        if p.threshold_by not in ("matches", "keypoints") or p.probe_pairs < 1:
            raise ConfigError("evaluate.pose.colmap: threshold_by must be 'matches' or 'keypoints' and "
                              "probe_pairs >= 1")
        return p


def _check_pre(p, where: str) -> None:
    if p.preprocess not in PREPROCESS or p.clahe_clip <= 0 or p.clahe_tiles < 1 or p.denoise_px < 0:
        raise ConfigError(f"{where}: preprocess must be one of {PREPROCESS}, clahe_clip > 0, clahe_tiles >= 1, "
                          "denoise_px >= 0")


PREPROCESS = ("none", "clahe")


def preprocess_gray(cv2, im: np.ndarray, how: str, clip: float, tiles: int, denoise_px: int) -> np.ndarray:
    """Grey uint8 frame for feature detection: ``none`` = luma only; ``clahe`` = median filter of
    ``denoise_px`` (sensor noise otherwise becomes keypoints that match nothing), then CLAHE (local
    contrast of the smooth, dim mucosa lifted to where a detector sees it)."""
    gray = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    if how == "none":
        return gray
    if denoise_px >= 3:
        gray = cv2.medianBlur(gray, int(denoise_px) | 1)
    return cv2.createCLAHE(clipLimit=float(clip), tileGridSize=(int(tiles), int(tiles))).apply(gray)


@dataclasses.dataclass(frozen=True)
class OrbParams:
    """``evaluate.pose.orb`` (see conf/evaluate/default.yaml for units)."""

    n_features: int = 2000
    fast_threshold: int = 10
    min_keypoints: int = 300
    fast_threshold_min: int = 2
    scale_factor: float = 1.2
    n_levels: int = 8
    ratio: float = 0.8
    ransac_threshold_px: float = 0.5
    ransac_confidence: float = 0.999
    min_matches: int = 15
    min_inliers: int = 12
    max_skips: int = 3

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "OrbParams":
        p = params_from_dict(cls, d, "evaluate.pose.orb")
        if p.min_keypoints < 0 or not 1 <= p.fast_threshold_min <= p.fast_threshold:
            raise ConfigError("evaluate.pose.orb: min_keypoints >= 0 and 1 <= fast_threshold_min <= "
                              "fast_threshold required")
        if (p.n_features < 8 or p.min_matches < 5 or p.min_inliers < 5 or p.max_skips < 0
                or not 0.0 < p.ratio <= 1.0):
            raise ConfigError("evaluate.pose.orb: n_features >= 8, min_matches >= 5, min_inliers >= 5, "
                              "max_skips >= 0 and 0 < ratio <= 1 required")
        if p.ransac_threshold_px <= 0 or not 0.0 < p.ransac_confidence < 1.0 or p.scale_factor <= 1.0:
            raise ConfigError("evaluate.pose.orb: ransac_threshold_px > 0, 0 < ransac_confidence < 1 and "
                              "scale_factor > 1 required")
        return p


@dataclasses.dataclass(frozen=True)
class SiftParams:
    """``evaluate.pose.sift`` (see conf/evaluate/default.yaml for units)."""

    n_features: int = 2000
    contrast_threshold: float = 0.01
    preprocess: str = "clahe"
    clahe_clip: float = 2.0
    clahe_tiles: int = 8
    denoise_px: int = 3
    ratio: float = 0.8
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    min_matches: int = 15
    min_inliers: int = 12
    max_skips: int = 3

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SiftParams":
        p = params_from_dict(cls, d, "evaluate.pose.sift")
        _check_pre(p, "evaluate.pose.sift")
        if (p.n_features < 8 or p.min_matches < 5 or p.min_inliers < 5 or p.max_skips < 0
                or not 0.0 < p.ratio <= 1.0 or p.contrast_threshold <= 0):
            raise ConfigError("evaluate.pose.sift: n_features >= 8, min_matches >= 5, min_inliers >= 5, "
                              "max_skips >= 0, 0 < ratio <= 1 and contrast_threshold > 0 required")
        if p.ransac_threshold_px <= 0 or not 0.0 < p.ransac_confidence < 1.0:
            raise ConfigError("evaluate.pose.sift: ransac_threshold_px > 0 and 0 < ransac_confidence < 1 required")
        return p


@dataclasses.dataclass(frozen=True)
class PoseMethodParams:
    """What every method may read: seed, per-method options and the learned methods' weight paths."""

    seed: int = 0
    colmap: ColmapParams = ColmapParams()
    orb: OrbParams = OrbParams()
    sift: SiftParams = SiftParams()
    weights: Mapping[str, str | None] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class PoseResult:
    """Estimated camera-to-world poses (N, 4, 4; NaN where unregistered), registered mask (N,), seconds."""

    poses_c2w: np.ndarray
    registered: np.ndarray
    seconds: float
    info: dict = dataclasses.field(default_factory=dict)

    @staticmethod
    def empty(n: int, seconds: float, **info: Any) -> "PoseResult":
        return PoseResult(np.full((n, 4, 4), np.nan), np.zeros(n, bool), seconds, dict(info))


class PoseMethod(Protocol):
    name: str

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        """(True, None) when the method can run here, else (False, why)."""

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        """Poses of the frames (see the module docstring)."""


def _check_inputs(images: list[np.ndarray], K: np.ndarray) -> tuple[int, int, np.ndarray]:
    if len(images) == 0:
        raise ValueError("no images")
    h, w = images[0].shape[:2]
    for k, im in enumerate(images):
        if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3 or im.shape[:2] != (h, w):
            raise ValueError(f"image {k}: expected ({h}, {w}, 3) uint8, got {im.shape} {im.dtype}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    return h, w, K
