"""Camera intrinsics (pinhole + Brown-Conrady lens distortion), projection and the calibration file.

Conventions (see :mod:`room_pipeline.conventions`): OpenCV camera frame
(x right, y down, z forward); pixel (u, v) = (column, row) with the centre of
the top-left pixel at (0, 0) (OpenCV).  A point at camera (x, y, z) has
normalised coordinates (x/z, y/z); OpenCV's distortion model (k1, k2, p1, p2,
k3) maps them to distorted normalised coordinates

    r^2 = x^2 + y^2,  s = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d = x s + 2 p1 x y + p2 (r^2 + 2 x^2),  y_d = y s + p1 (r^2 + 2 y^2) + 2 p2 x y

and the pixel is u = fx x_d + cx, v = fy y_d + cy (all zero coefficients: the
ideal pinhole).  Every image the renderer writes is in this (distorted) image:
pixel (u, v) of RGB, depth, normals, flow and segmentation sees the surface
point along :meth:`CameraIntrinsics.pixel_rays` ``[v, u]``, the undistorted
direction of the distorted pixel centre.  Depth is planar z in metres.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..conventions import metadata_block

#: Newton iterations and residual (normalised units) of :meth:`CameraIntrinsics.undistort`
UNDISTORT_MAX_ITER = 50
UNDISTORT_TOL = 1e-12


@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    """Intrinsics in pixels; ``near``/``far`` clip distances in metres (planar z).

    The default matches the Ambu aScope 4 frames of the shared BREA-Depth
    samples: 600x600 pixels, about 85 degrees horizontal field of view.
    ``distortion``: OpenCV's (k1, k2, p1, p2, k3) on normalised coordinates
    (module docstring); all zero (default) = ideal pinhole.  A non-zero model
    must be one-to-one over the image (:meth:`check_distortion`).
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
    def from_fov(width: int, height: int, fov_deg: float, near: float = 1e-4, far: float = 0.5,
                 distortion=(0.0, 0.0, 0.0, 0.0, 0.0)) -> "CameraIntrinsics":
        """Square pixels, principal point at the image centre, fx from ``fov_deg`` (the horizontal field of
        view of the pinhole part: with barrel distortion the image sees wider), OpenCV ``distortion``."""
        f = width / 2 / math.tan(math.radians(fov_deg) / 2)
        return CameraIntrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2, near, far,
                                tuple(float(c) for c in distortion))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width / 2 / self.fx))

    @property
    def has_distortion(self) -> bool:
        return any(float(c) != 0.0 for c in self.distortion)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates (x/z, y/z) -> distorted ones (OpenCV's model, module docstring)."""
        k1, k2, p1, p2, k3 = (float(c) for c in self.distortion)
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        r2 = x * x + y * y
        s = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = x * y
        return x * s + 2 * p1 * xy + p2 * (r2 + 2 * x * x), y * s + p1 * (r2 + 2 * y * y) + 2 * p2 * xy

    def _distort_jacobian(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """d(x_d, y_d) / d(x, y) of :meth:`distort`: (dxx, dxy, dyx, dyy)."""
        k1, k2, p1, p2, k3 = (float(c) for c in self.distortion)
        r2 = x * x + y * y
        s = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ds = k1 + r2 * (2 * k2 + 3 * k3 * r2)            # ds / d(r^2)
        dxx = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
        dxy = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
        dyx = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
        dyy = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
        return dxx, dxy, dyx, dyy

    def undistort(self, xd: np.ndarray, yd: np.ndarray, max_iter: int = UNDISTORT_MAX_ITER,
                  tol: float = UNDISTORT_TOL) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates -> undistorted ones: Newton's method on :meth:`distort`.

        Starts at the distorted point and iterates until every residual
        ``|distort(x, y) - (xd, yd)|`` is below ``tol`` (normalised units; 1e-12
        is ~3e-10 px at fx 300).  Raises ValueError if it does not converge in
        ``max_iter`` steps (a model that folds the image there).
        """
        xd = np.asarray(xd, dtype=np.float64)
        yd = np.asarray(yd, dtype=np.float64)
        if not self.has_distortion:
            return xd.copy(), yd.copy()
        x, y = xd.copy(), yd.copy()
        for _ in range(max_iter):
            fx_, fy_ = self.distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            err = float(np.max(np.abs(ex), initial=0.0)), float(np.max(np.abs(ey), initial=0.0))
            if max(err) <= tol:
                return x, y
            a, b, c, d = self._distort_jacobian(x, y)
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x - (d * ex - b * ey) / det
            y = y - (a * ey - c * ex) / det
        fx_, fy_ = self.distort(x, y)
        res = float(np.max(np.hypot(fx_ - xd, fy_ - yd), initial=0.0))
        if not np.isfinite(res) or res > tol:
            raise ValueError(f"camera distortion {list(self.distortion)}: undistortion did not converge "
                             f"(residual {res:.2e} after {max_iter} Newton steps); the model folds the image")
        return x, y

    def check_distortion(self) -> None:
        """Raise ValueError unless the distortion is one-to-one over the image.

        The radial map r -> r s(r) must increase up to the undistorted radius of the image's
        farthest corner (else pixels past the fold would see two directions), and every pixel
        centre must undistort (Newton) to a point that distorts back onto it.
        """
        if not self.has_distortion:
            return
        vals = [float(c) for c in self.distortion]
        if not all(math.isfinite(c) for c in vals):
            raise ValueError(f"camera distortion must be 5 finite numbers (k1, k2, p1, p2, k3), got {vals}")
        corners_u = np.array([-0.5, self.width - 0.5]) - self.cx
        corners_v = np.array([-0.5, self.height - 0.5]) - self.cy
        rd_max = float(np.max(np.hypot(corners_u[:, None] / self.fx, corners_v[None, :] / self.fy)))
        k1, k2, _, _, k3 = vals
        r = np.linspace(0.0, 4.0 * rd_max + 1.0, 20001)
        r2 = r * r
        rd = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        drd = 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2))
        reach = np.nonzero(rd >= rd_max * 1.0001)[0]
        fold = np.nonzero(drd <= 0)[0]
        if len(fold) and (not len(reach) or fold[0] <= reach[0]):
            raise ValueError(f"camera distortion {vals}: the radial map folds at normalised radius "
                             f"{r[fold[0]]:.3f}, inside the image (its corners reach distorted radius "
                             f"{rd_max:.3f}): not a lens")
        if not len(reach):
            raise ValueError(f"camera distortion {vals}: the distorted radius never reaches the image corner "
                             f"({rd_max:.3f}): not a lens")
        self.pixel_rays()          # Newton converges at every pixel centre (raises otherwise)

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame ray directions with z = 1 (so depth * ray = point).

        Entry ``[v, u]`` is the undistorted direction of the (distorted) pixel centre (u, v).
        """
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return self.rays_at(np.stack([u, v], axis=-1))

    def rays_at(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) pixel coordinates (u, v) -> (..., 3) camera-frame directions with z = 1 (undistorted)."""
        uv = np.asarray(uv, dtype=np.float64)
        x, y = self.undistort((uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy)
        return np.stack([x, y, np.ones_like(x)], axis=-1)

    def project_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates (x/z, y/z) -> pixel (u, v), distortion applied."""
        if self.has_distortion:
            x, y = self.distort(x, y)
        return self.fx * np.asarray(x, dtype=np.float64) + self.cx, self.fy * np.asarray(y, dtype=np.float64) + self.cy

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates (u, v) in the (distorted) image."""
        p = np.asarray(points_cam, dtype=np.float64)
        u, v = self.project_normalized(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2])
        return np.stack([u, v], axis=1)

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) planar depth (metres) -> (H, W, 3) camera-frame points."""
        return self.pixel_rays() * np.asarray(depth, dtype=np.float64)[..., None]

    def to_dict(self) -> dict:
        """Content of ``calibration/camera_params.json``."""
        return {"model": "pinhole" if not self.has_distortion else "pinhole + opencv distortion",
                "width": self.width, "height": self.height,
                "K": self.K.tolist(), "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "fov_x_deg": self.fov_x_deg, "distortion_model": "opencv (k1, k2, p1, p2, k3)",
                "distortion": [float(c) for c in self.distortion],
                "distortion_applied": ("none: ideal pinhole" if not self.has_distortion else
                                       "rendered: every image (rgb, depth, normals, flow, segmentation) is in the "
                                       "distorted image; pixel_rays = undistorted direction of each distorted pixel "
                                       "centre; points project with K and this distortion"),
                "near_m": self.near, "far_m": self.far,
                "pixel_convention": "OpenCV: (u, v) = (column, row), centre of the top-left pixel at (0, 0)",
                "depth": "planar z along the optical axis, metres",
                "conventions": metadata_block()}

    @staticmethod
    def from_dict(d: dict) -> "CameraIntrinsics":
        return CameraIntrinsics(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                                float(d["cx"]), float(d["cy"]), float(d.get("near_m", 1e-4)),
                                float(d.get("far_m", 0.5)), tuple(float(c) for c in d.get("distortion", (0.0,) * 5)))


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
