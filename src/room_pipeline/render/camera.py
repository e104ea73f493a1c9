"""Pinhole camera intrinsics, projection and the calibration file.

Conventions (see :mod:`room_pipeline.conventions`): OpenCV camera frame
(x right, y down, z forward); pixel (u, v) = (column, row) with the centre of
the top-left pixel at (0, 0) (OpenCV), so a point at camera (x, y, z) lands at
u = fx x / z + cx, v = fy y / z + cy.  Depth is planar z in metres.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..conventions import metadata_block


@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels; ``near``/``far`` clip distances in metres (planar z).

    The default matches the Ambu aScope 4 frames of the shared BREA-Depth
    samples: 600x600 pixels, about 85 degrees horizontal field of view.
    Distortion coefficients follow OpenCV's (k1, k2, p1, p2, k3); renders are
    ideal pinhole images, so they are zero unless a distortion model is added.
    """

    width: int = 600
    height: int = 600
    fx: float = 600 / 2 / math.tan(math.radians(85.0) / 2)
    fy: float = 600 / 2 / math.tan(math.radians(85.0) / 2)
    cx: float = (600 - 1) / 2
    cy: float = (600 - 1) / 2
    near: float = 1e-4
    far: float = 0.5
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @staticmethod
    def from_fov(width: int, height: int, fov_deg: float, near: float = 1e-4, far: float = 0.5) -> "CameraIntrinsics":
        """Square pixels, principal point at the image centre, ``fov_deg`` horizontal field of view."""
        f = width / 2 / math.tan(math.radians(fov_deg) / 2)
        return CameraIntrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2, near, far)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width / 2 / self.fx))

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame ray directions with z = 1 (so depth * ray = point)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates (u, v)."""
        p = np.asarray(points_cam, dtype=np.float64)
        return np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx, self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1)

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) planar depth (metres) -> (H, W, 3) camera-frame points."""
        return self.pixel_rays() * np.asarray(depth, dtype=np.float64)[..., None]

    def to_dict(self) -> dict:
        """Content of ``calibration/camera_params.json``."""
        return {"model": "pinhole", "width": self.width, "height": self.height,
                "K": self.K.tolist(), "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "fov_x_deg": self.fov_x_deg, "distortion_model": "opencv (k1, k2, p1, p2, k3)",
                "distortion": list(self.distortion), "near_m": self.near, "far_m": self.far,
                "pixel_convention": "OpenCV: (u, v) = (column, row), centre of the top-left pixel at (0, 0)",
                "depth": "planar z along the optical axis, metres",
                "conventions": metadata_block()}

    @staticmethod
    def from_dict(d: dict) -> "CameraIntrinsics":
        return CameraIntrinsics(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                                float(d["cx"]), float(d["cy"]), float(d.get("near_m", 1e-4)),
                                float(d.get("far_m", 0.5)), tuple(d.get("distortion", (0.0,) * 5)))


def look_at(eye, forward, down=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (4x4, OpenCV frame: x right, y down, z forward) at ``eye`` looking along
    ``forward``, with the image's down direction as close to ``down`` as possible (any vector; if it is
    parallel to ``forward`` a perpendicular one is picked).  Lengths in the caller's units (metres here)."""
    z = np.asarray(forward, dtype=float)
    z = z / np.linalg.norm(z)
    d = np.asarray(down, dtype=float)
    y = d - np.dot(d, z) * z
    if np.linalg.norm(y) < 1e-9:                # down parallel to forward: the least aligned world axis
        y = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    y = y / np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.stack([np.cross(y, z), y, z], axis=1)
    T[:3, 3] = eye
    return T
