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
    ``colmap``   COLMAP through pycolmap: SIFT, sequential matching, incremental
                 mapping with the intrinsics fixed to ``K`` (PINHOLE camera,
                 never refined); the largest reconstruction is kept.  Single
                 threaded and seeded, so the same images give the same poses.
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
    ``dust3r``, ``vggt``
                 Learned multi-view methods.  They need network weights (path in
                 ``evaluate.pose.weights``) and their packages; this build has no
                 adapter for them, so they always report *unavailable* with the
                 reason and never produce numbers.
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
        return p


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
class PoseMethodParams:
    """What every method may read: seed, per-method options and the learned methods' weight paths."""

    seed: int = 0
    colmap: ColmapParams = ColmapParams()
    orb: OrbParams = OrbParams()
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
    def relative_pose(cv2, f0, f1, K: np.ndarray, p: OrbParams, seed: int) -> tuple[np.ndarray | None, str, int]:
        """Camera 1 in camera 0's frame (4x4, unit translation), or None and why; and the pose inliers."""
        (p0, d0), (p1, d1) = f0, f1
        if d0 is None or d1 is None or len(p0) < 2 or len(p1) < 2:
            return None, "few_matches", 0
        good = []
        for m in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d0, d1, k=2):
            if len(m) == 2 and m[0].distance < p.ratio * m[1].distance:
                good.append((m[0].queryIdx, m[0].trainIdx))
        if len(good) < p.min_matches:
            return None, "few_matches", 0
        q, t = np.array(good).T
        x0, x1 = p0[q], p1[t]
        cv2.setRNGSeed(seed)
        E, mask = cv2.findEssentialMat(x0, x1, K, method=cv2.RANSAC, prob=p.ransac_confidence,
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

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        """Chain frame k to the last registered frame of the current segment; after ``max_skips`` frames in a
        row that cannot be related to it, tracking is lost and a new segment starts at the current frame (a
        segment's reference that nothing could be chained to is replaced by the next frame).  The largest
        segment (most frames; the earliest on ties) is the result, in its first frame's camera frame."""
        import cv2

        t0 = time.perf_counter()
        _, _, K = _check_inputs(images, K)
        p = params.orb
        n = len(images)
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
        steps = {"ok": 0, "few_matches": 0, "no_essential": 0, "few_inliers": 0}
        inliers = []
        segments: list[dict[int, np.ndarray]] = [{0: np.eye(4)}]
        last, misses = 0, 0
        for k in range(1, n):
            T, status, n_in = self.relative_pose(cv2, feats[last], feats[k], K, p, int(params.seed) + k)
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
                "median_keypoints": float(np.median([len(f[0]) for f in feats])),
                "fast_threshold_median": float(np.median(thresholds)) if thresholds else None,
                "scale": "unit translation per step (monocular; fixed by the Sim(3) alignment)"}
        return PoseResult(poses, reg, time.perf_counter() - t0, info)


# --------------------------------------------------------------------------- COLMAP


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
    def peak_threshold(pycolmap, images: list[np.ndarray], p: ColmapParams, n_probe: int = 5) -> float:
        """SIFT peak threshold for this sequence: ``peak_threshold``, halved (down to ``peak_threshold_min``)
        while the median keypoint count of up to ``n_probe`` evenly spaced frames is under ``min_keypoints``
        (low-contrast endoscopic frames give a few dozen SIFT keypoints at COLMAP's usual threshold)."""
        thr = p.peak_threshold
        if p.min_keypoints <= 0 or not images:
            return thr
        probe = [images[int(i)] for i in np.unique(np.linspace(0, len(images) - 1, n_probe).round())]
        grays = [(im.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)) / 255.0 for im in probe]
        opts = pycolmap.FeatureExtractionOptions()
        opts.use_gpu = False
        opts.num_threads = p.num_threads
        opts.sift.max_num_features = p.max_num_features
        while True:
            opts.sift.peak_threshold = thr
            sift = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
            counts = [len(sift.extract_from_float32_array(np.ascontiguousarray(g))[0]) for g in grays]
            if np.median(counts) >= p.min_keypoints or thr <= p.peak_threshold_min:
                return thr
            thr = max(p.peak_threshold_min, 0.5 * thr)

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        import pycolmap

        t0 = time.perf_counter()
        _, _, K = _check_inputs(images, K)
        n = len(images)
        p = params.colmap
        pycolmap.set_random_seed(int(params.seed))
        log_level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = p.log_level
        try:
            p = dataclasses.replace(p, peak_threshold=self.peak_threshold(pycolmap, images, p))
        finally:
            pycolmap.logging.minloglevel = log_level
        reader, extract, match, pairing, verify, mapping = self._options(pycolmap, p, K, n, int(params.seed))
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
                                    peak_threshold=p.peak_threshold)
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
                "peak_threshold": p.peak_threshold}
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


# --------------------------------------------------------------------------- learned methods


class LearnedMethod:
    """A learned multi-view method (DUSt3R, VGGT, ...): reported unavailable, with the reason, never run here."""

    def __init__(self, name: str, package: str, homepage: str) -> None:
        self.name, self.package, self.homepage = name, package, homepage

    def availability(self, params: PoseMethodParams) -> tuple[bool, str | None]:
        path = (params.weights or {}).get(self.name)
        if not path:
            return False, f"no weights configured (evaluate.pose.weights.{self.name} is null; see {self.homepage})"
        if not os.path.exists(os.path.expanduser(str(path))):
            return False, f"weights not found: {path}"
        if importlib.util.find_spec(self.package) is None:
            return False, f"weights present but the '{self.package}' package is not installed"
        return False, (f"weights and '{self.package}' present, but room-pipeline has no {self.name} adapter yet "
                       f"(add one to room_pipeline.evaluate.pose_methods)")

    def estimate(self, images: list[np.ndarray], K: np.ndarray, params: PoseMethodParams) -> PoseResult:
        ok, why = self.availability(params)
        raise ConfigError(f"pose method '{self.name}' cannot run here: {why}")


#: name -> method; the stage runs the names listed in ``evaluate.pose.methods``
METHODS: dict[str, PoseMethod] = {
    "colmap": Colmap(),
    "orb_vo": OrbVO(),
    "dust3r": LearnedMethod("dust3r", "dust3r", "https://github.com/naver/dust3r"),
    "vggt": LearnedMethod("vggt", "vggt", "https://github.com/facebookresearch/vggt"),
}


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
