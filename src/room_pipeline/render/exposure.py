"""Per-frame automatic exposure, like a video bronchoscope's gain control.

A real scope meters every frame and adjusts its gain smoothly: walls close
to the tip do not blow out, a far dark bronchus is lifted.  Here the meter
is a cheap low-resolution pass over the whole sequence before any frame is
rendered.  Steps 1-2 depend on one frame each, so the render stage meters
frames on its executor's workers (:class:`ExposureMeter`); steps 3-5 are one
sequential pass in the driver.  The exposures (and hence the bytes of every
frame) do not depend on the executor or the worker count.

For each frame ``i`` (in pose order):

1. the frame is ray cast at ``meter_scale`` of the image size (same field
   of view, light, falloff, vignetting) with the mucosa's mean albedo
   (``base_color``: the meter sees the frame's geometry and light, not the
   texture detail);
2. the ``percentile``-th percentile of the lit pixels' linear luminance,
   ``y_i``, gives the raw exposure ``e_i = log2(target / y_i)`` (0 EV for
   a frame with nothing lit);
3. a causal exponential smoothing in time (in EV, time constant
   ``smoothing_s`` seconds, using the timestamps): ``E_i = E_{i-1} + (1 -
   exp(-dt / smoothing_s)) (e_i - E_{i-1})``, ``E_0 = e_0``;
4. highlight protection, without lag (a gain control's fast attack): the
   exposure is at most ``log2(highlight_max / h_i)`` with ``h_i`` the
   ``highlight_percentile``-th percentile of the lit pixels' largest linear
   channel (a saturated red clips before the luminance does), so no more
   than about ``100 - highlight_percentile`` % of a frame clips
   (``highlight_max`` < 1 leaves head-room for the texture, which the meter
   does not see);
5. the result is clamped to ``[min_ev, max_ev]`` (the gain range) and
   rounded to 1/1000 EV.

Each frame's steps 1-2 are the same arithmetic in whichever process meters
it, and 3-5 sequential numpy in one: same scene, same parameters -> same
exposures, bit for bit (tests/test_realism.py: the meter in blocks on one thread
equals the one-process meter; tests/test_execution.py: the render stage's bytes
with two workers equal one process's).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .camera import CameraIntrinsics
from .scene import Scene
from .shading import luminance


@dataclasses.dataclass(frozen=True)
class ExposureParams:
    """Automatic exposure (see the module docstring); EV in stops, time in seconds."""

    target: float = 0.43
    percentile: float = 95.0
    smoothing_s: float = 0.3
    min_ev: float = -12.0
    max_ev: float = 12.0
    meter_scale: float = 0.125
    highlight_percentile: float = 99.0
    highlight_max: float = 0.9

    def __post_init__(self) -> None:
        if not 0 < self.target <= 1:
            raise ValueError(f"auto exposure target must be in (0, 1], got {self.target}")
        if not 0 < self.percentile <= 100:
            raise ValueError(f"auto exposure percentile must be in (0, 100], got {self.percentile}")
        if not 0 < self.highlight_percentile <= 100 or not self.highlight_max > 0:
            raise ValueError("auto exposure: highlight_percentile in (0, 100] and highlight_max > 0 required")
        if not self.smoothing_s >= 0 or not self.min_ev < self.max_ev or not 0 < self.meter_scale <= 1:
            raise ValueError("auto exposure: smoothing_s >= 0, min_ev < max_ev and 0 < meter_scale <= 1 required")


def meter_camera(cam: CameraIntrinsics, scale: float) -> CameraIntrinsics:
    """The same field of view at ``scale`` of the resolution (at least 16 px a side)."""
    w = max(16, int(round(cam.width * scale)))
    h = max(16, int(round(cam.height * scale)))
    sx, sy = w / cam.width, h / cam.height
    return dataclasses.replace(cam, width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy,
                               cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)


def meter_scene(scene: Scene, p: ExposureParams) -> Scene:
    """What the meter casts: the scene at ``meter_scale`` of the image size, the mucosa's mean albedo (no
    texture), the film at 0 EV without per-frame exposures."""
    mat = dataclasses.replace(scene.material, texture=None)
    film = dataclasses.replace(scene.film, exposure_ev=0.0, frame_ev=None)
    return Scene(scene.mesh, meter_camera(scene.camera, p.meter_scale), scene.poses, scene.timestamps,
                 material=mat, light=scene.light, film=film)


class ExposureMeter:
    """Steps 1-2 of the module docstring, one frame at a time: :meth:`frame` gives frame ``i``'s raw exposure
    ``e_i`` (0 EV when nothing is lit) and highlight limit (``inf`` when none), EV.

    ``indirect``: the ray caster's inter-reflection (:class:`~room_pipeline.render.indirect.IndirectConfig`),
    which the meter then sees too (on the mean albedo); None: direct light only.  ``nthreads``: Open3D casting
    threads (0: all cores); it changes no value."""

    def __init__(self, scene: Scene, p: ExposureParams, nthreads: int = 0, indirect=None) -> None:
        from .raycast import RaycastConfig, RaycastRenderer

        self.p = p
        cfg = RaycastConfig(nthreads=nthreads, per_pixel_texture=False)
        if indirect is not None:
            cfg = dataclasses.replace(cfg, indirect=indirect)
        self.renderer = RaycastRenderer(meter_scene(scene, p), cfg)

    def frame(self, i: int) -> tuple[float, float]:
        p = self.p
        res = self.renderer.render(i, ("rgb",))
        lin = res["rgb_linear"][res["hit"]]
        y = luminance(lin)
        ok = np.isfinite(y) & (y > 0)
        e, limit = 0.0, math.inf
        if not ok.any():
            return e, limit
        ref = float(np.percentile(y[ok], p.percentile))
        hi = float(np.percentile(lin[ok].max(axis=1), p.highlight_percentile))
        if ref > 0 and math.isfinite(ref):
            e = math.log2(p.target / ref)
        if hi > 0 and math.isfinite(hi):
            limit = math.log2(p.highlight_max / hi)
        return e, limit


def raw_exposures(scene: Scene, p: ExposureParams, nthreads: int = 0, indirect=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame unsmoothed exposures ``e_i`` and highlight limits (float64, EV), every frame metered in this
    process (:class:`ExposureMeter`)."""
    meter = ExposureMeter(scene, p, nthreads, indirect)
    out = np.zeros(len(scene.poses))
    limit = np.full(len(scene.poses), np.inf)
    for i in range(len(scene.poses)):
        out[i], limit[i] = meter.frame(i)
    return out, limit


