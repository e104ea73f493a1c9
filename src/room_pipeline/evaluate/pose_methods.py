"""Multi-view camera-pose estimators behind one interface, and their registry.

``METHODS[name].estimate(images, K, params) -> PoseResult``: images are
(H, W, 3) uint8 RGB frames of one sequence in order, ``K`` the 3x3 pinhole
matrix in OpenCV's pixel convention (centre of the top-left pixel at (0, 0)),
``params`` a :class:`PoseMethodParams`.  The result holds camera-to-world
poses (N, 4, 4) in an arbitrary world frame and scale (OpenCV camera frame),
NaN for the frames the method could not register, the registered mask and the
wall time.  A method that fails on the data (no texture, too few matches)
returns an empty registration; it does not raise.

Methods
    ``colmap``   COLMAP through pycolmap, run as a careful user would on noisy
                 endoscopy: frames median-denoised and CLAHE-equalised before
                 SIFT, the SIFT peak threshold chosen by verified matches on
                 probe pairs (not keypoint counts), sequential matching (loop
                 detection when a vocabulary tree is configured), incremental
                 mapping with bundle adjustment and the intrinsics fixed to ``K``
                 (PINHOLE camera, never refined); the largest reconstruction is
                 kept.  Single threaded and seeded, so the same images give the
                 same poses.
    ``orb_vo``   Two-frame monocular visual odometry with OpenCV: ORB features,
                 brute-force Hamming matching with Lowe's ratio test, essential
                 matrix by RANSAC (seeded with ``cv2.setRNGSeed``), pose recovery,
                 chained.  Monocular VO has no scale: every step gets a unit
                 translation, so the chained trajectory is right up to one
                 global scale only where the speed is constant; the Sim(3)
                 alignment of the ATE fixes that global scale, and the pairwise
                 metrics use translation directions only.  A frame that cannot
                 be related to the last registered frame is unregistered and the
                 next one is tried against that same frame; after ``max_skips``
                 such frames in a row tracking is lost and a new segment starts
                 (its scale and frame unrelated to the first); the largest
                 segment is returned, like COLMAP's largest reconstruction.
    ``sift_vo``  The same chaining with CLAHE-equalised (median-denoised) SIFT, L2
                 ratio-test matching and the essential matrix by MAGSAC
                 (``cv2.USAC_MAGSAC``) before ``recoverPose``.
    ``identity``, ``constant_forward``
                 Image-blind trivial baselines (:class:`Blind`): what a method must
                 beat before its score says anything about the images.

DUSt3R and VGGT are not offered: their code and weights cannot be installed
here (no network), so an adapter could never be run nor checked; rather than a
row that can never run, there is none (Table I's notes say so).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping, Protocol

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError


# --------------------------------------------------------------------------- parameters


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


# --------------------------------------------------------------------------- ORB visual odometry


class OrbVO:
    """Chained two-frame ORB visual odometry (OpenCV)."""

    name = "orb_vo"

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        return (True, None) if importlib.util.find_spec("cv2") else (False, "OpenCV (cv2) is not installed")

    @staticmethod
    def relative_pose(cv2, f0, f1, K: np.ndarray, p, seed: int, norm: int | None = None,
                      method: int | None = None) -> tuple[np.ndarray | None, str, int]:
        """Camera 1 in camera 0's frame (4x4, unit translation), or None and why; and the pose inliers.

        ``norm``: descriptor distance (Hamming for ORB, L2 for SIFT); ``method``: the robust estimator of
        ``cv2.findEssentialMat`` (RANSAC for ORB, USAC_MAGSAC for SIFT)."""
        norm = cv2.NORM_HAMMING if norm is None else norm
        method = cv2.RANSAC if method is None else method
        (p0, d0), (p1, d1) = f0, f1
        if d0 is None or d1 is None or len(p0) < 2 or len(p1) < 2:
            return None, "few_matches", 0
        good = []
        for m in cv2.BFMatcher(norm).knnMatch(d0, d1, k=2):
            if len(m) == 2 and m[0].distance < p.ratio * m[1].distance:
                good.append((m[0].queryIdx, m[0].trainIdx))
        if len(good) < p.min_matches:
            return None, "few_matches", 0
        q, t = np.array(good).T
        x0, x1 = p0[q], p1[t]
        cv2.setRNGSeed(seed)
        E, mask = cv2.findEssentialMat(x0, x1, K, method=method, prob=p.ransac_confidence,
                                       threshold=p.ransac_threshold_px)
        if E is None or E.ndim != 2 or E.shape[1] != 3 or E.shape[0] < 3:
            return None, "no_essential", 0
        E = E[:3]                                     # several stacked solutions: the first (best) one
        n_in, R, tvec, _ = cv2.recoverPose(E, x0, x1, K, mask=mask)
        if n_in < p.min_inliers or not np.all(np.isfinite(R)) or not np.all(np.isfinite(tvec)):
            return None, "few_inliers", int(n_in)
        # x_1 = R x_0 + t (camera frames), so camera 1 in camera 0 is [R^T, -R^T t]
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ (tvec.reshape(3) / max(float(np.linalg.norm(tvec)), 1e-12))
        return T, "ok", int(n_in)

    def features(self, cv2, images: list[np.ndarray], params: PoseMethodParams) -> tuple[list, dict]:
        p = params.orb
        feats, thresholds = [], []
        for im in images:
            # low-contrast endoscopic images: a fixed FAST threshold finds (almost) nothing on a smooth
            # mucosa until sensor noise lifts corners over it; halve it while too few keypoints are found
            gray, thr = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), p.fast_threshold
            while True:
                orb = cv2.ORB_create(nfeatures=p.n_features, scaleFactor=p.scale_factor, nlevels=p.n_levels,
                                     fastThreshold=thr)
                kp, des = orb.detectAndCompute(gray, None)
                if len(kp) >= p.min_keypoints or thr <= p.fast_threshold_min:
                    break
                thr = max(p.fast_threshold_min, thr // 2)
            thresholds.append(thr)
            feats.append((np.array([k.pt for k in kp], np.float64).reshape(-1, 2), des))
        return feats, {"fast_threshold_median": float(np.median(thresholds)) if thresholds else None}

    def relate(self, cv2, f0, f1, K, params: PoseMethodParams, seed: int):
        return self.relative_pose(cv2, f0, f1, K, params.orb, seed)

    def vo_params(self, params: PoseMethodParams):
        return params.orb

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        """Chain frame k to the last registered frame of the current segment; after ``max_skips`` frames in a
        row that cannot be related to it, tracking is lost and a new segment starts at the current frame (a
        segment's reference that nothing could be chained to is replaced by the next frame).  The largest
        segment (most frames; the earliest on ties) is the result, in its first frame's camera frame."""
        import cv2

        t0, c0 = time.perf_counter(), time.process_time()
        _, _, K = _check_inputs(images, K)
        p = self.vo_params(params)
        n = len(images)
        feats, feat_info = self.features(cv2, images, params)
        steps = {"ok": 0, "few_matches": 0, "no_essential": 0, "few_inliers": 0}
        inliers = []
        segments: list[dict[int, np.ndarray]] = [{0: np.eye(4)}]
        last, misses = 0, 0
        for k in range(1, n):
            T, status, n_in = self.relate(cv2, feats[last], feats[k], K, params, int(params.seed) + k)
            steps[status] += 1
            if T is not None:
                segments[-1][k] = segments[-1][last] @ T
                last, misses = k, 0
                inliers.append(n_in)
                continue
            if len(segments[-1]) == 1:                # nothing chained to the reference yet: k replaces it
                segments[-1] = {k: np.eye(4)}
                last, misses = k, 0
                continue
            misses += 1
            if misses > p.max_skips:                  # tracking lost: start again from frame k
                segments.append({k: np.eye(4)})
                last, misses = k, 0
        best = max(segments, key=len)                 # max() keeps the first of equally long segments
        poses = np.full((n, 4, 4), np.nan)
        reg = np.zeros(n, bool)
        if len(best) >= 2:                            # a lone reference frame is no registration
            for k, T in best.items():
                poses[k] = T
                reg[k] = True
        info = {"steps": steps, "segments": len([s for s in segments if len(s) >= 2]),
                "median_inliers": float(np.median(inliers)) if inliers else 0.0,
                "median_keypoints": float(np.median([len(f[0]) for f in feats])), **feat_info,
                "scale": "unit translation per step (monocular; fixed by the Sim(3) alignment)",
                "cpu_seconds": time.process_time() - c0}
        return PoseResult(poses, reg, time.perf_counter() - t0, info)


class SiftVO(OrbVO):
    """Chained two-frame visual odometry: CLAHE-equalised SIFT, ratio test, essential matrix by MAGSAC
    (``cv2.USAC_MAGSAC``, seeded), ``recoverPose``; the chaining and tracking-loss rules of :class:`OrbVO`."""

    name = "sift_vo"

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        ok, why = super().availability(params)
        if ok:
            import cv2
            if not hasattr(cv2, "SIFT_create") or not hasattr(cv2, "USAC_MAGSAC"):
                return False, "this OpenCV has no SIFT_create / USAC_MAGSAC (OpenCV >= 4.5 needed)"
        return ok, why

    def vo_params(self, params: PoseMethodParams):
        return params.sift

    def features(self, cv2, images: list[np.ndarray], params: PoseMethodParams) -> tuple[list, dict]:
        p = params.sift
        sift = cv2.SIFT_create(nfeatures=p.n_features, contrastThreshold=p.contrast_threshold)
        feats = []
        for im in images:
            gray = preprocess_gray(cv2, im, p.preprocess, p.clahe_clip, p.clahe_tiles, p.denoise_px)
            kp, des = sift.detectAndCompute(gray, None)
            feats.append((np.array([k.pt for k in kp], np.float64).reshape(-1, 2), des))
        return feats, {"preprocess": p.preprocess}

    def relate(self, cv2, f0, f1, K, params: PoseMethodParams, seed: int):
        return self.relative_pose(cv2, f0, f1, K, params.sift, seed, cv2.NORM_L2, cv2.USAC_MAGSAC)


# --------------------------------------------------------------------------- trivial baselines


class Blind:
    """An image-blind trivial baseline: the same poses whatever the frames show.

    ``identity``          every frame at the first frame's pose (no motion at all);
    ``constant_forward``  identity rotation, camera centre moving by one unit per frame along the first
                          frame's optical axis (+z): what an estimator that only knows "the scope advances"
                          would answer.
    A benchmark whose frames these score well on measures the window, not the method."""

    baseline = True

    def __init__(self, name: str) -> None:
        self.name = name

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        return True, None

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        t0 = time.perf_counter()
        n = len(images)
        poses = np.tile(np.eye(4), (n, 1, 1))
        if self.name == "constant_forward":
            poses[:, 2, 3] = np.arange(n, dtype=np.float64)
        return PoseResult(poses, np.ones(n, bool), time.perf_counter() - t0, {"baseline": "trivial, image-blind"})


# --------------------------------------------------------------------------- COLMAP


def _verified_matches(cv2, k0, d0, k1, d1, K: np.ndarray, ratio: float) -> int:
    """Ratio-test matches between two SIFT sets that survive an essential-matrix MAGSAC (1 px), seeded."""
    if d0 is None or d1 is None or len(k0) < 5 or len(k1) < 5:
        return 0
    d0 = np.asarray(getattr(d0, "data", d0), np.float32)
    d1 = np.asarray(getattr(d1, "data", d1), np.float32)
    k0 = np.array([(kp.x, kp.y) for kp in k0], np.float64).reshape(-1, 2)
    k1 = np.array([(kp.x, kp.y) for kp in k1], np.float64).reshape(-1, 2)
    good = [(m[0].queryIdx, m[0].trainIdx) for m in cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
            if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < 5:
        return 0
    q, t = np.array(good).T
    # COLMAP keypoints: pixel-corner origin (centre of the top-left pixel at 0.5); K is OpenCV's (0)
    x0 = k0[q] - 0.5
    x1 = k1[t] - 0.5
    cv2.setRNGSeed(0)
    E, mask = cv2.findEssentialMat(x0, x1, K, method=cv2.USAC_MAGSAC, prob=0.999, threshold=1.0)
    return int(mask.sum()) if E is not None and mask is not None else 0


class Colmap:
    """COLMAP incremental SfM via pycolmap, intrinsics fixed."""

    name = "colmap"

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        return (True, None) if importlib.util.find_spec("pycolmap") else (False, "pycolmap is not installed")

    @staticmethod
    def _options(pycolmap, p: ColmapParams, K: np.ndarray, n: int, seed: int):
        # COLMAP puts the centre of the top-left pixel at (0.5, 0.5); OpenCV at (0, 0)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{fx!r},{fy!r},{cx!r},{cy!r}"
        extract = pycolmap.FeatureExtractionOptions()
        extract.num_threads = p.num_threads
        extract.use_gpu = False
        extract.sift.max_num_features = p.max_num_features
        extract.sift.peak_threshold = p.peak_threshold
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = p.num_threads
        match.use_gpu = False
        match.sift.max_ratio = p.max_ratio
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = p.overlap
        pairing.quadratic_overlap = p.quadratic_overlap
        pairing.num_threads = p.num_threads
        if p.vocab_tree_path:                   # loop detection needs COLMAP's vocabulary tree file
            pairing.loop_detection = True
            pairing.vocab_tree_path = str(p.vocab_tree_path)
        verify = pycolmap.TwoViewGeometryOptions()
        verify.ransac.random_seed = seed
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = p.num_threads
        mapping.random_seed = seed
        mapping.min_num_matches = p.min_num_matches
        mapping.min_model_size = min(p.min_model_size, n)
        mapping.multiple_models = True
        mapping.extract_colors = False
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
        m = mapping.mapper
        m.init_min_tri_angle = p.init_min_tri_angle_deg
        m.init_max_forward_motion = p.init_max_forward_motion
        m.init_min_num_inliers = p.init_min_num_inliers
        m.abs_pose_refine_focal_length = False
        m.abs_pose_refine_extra_params = False
        m.num_threads = p.num_threads
        m.random_seed = seed
        mapping.triangulation.random_seed = seed
        return reader, extract, match, pairing, verify, mapping

    @staticmethod
    def peak_threshold(pycolmap, images: list[np.ndarray], p: ColmapParams, K: np.ndarray | None = None,
                       n_probe: int = 5) -> tuple[float, dict]:
        """SIFT peak threshold for this sequence and how it was chosen.

        ``threshold_by: matches`` (default): every candidate ``peak_threshold * 2^-k`` down to
        ``peak_threshold_min`` is tried on ``probe_pairs`` evenly spaced consecutive frame pairs (of the
        preprocessed frames); the one with the largest median number of verified matches (ratio test, then
        essential-matrix MAGSAC inliers with ``K``) wins, the higher threshold on ties.  Keypoint counts are
        not the criterion: sensor noise gives many keypoints that match nothing.
        ``threshold_by: keypoints``: halved while the median keypoint count of ``n_probe`` frames is under
        ``min_keypoints`` (the old rule)."""
        import cv2

        thr = p.peak_threshold
        cands = [thr]
        while cands[-1] > p.peak_threshold_min:
            cands.append(max(p.peak_threshold_min, 0.5 * cands[-1]))
        opts = pycolmap.FeatureExtractionOptions()
        opts.use_gpu = False
        opts.num_threads = p.num_threads
        opts.sift.max_num_features = p.max_num_features

        def extract(t, grays):
            opts.sift.peak_threshold = t
            sift = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
            return [sift.extract_from_float32_array(np.ascontiguousarray(g)) for g in grays]

        if not images:
            return thr, {"rule": "fixed"}
        if p.threshold_by == "keypoints":
            if p.min_keypoints <= 0:
                return thr, {"rule": "fixed"}
            probe = [images[int(i)] for i in np.unique(np.linspace(0, len(images) - 1, n_probe).round())]
            grays = [(im.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)) / 255.0 for im in probe]
            for t in cands:
                counts = [len(f[0]) for f in extract(t, grays)]
                if np.median(counts) >= p.min_keypoints or t <= p.peak_threshold_min:
                    return t, {"rule": "keypoints", "median_keypoints": float(np.median(counts))}
        if len(images) < 2 or K is None:
            return thr, {"rule": "fixed (fewer than 2 frames)"}
        starts = np.unique(np.linspace(0, len(images) - 2, p.probe_pairs).round().astype(int))
        grays = []
        for k in starts:
            for im in (images[k], images[k + 1]):
                g = preprocess_gray(cv2, im, p.preprocess, p.clahe_clip, p.clahe_tiles, p.denoise_px)
                grays.append(g.astype(np.float32) / 255.0)
        scores = {}
        for t in cands:
            feats = extract(t, grays)
            per_pair = []
            for q in range(0, len(feats), 2):
                (k0, d0), (k1, d1) = feats[q], feats[q + 1]
                per_pair.append(_verified_matches(cv2, k0, d0, k1, d1, K, p.max_ratio))
            scores[t] = float(np.median(per_pair))
        best = max(cands, key=lambda t: (scores[t], t))
        return best, {"rule": "matches", "median_verified_matches": {f"{t:g}": v for t, v in scores.items()}}

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        import pycolmap

        t0, c0 = time.perf_counter(), time.process_time()
        _, _, K = _check_inputs(images, K)
        n = len(images)
        p = params.colmap
        pycolmap.set_random_seed(int(params.seed))
        log_level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = p.log_level
        try:
            thr, thr_info = self.peak_threshold(pycolmap, images, p, K)
            p = dataclasses.replace(p, peak_threshold=thr)
        finally:
            pycolmap.logging.minloglevel = log_level
        import cv2

        if p.preprocess != "none":
            images = [np.repeat(preprocess_gray(cv2, im, p.preprocess, p.clahe_clip, p.clahe_tiles,
                                                p.denoise_px)[..., None], 3, axis=2) for im in images]
        reader, extract, match, pairing, verify, mapping = self._options(pycolmap, p, K, n, int(params.seed))
        if p.vocab_tree_path and not os.path.isfile(os.path.expanduser(str(p.vocab_tree_path))):
            return PoseResult.empty(n, time.perf_counter() - t0,
                                    error=f"vocabulary tree not found: {p.vocab_tree_path}")
        loop = ("on (vocabulary tree " + str(p.vocab_tree_path) + ")" if p.vocab_tree_path else
                "off: needs a COLMAP vocabulary tree file (evaluate.pose.colmap.vocab_tree_path), none offline")
        names = [f"frame_{k:04d}.png" for k in range(n)]
        log_level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = p.log_level
        try:
            recs = self._run(pycolmap, images, names, reader, extract, match, pairing, verify, mapping)
        except Exception as exc:  # noqa: BLE001 -- COLMAP failing on the data is a result, not a crash
            return PoseResult.empty(n, time.perf_counter() - t0, error=f"{type(exc).__name__}: {exc}")
        finally:
            pycolmap.logging.minloglevel = log_level
        if not recs:
            return PoseResult.empty(n, time.perf_counter() - t0, error="no reconstruction", reconstructions=0,
                                    peak_threshold=p.peak_threshold, threshold_choice=thr_info)
        best_key = max(sorted(recs), key=lambda k: recs[k].num_reg_images())
        rec = recs[best_key]
        index = {name: k for k, name in enumerate(names)}
        poses = np.full((n, 4, 4), np.nan)
        reg = np.zeros(n, bool)
        for image in rec.images.values():
            if not image.has_pose:
                continue
            k = index[image.name]
            w2c = np.eye(4)
            w2c[:3, :] = image.cam_from_world().matrix()
            poses[k] = np.linalg.inv(w2c)
            reg[k] = True
        info = {"reconstructions": len(recs), "points3D": int(rec.num_points3D()),
                "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
                "peak_threshold": p.peak_threshold, "threshold_choice": thr_info, "preprocess": p.preprocess,
                "loop_detection": loop, "bundle_adjustment": "COLMAP incremental mapper (local + global BA), "
                                                             "intrinsics fixed", "cpu_seconds": time.process_time() - c0}
        return PoseResult(poses, reg, time.perf_counter() - t0, info)

    @staticmethod
    def _run(pycolmap, images, names, reader, extract, match, pairing, verify, mapping) -> dict:
        """Write the frames to a temporary folder and run extraction, matching and mapping there."""
        import cv2

        with tempfile.TemporaryDirectory(prefix="room_colmap_") as tmp:
            tmp = Path(tmp)
            img_dir, out_dir, db = tmp / "images", tmp / "sparse", tmp / "database.db"
            img_dir.mkdir()
            out_dir.mkdir()
            for name, im in zip(names, images):
                if not cv2.imwrite(str(img_dir / name), cv2.cvtColor(im, cv2.COLOR_RGB2BGR)):
                    raise OSError(f"cannot write {img_dir / name}")
            pycolmap.extract_features(db, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extract, device=pycolmap.Device.cpu)
            pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing,
                                      verification_options=verify, device=pycolmap.Device.cpu)
            return pycolmap.incremental_mapping(db, img_dir, out_dir, options=mapping)


