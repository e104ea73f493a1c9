"""The ``colmap`` pose method: COLMAP through pycolmap on denoised, CLAHE-equalised frames, the SIFT
threshold chosen by verified matches on probe pairs, sequential matching, incremental mapping with the
intrinsics fixed (:mod:`~room_pipeline.evaluate.pose_methods` describes it)."""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .pose_method_base import ColmapParams, PoseMethodParams, PoseResult, _check_inputs, preprocess_gray


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
