"""Depth -> local point cloud in the camera frame (OpenCV: x right, y down, z forward; metres).

``back_project`` keeps every ``stride``-th row and column of a planar-z depth map (0, NaN or
negative = no answer) and returns the camera-frame points with their pixel coordinates.
``median_scale`` scales a depth map known up to scale (a relative estimator's) to ground truth by the
ratio of medians over pixels valid in both, as the ROOM paper's demonstration does (its planner ran on
predicted depth "scaled" to metric with the ground truth's median).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InputError
from ..render.camera import CameraIntrinsics


@dataclasses.dataclass(frozen=True)
class LocalCloud:
    """A back-projected depth map.

    points: (N, 3) camera-frame points, m.  pixels: (N, 2) (u, v) full-resolution pixel coordinates.
    depth: (h, w) the sub-sampled planar depth (0 = no answer), m; ``uv0``/``stride`` map its
    index (i, j) to the full-resolution pixel (u, v) = (j * stride, i * stride).
    """

    points: np.ndarray
    pixels: np.ndarray
    depth: np.ndarray
    stride: int
    camera: CameraIntrinsics


def back_project(depth: np.ndarray, camera: CameraIntrinsics, stride: int = 1) -> LocalCloud:
    """Camera-frame points of every ``stride``-th pixel with a positive finite depth (planar z, m)."""
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != (camera.height, camera.width):
        raise InputError(f"depth map is {d.shape[1]}x{d.shape[0]} pixels, the camera {camera.width}x{camera.height}")
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    sub = d[::stride, ::stride].copy()
    sub[~np.isfinite(sub) | (sub <= 0)] = 0.0
    ii, jj = np.nonzero(sub > 0)
    u = jj.astype(np.float64) * stride
    v = ii.astype(np.float64) * stride
    z = sub[ii, jj]
    pts = camera.rays_at(np.stack([u, v], axis=1)) * z[:, None]      # the camera's own model (lens included)
    return LocalCloud(points=pts, pixels=np.stack([u, v], axis=1), depth=sub, stride=int(stride), camera=camera)


def median_scale(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """``pred * s`` with ``s = median(gt) / median(pred)`` over pixels valid (finite, > 0) in both."""
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if p.shape != g.shape:
        raise InputError(f"predicted depth {p.shape} and ground truth {g.shape} differ in shape")
    ok = np.isfinite(p) & (p > 0) & np.isfinite(g) & (g > 0)
    if not ok.any():
        raise InputError("no pixel has both a predicted and a ground-truth depth: cannot median-scale")
    s = float(np.median(g[ok]) / np.median(p[ok]))
    out = np.where(np.isfinite(p) & (p > 0), p * s, 0.0)
    return out, s
