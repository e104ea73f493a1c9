"""Forward optical flow from depth and relative pose, its validity mask, and warping.

Definitions (OpenCV camera, pixel (u, v) = (column, row), centre of the
top-left pixel at (0, 0); poses camera-to-world):

* The surface point seen at pixel ``p = (u, v)`` of frame ``t`` is
  ``X_t = depth_t(p) * ray(p)`` in camera ``t`` (``ray`` = ``camera.pixel_rays()``: ``K^-1 [u, v, 1]``
  for a pinhole, the undistorted direction of the distorted pixel with lens distortion).  In camera ``t+1``
  it is ``X_{t+1} = T_{t+1<-t} X_t`` with ``T_{t+1<-t} = inv(pose_{t+1}) @ pose_t``
  (:func:`relative_pose`), at depth ``z_{t+1} = X_{t+1}.z`` and pixel
  ``p' = project(X_{t+1})``.
* **Forward flow** ``flow_t(p) = p' - p`` (pixels, float32, ``[..., 0]`` = u
  along columns, ``[..., 1]`` = v along rows), defined for every surface pixel
  of frame t.
* **Valid** where the flow is a true correspondence: ``p`` is a surface pixel,
  ``z_{t+1} > near`` (in front of camera t+1), ``p'`` inside the image
  (``0 <= u' <= W-1``, ``0 <= v' <= H-1``: the hull of the pixel centres, where
  bilinear sampling is defined; ``EDGE_EPS_PX`` of slack for rounding), and the point is **not occluded** at t+1: the
  first surface along the ray of camera t+1 through ``p'`` lies at planar depth
  ``z_{t+1}`` within ``abs_tol + rel_tol * z_{t+1}``.  The renderer tests that
  by casting the ray (exact) or, faster, against the depth map of frame t+1
  (:func:`visible_in_depth`).  Elsewhere the flow is still the geometric
  value (0 for no-hit pixels); consumers must use the mask.
* **Warping check** (:func:`warp_residual`): on valid pixels, the depth of
  frame t+1 sampled at ``p + flow_t(p)`` equals ``z_{t+1}(p)`` -- the depth
  of the *same point* in camera t+1, not ``depth_t(p)``.  Sampling is bilinear
  in *inverse* depth, which is exact wherever the 2x2 pixel neighbourhood of
  ``p'`` sees one plane (1/z is affine in (u, v) on a plane); across a mesh
  edge it is an approximation.  The exact check casts a ray through ``p'``
  (``RaycastRenderer.depth_at``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .camera import CameraIntrinsics

#: ``p'`` within this many pixels outside the pixel-centre hull still counts as inside (float rounding)
EDGE_EPS_PX = 1e-6


def relative_pose(pose_t: np.ndarray, pose_t1: np.ndarray) -> np.ndarray:
    """4x4 transform from camera t coordinates to camera t+1 coordinates (both poses camera-to-world)."""
    return np.linalg.inv(np.asarray(pose_t1, dtype=np.float64)) @ np.asarray(pose_t, dtype=np.float64)


@dataclasses.dataclass
class Reprojection:
    """Frame-t pixels carried into camera t+1.

    flow: (H, W, 2) float32 pixels (0 where ``hit_t`` is False);
    u1, v1: (H, W) float64 target pixel ``p' = (u1, v1)`` (``uv1``: the two stacked, (H, W, 2));
    z1: (H, W) float64 planar depth of the point in camera t+1 (0 where ``hit_t`` is False);
    in_view: (H, W) bool -- hit at t, in front of camera t+1, ``p'`` inside the image.
    """

    flow: np.ndarray
    u1: np.ndarray
    v1: np.ndarray
    z1: np.ndarray
    in_view: np.ndarray

    @property
    def uv1(self) -> np.ndarray:
        return np.stack([self.u1, self.v1], axis=-1)


def reproject(depth_t: np.ndarray, hit_t: np.ndarray, camera: CameraIntrinsics, pose_t: np.ndarray,
              pose_t1: np.ndarray, rays: np.ndarray | None = None) -> Reprojection:
    """Carry every surface pixel of frame t into camera t+1 (float64 arithmetic).

    Written for speed (the render stage calls it every frame): each (H, W)
    float64 quantity is computed in place in one buffer and the flow is
    written straight into its float32 array; the operations and their order
    are those of the plain formulas, so the values are bit for bit the same.
    """
    hit = np.asarray(hit_t, dtype=bool)
    rays = camera.pixel_rays() if rays is None else rays
    rx, ry = rays[..., 0], rays[..., 1]
    d = np.where(hit, np.asarray(depth_t, dtype=np.float64), 0.0)
    T = relative_pose(pose_t, pose_t1)
    R, t = T[:3, :3], T[:3, 3]

    def row(k: int) -> np.ndarray:
        # X1[k] = d * (R[k, 0] * ray_x + R[k, 1] * ray_y + R[k, 2]) + t[k]   (ray_z = 1)
        out = rx * R[k, 0]
        out += ry * R[k, 1]
        out += R[k, 2]
        out *= d
        out += t[k]
        return out

    x1, y1, z1 = row(0), row(1), row(2)
    front = z1 > camera.near
    front &= hit
    zs = np.where(front, z1, 1.0)
    h, w = hit.shape
    if camera.has_distortion:               # the (distorted) image's pixel of the point: the camera's lens model
        u1, v1 = camera.project_normalized(x1 / zs, y1 / zs)
    else:                                                   # u1 = fx * x1 / zs + cx, v1 = fy * y1 / zs + cy
        u1 = x1
        u1 *= camera.fx
        u1 /= zs
        u1 += camera.cx
        v1 = y1
        v1 *= camera.fy
        v1 /= zs
        v1 += camera.cy
    uu = np.broadcast_to(np.arange(w, dtype=np.float64)[None, :], (h, w))
    vv = np.broadcast_to(np.arange(h, dtype=np.float64)[:, None], (h, w))
    e = EDGE_EPS_PX
    in_view = (u1 >= -e) & (u1 <= w - 1 + e) & (v1 >= -e) & (v1 <= h - 1 + e)
    in_view &= front
    behind = ~front
    np.copyto(u1, uu, where=behind)
    np.copyto(v1, vv, where=behind)
    flow = np.empty((h, w, 2), dtype=np.float32)
    np.subtract(u1, uu, out=flow[..., 0], casting="unsafe")
    np.subtract(v1, vv, out=flow[..., 1], casting="unsafe")
    miss = ~hit
    flow[miss] = 0.0
    z1[miss] = 0.0
    return Reprojection(flow=flow, u1=u1, v1=v1, z1=z1, in_view=in_view)


def sample_inverse_depth(depth: np.ndarray, hit: np.ndarray, uv: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Depth at sub-pixel positions, bilinear in 1/depth over the 2x2 neighbourhood.

    ``uv``: (..., 2) pixel coordinates.  Returns (depth float64 (...), ok):
    ``ok`` where ``uv`` lies in ``[0, W-1] x [0, H-1]`` and all four
    neighbours are surface pixels; elsewhere depth is 0.
    """
    depth = np.asarray(depth, dtype=np.float64)
    hit = np.asarray(hit, dtype=bool)
    h, w = depth.shape
    u = np.asarray(uv[..., 0], dtype=np.float64)
    v = np.asarray(uv[..., 1], dtype=np.float64)
    e = EDGE_EPS_PX
    inside = (u >= -e) & (u <= w - 1 + e) & (v >= -e) & (v <= h - 1 + e)
    u = np.where(inside, np.clip(u, 0, w - 1), 0.0)
    v = np.where(inside, np.clip(v, 0, h - 1), 0.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), max(w - 2, 0))
    v0 = np.minimum(np.floor(v).astype(np.int64), max(h - 2, 0))
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    a = u - u0
    b = v - v0
    inv = np.where(hit, 1.0 / np.where(hit, depth, 1.0), 0.0)
    ok = inside & hit[v0, u0] & hit[v0, u1] & hit[v1, u0] & hit[v1, u1]
    s = ((1 - a) * (1 - b) * inv[v0, u0] + a * (1 - b) * inv[v0, u1]
         + (1 - a) * b * inv[v1, u0] + a * b * inv[v1, u1])
    ok &= s > 0
    return np.where(ok, 1.0 / np.where(ok, s, 1.0), 0.0), ok


