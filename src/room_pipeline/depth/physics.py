"""Physics baseline: depth from image brightness under the renderer's known light model (no training).

The fast renderer (:mod:`room_pipeline.render.shading`) forms a pixel as

    code = sRGB8( 2^EV * L ),   L_c = k_c(cos) / r^2,   k_c(cos) = shade_coaxial(cos, r^2 = 1)_c

with the point light at the camera (``TipLight.offset_m`` = 0): ``r`` is the
distance from the camera centre to the surface point, ``cos`` the angle
between its normal and the viewing ray, and ``k_c`` the BRDF times the light
intensity (diffuse ``(1 - F0) base_c / pi`` plus the GGX lobe, times ``cos``).
This module inverts that chain:

1. sRGB code -> linear value (exact inverse of the transfer function, code
   centre), divided by ``2^EV`` -> radiance ``L_c``;
2. per channel ``r_c^2 = k_c(cos) / L_c``; channels that are clipped (code
   >= ``saturated_code``) or black (code 0) are upper/lower bounds only, so the
   estimate is the radiance-weighted mean of ``log r_c`` over the channels
   inside the range (all clipped: the dimmest channel; all black: half a code);
3. planar depth ``z = r / |ray|`` (rays with z = 1, as in
   :meth:`~room_pipeline.render.camera.CameraIntrinsics.pixel_rays`).

The cosine is unknown from one image.  ``cos_model='unit'`` assumes 1 (a
surface facing the camera: it overestimates depth on oblique walls, where the
true ``k(cos)`` is smaller); ``cos_model='iterate'`` starts from that and
re-estimates ``cos`` ``iterations`` times from the normals of the current depth
map (cross product of the unprojected points' image gradients after a
Gaussian blur of ``normal_smoothing_px``), clipped below at ``min_cos``.
benchmarks/depth_eval.py measures both (the default is the better one).

The result is metric when the light model (power, material, exposure) is
the one that rendered the image: the estimator reads it from the sequence's
``metadata/render.json`` "renderer" block.  With Cycles images (indirect light,
soft highlights) or real frames it is only an approximation, evaluated
median-scaled as well.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..render.camera import CameraIntrinsics
from ..render.scene import TipLight, TissueMaterial
from ..render.shading import shade_coaxial

COS_MODELS = ("unit", "iterate")


@dataclasses.dataclass(frozen=True)
class LightModel:
    """What turned radiance into pixels: material, light and exposure (EV)."""

    material: TissueMaterial
    light: TipLight
    exposure_ev: float
    #: per-frame exposures (EV) of a run with automatic per-frame exposure (render.json film.frame_ev), indexed
    #: by the frame's index in its sequence; None: ``exposure_ev`` holds for every frame
    frame_ev: tuple[float, ...] | None = None

    def at_frame(self, index: int) -> "LightModel":
        """The model with the exposure of frame ``index`` (the same model when the exposure is fixed)."""
        if self.frame_ev is None:
            return self
        if not 0 <= index < len(self.frame_ev):
            raise InputError(f"frame {index} has no exposure in render.json (film.frame_ev holds "
                             f"{len(self.frame_ev)} frames)")
        return dataclasses.replace(self, exposure_ev=float(self.frame_ev[index]), frame_ev=None)

    @staticmethod
    def from_render_metadata(renderer: Mapping[str, Any]) -> "LightModel":
        """From ``metadata/render.json["renderer"]`` (raycast block, or Cycles' {"rgb", "geometry"} pair)."""
        if "geometry" in renderer and "rgb" in renderer:          # backend cycles: RGB exposure from Cycles
            geo, ev = renderer["geometry"], renderer["rgb"].get("exposure_ev")
        else:
            geo, ev = renderer, renderer.get("exposure_ev")
        try:
            mat = {k: (tuple(v) if isinstance(v, list) else v) for k, v in geo["material"].items()}
            light = {k: (tuple(v) if isinstance(v, list) else v) for k, v in geo["light"].items()}
            film = geo.get("film") or {}
            frame_ev = film.get("frame_ev") if "rgb" not in renderer else renderer["rgb"].get("frame_ev")
            frame_ev = tuple(float(e) for e in frame_ev) if frame_ev else None
            return LightModel(TissueMaterial(**mat), TipLight(**light), float(ev), frame_ev)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError("render metadata has no usable light model (material, light, exposure_ev): "
                             f"{exc}") from None


def srgb8_to_linear(rgb8: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes -> linear values in [0, 1] (float32), the exact inverse transfer at code centres."""
    codes = np.arange(256, dtype=np.float64) / 255.0
    lut = np.where(codes <= 0.04045, codes / 12.92, ((codes + 0.055) / 1.055) ** 2.4).astype(np.float32)
    a = np.asarray(rgb8)
    if a.dtype != np.uint8:
        raise InputError(f"physics depth expects 8-bit sRGB, got dtype {a.dtype}")
    return lut[a]


def brdf_k(cos: np.ndarray, model: LightModel) -> np.ndarray:
    """``k_c(cos)``: radiance at unit distance, (..., 3) float32 (the renderer's own shading function)."""
    c = np.asarray(cos, dtype=np.float32)
    return shade_coaxial(c, np.ones_like(c), None, model.material, model.light)


@dataclasses.dataclass(frozen=True)
class PhysicsParams:
    """Keys of ``depth.physics`` (see conf/depth/default.yaml)."""

    cos_model: str = "iterate"
    iterations: int = 1
    normal_smoothing_px: float = 2.0
    min_cos: float = 0.05
    saturated_code: int = 255
    max_depth_mm: float = 500.0

    def __post_init__(self) -> None:
        from ..errors import ConfigError

        if self.cos_model not in COS_MODELS:
            raise ConfigError(f"depth.physics.cos_model must be one of {COS_MODELS}, got {self.cos_model!r}")
        if self.iterations < 0 or not 0 < self.min_cos <= 1 or self.normal_smoothing_px < 0:
            raise ConfigError("depth.physics: iterations >= 0, 0 < min_cos <= 1, normal_smoothing_px >= 0 required")
        if not 1 <= self.saturated_code <= 255 or self.max_depth_mm <= 0:
            raise ConfigError("depth.physics: 1 <= saturated_code <= 255 and max_depth_mm > 0 required")


def _log_distance(lin: np.ndarray, rgb8: np.ndarray, k: np.ndarray, sat: int) -> np.ndarray:
    """log r (H, W) float32 from linear pixel radiance (H, W, 3), the codes and k(cos) ((H, W, 3) or (3,)).

    Channel by channel (numpy reductions over a last axis of 3 are slow).
    """
    f32 = np.float32
    half_code = f32(srgb8_to_linear(np.array([1], np.uint8))[0] * 0.5)
    k = np.asarray(k, dtype=f32)
    wsum = np.zeros(lin.shape[:2], f32)
    acc = np.zeros(lin.shape[:2], f32)
    lo = hi = None
    all_clipped = np.ones(lin.shape[:2], bool)
    for c in range(3):
        code = rgb8[..., c]
        lc = lin[..., c]
        kc = np.maximum(k[..., c], f32(1e-30))
        logr = f32(0.5) * (np.log(kc) - np.log(np.where(code > 0, lc, half_code)))
        w = np.where((code > 0) & (code < sat), lc, f32(0))
        wsum += w
        acc += w * logr
        lo = logr if lo is None else np.minimum(lo, logr)
        hi = logr if hi is None else np.maximum(hi, logr)
        all_clipped &= code >= sat
    # all clipped: the dimmest channel gives the tightest bound; all black: half a code in every channel
    fallback = np.where(all_clipped, hi, lo)
    return np.where(wsum > 0, acc / np.maximum(wsum, f32(1e-30)), fallback).astype(f32)


@functools.lru_cache(maxsize=8)
def _rays(camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel ray components x/z, y/z (float32, z = 1) and the ray length."""
    u = (np.arange(camera.width, dtype=np.float64) - camera.cx) / camera.fx
    v = (np.arange(camera.height, dtype=np.float64) - camera.cy) / camera.fy
    rx, ry = np.meshgrid(u, v)
    return rx.astype(np.float32), ry.astype(np.float32), np.sqrt(rx * rx + ry * ry + 1).astype(np.float32)


def camera_cos(depth: np.ndarray, camera: CameraIntrinsics, smoothing_px: float) -> np.ndarray:
    """|cos| between the surface normal and the viewing ray of a planar depth map (H, W) float32.

    Normals are the cross product of the image gradients (central differences)
    of the unprojected points, after a Gaussian blur of log depth.
    """
    import cv2

    f32 = np.float32
    rx, ry, rl = _rays(camera)
    logd = np.log(np.maximum(np.asarray(depth, dtype=f32), f32(1e-9)))
    if smoothing_px > 0:
        logd = cv2.GaussianBlur(logd, (0, 0), float(smoothing_px), borderType=cv2.BORDER_REPLICATE)
    d = np.exp(logd)
    comps = (rx * d, ry * d, d)
    du = [np.gradient(a, axis=1) for a in comps]
    dv = [np.gradient(a, axis=0) for a in comps]
    nx = du[1] * dv[2] - du[2] * dv[1]
    ny = du[2] * dv[0] - du[0] * dv[2]
    nz = du[0] * dv[1] - du[1] * dv[0]
    ln = np.sqrt(nx * nx + ny * ny + nz * nz)
    # the sign of the cross product depends on the handedness, not the geometry: take |n . ray|
    cos = np.abs(nx * rx + ny * ry + nz) / np.maximum(ln * rl, f32(1e-30))
    return np.where(ln > 0, cos, f32(1)).astype(f32)


def physics_depth(rgb8: np.ndarray, camera: CameraIntrinsics, model: LightModel,
                  params: PhysicsParams = PhysicsParams()) -> np.ndarray:
    """Planar depth (H, W) float32 metres of an 8-bit sRGB image (H, W, 3) under ``model``."""
    rgb8 = np.asarray(rgb8)
    if rgb8.ndim != 3 or rgb8.shape[2] < 3:
        raise InputError(f"physics depth expects an (H, W, 3) RGB image, got shape {rgb8.shape}")
    rgb8 = rgb8[..., :3]
    h, w = rgb8.shape[:2]
    if (h, w) != (camera.height, camera.width):
        raise InputError(f"image is {w}x{h} but the camera is {camera.width}x{camera.height}")
    lin = srgb8_to_linear(rgb8) * np.float32(2.0 ** -model.exposure_ev)
    _, _, ray_len = _rays(camera)
    log_ray = np.log(ray_len)
    k1 = brdf_k(np.ones(1, np.float32), model)[0]                            # (3,): cos = 1
    log_max = np.float32(np.log(params.max_depth_mm * 1e-3))
    logz = np.minimum(_log_distance(lin, rgb8, k1, params.saturated_code) - log_ray, log_max)
    if params.cos_model == "iterate":
        for _ in range(params.iterations):
            cos = np.clip(camera_cos(np.exp(logz), camera, params.normal_smoothing_px), params.min_cos, 1.0)
            logz = np.minimum(_log_distance(lin, rgb8, brdf_k(cos, model), params.saturated_code) - log_ray, log_max)
    return np.exp(logz).astype(np.float32)


def light_is_coaxial(model: LightModel, tol_m: float = 1e-6) -> bool:
    return math.hypot(*model.light.offset_m) <= tol_m
