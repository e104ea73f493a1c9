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

Modules: :mod:`.pose_method_base` (parameters, the result record, the interface, image preprocessing),
:mod:`.visual_odometry` (``orb_vo``, ``sift_vo``), :mod:`.colmap_method` (``colmap``); this one holds the
blind baselines, the registry and the image-scaling helpers, and re-exports the others' public names.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..errors import ConfigError
from .colmap_method import Colmap
from .pose_method_base import PoseMethod, PoseMethodParams, PoseResult
from .visual_odometry import OrbVO, SiftVO

# the pose methods' API, importable from here as before the split
from .pose_method_base import PREPROCESS, ColmapParams, OrbParams, SiftParams, preprocess_gray  # noqa: F401


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