def visible_in_depth(rep: Reprojection, depth_t1: np.ndarray, hit_t1: np.ndarray,
                     abs_tol: float = 2e-5, rel_tol: float = 1e-2, exact: bool = False) -> np.ndarray:
    """Validity mask from the depth map of frame t+1 (no extra ray cast).

    Valid where ``rep.in_view`` and the depth of frame t+1 at ``p'``,
    interpolated bilinearly in 1/depth, equals ``z_{t+1}`` within
    ``abs_tol + rel_tol * z_{t+1}``.  Conservative at depth discontinuities
    of frame t+1 (the 2x2 neighbourhood straddles them or touches a no-hit
    pixel): those pixels come out invalid.  ``exact=False`` interpolates with
    ``cv2.remap`` (float32, weights quantised to 1/32 pixel: far inside the
    tolerance, several times faster); ``exact=True`` uses
    :func:`sample_inverse_depth` (float64, all four neighbours must be hits).
    """
    tol = abs_tol + rel_tol * rep.z1
    if exact:
        d1, ok = sample_inverse_depth(depth_t1, hit_t1, rep.uv1)
        return rep.in_view & ok & (np.abs(d1 - rep.z1) <= tol)
    import cv2

    hit = np.asarray(hit_t1, dtype=bool)
    inv = np.zeros(hit.shape, dtype=np.float32)
    np.divide(np.float32(1), depth_t1, out=inv, where=hit)
    h, w = hit.shape
    mx, my = rep.u1.astype(np.float32), rep.v1.astype(np.float32)     # then clipped: the same as clip, then cast
    np.clip(mx, 0, w - 1, out=mx)
    np.clip(my, 0, h - 1, out=my)
    s = cv2.remap(inv, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # |1/s - z| <= tol  <=>  |1 - s z| <= tol s   (s > 0); no division
    sz = s * rep.z1
    return rep.in_view & (s > 0) & (np.abs(1.0 - sz) <= tol * s)


def warp_backward(image_t1: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample frame t+1's image at ``p + flow(p)`` (bilinear, border replicated): image t+1 warped into frame t.

    Any dtype and channel count; float output.  For depth use
    :func:`warp_depth` (inverse-depth interpolation, no-hit aware).
    """
    img = np.asarray(image_t1, dtype=np.float64)
    h, w = img.shape[:2]
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    u = np.clip(uu + flow[..., 0], 0, w - 1)
    v = np.clip(vv + flow[..., 1], 0, h - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), max(w - 2, 0))
    v0 = np.minimum(np.floor(v).astype(np.int64), max(h - 2, 0))
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    a = u - u0
    b = v - v0
    if img.ndim == 3:
        a, b = a[..., None], b[..., None]
    return ((1 - a) * (1 - b) * img[v0, u0] + a * (1 - b) * img[v0, u1]
            + (1 - a) * b * img[v1, u0] + a * b * img[v1, u1])


def warp_depth(depth_t1: np.ndarray, hit_t1: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame t+1's depth sampled at ``p + flow(p)`` (inverse-depth bilinear): (depth float64, ok)."""
    h, w = np.shape(depth_t1)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    uv = np.stack([uu + flow[..., 0].astype(np.float64), vv + flow[..., 1].astype(np.float64)], axis=-1)
    return sample_inverse_depth(depth_t1, hit_t1, uv)


def warp_residual(depth_t: np.ndarray, hit_t: np.ndarray, depth_t1: np.ndarray, hit_t1: np.ndarray,
                  flow: np.ndarray, valid: np.ndarray, camera: CameraIntrinsics, pose_t: np.ndarray,
                  pose_t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The warping check: ``warp_depth(depth_t1, flow) - z_{t+1}`` (metres) and where it is defined.

    Returns (residual float64 (H, W), mask = ``valid`` & sampling ok).  On a
    planar 2x2 neighbourhood the residual is rounding only (float32 depth and
    flow: ~1e-8 m); across mesh edges it is the inverse-depth interpolation
    error.
    """
    rep = reproject(depth_t, hit_t, camera, pose_t, pose_t1)
    warped, ok = warp_depth(depth_t1, hit_t1, flow)
    m = np.asarray(valid, dtype=bool) & ok
    return np.where(m, warped - rep.z1, 0.0), m
