"""Two-frame monocular visual odometry with OpenCV, chained: ``orb_vo`` (ORB, Hamming ratio test, RANSAC
essential matrix) and ``sift_vo`` (CLAHE SIFT, L2 ratio test, MAGSAC); scale-free, the largest tracked
segment returned (:mod:`~room_pipeline.evaluate.pose_methods` describes both)."""
from __future__ import annotations

import importlib.util
import time

import numpy as np

from .pose_method_base import PoseMethodParams, PoseResult, _check_inputs, preprocess_gray


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