# --------------------------------------------------------------------------- registry

#: name -> method; the stage runs the names listed in ``evaluate.pose.methods``.  DUSt3R and VGGT are not
#: here: neither their code nor their weights can be installed on this project's machines (no network), so an
#: adapter could never be run or checked against the real model; rows that can never run are left out.
METHODS: dict[str, PoseMethod] = {
    "colmap": Colmap(),
    "orb_vo": OrbVO(),
    "sift_vo": SiftVO(),
    "identity": Blind("identity"),
    "constant_forward": Blind("constant_forward"),
}

#: the image-blind trivial baselines every method row is compared against (Table I flags a row that does not
#: beat all of them)
BASELINES = ("identity", "constant_forward")


def get_method(name: str) -> PoseMethod:
    if name not in METHODS:
        raise ConfigError(f"evaluate.pose.methods: unknown method '{name}' (known: {', '.join(sorted(METHODS))})")
    return METHODS[name]


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K of an image resized by (sx, sy), OpenCV pixel-centre convention: u' + 0.5 = sx (u + 0.5)."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K2[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K2[1, 2] + 0.5) * sy - 0.5
    return K2


def downscale(images: list[np.ndarray], K: np.ndarray, factor: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Images shrunk by ``factor`` >= 1 (area averaging) and the matching K."""
    if factor < 1.0:
        raise ConfigError(f"evaluate.pose.downscale must be >= 1, got {factor}")
    if factor == 1.0 or not images:
        return list(images), np.asarray(K, dtype=np.float64)
    import cv2

    h, w = images[0].shape[:2]
    w2, h2 = max(8, int(math.floor(w / factor + 0.5))), max(8, int(math.floor(h / factor + 0.5)))
    out = [cv2.resize(im, (w2, h2), interpolation=cv2.INTER_AREA) for im in images]
    return out, scale_intrinsics(K, w2 / w, h2 / h)