def smooth_exposures(raw: np.ndarray, timestamps: np.ndarray, p: ExposureParams,
                     limit: np.ndarray | None = None) -> np.ndarray:
    """Causal exponential smoothing in EV (time constant ``smoothing_s``), capped by ``limit`` (per frame,
    no lag), clamped, rounded to 1e-3 EV."""
    raw = np.asarray(raw, dtype=np.float64)
    ts = np.asarray(timestamps, dtype=np.float64)
    out = np.zeros(len(raw))
    for i in range(len(raw)):
        if i == 0 or p.smoothing_s == 0:
            out[i] = raw[i]
        else:
            dt = max(float(ts[i] - ts[i - 1]), 0.0)
            a = 1.0 - math.exp(-dt / p.smoothing_s)
            out[i] = out[i - 1] + a * (raw[i] - out[i - 1])
    if limit is not None:
        out = np.minimum(out, np.asarray(limit, dtype=np.float64))
    return np.round(np.clip(out, p.min_ev, p.max_ev), 3)


def exposure_track(scene: Scene, p: ExposureParams, nthreads: int = 0, indirect=None) -> tuple[float, ...]:
    """The per-frame exposures of a sequence (EV, one per pose): meter, smooth, clamp."""
    if len(scene.poses) == 0:
        return ()
    raw, limit = raw_exposures(scene, p, nthreads, indirect)
    return tuple(float(x) for x in smooth_exposures(raw, scene.timestamps, p, limit))
