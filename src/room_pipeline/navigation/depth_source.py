"""What the closed loop's ``depth`` policy plans on: ground truth or a registered depth estimator (issue #19).

``navigate.depth``: ``gt`` (the ray caster's planar depth: the upper bound) or any name of the depth
registry (:func:`room_pipeline.depth.estimators.create`: ``shading_sfs``, ``tube_prior``, ``constant``,
``cnn`` / ``cnn_pretrained`` / ``train_mean`` (trained by ``train_depth``: need ``--output-dir`` with the
checkpoint patient's ``depth_model/``), ``depth.hf`` / ``depth.external`` keys).  The estimator runs on the
closed loop's rendered RGB (``_Eyes.rgb``: the ray caster's 8-bit sRGB frame at the simulated tip pose), with
the calibrated sensor noise added first when ``navigate.noise`` > 0 (the noise stage's model,
:func:`room_pipeline.noise.add_noise`, ``beta = navigate.noise``, profile ``noise.profile``, seeded per
control step).  A ``median``-scaling estimator's answer is scaled to the ground truth by the ratio of medians
(:func:`.perception.median_scale`, as the ROOM paper scales its demonstration; an oracle of scale only); a
``metric`` one is used as it answers.  The ``physics`` baseline is not available here: it needs the
renderer's ``render.json`` light block, which the closed loop does not write.

    src = make_depth_source(NavPerception.from_navigate(cfg_navigate), depth_cfg, noise_cfg, camera, output_dir)
    run_episode(..., depth_source=src)        # None for gt

Depth in metres (planar z, 0 = no answer); ``noise`` is the noise model's beta (1 = the level measured on
real frames, 0 = clean).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import BackendUnavailable, ConfigError, InputError
from ..render.camera import CameraIntrinsics
from .perception import median_scale


#: the ``navigate`` section's sub-sections and their readers (the rest of the section is :class:`NavPerception`)
NAVIGATE_SUBSECTIONS = {"planner": "navigation.planner.PlannerParams",
                        "episode": "navigation.closed_loop.EpisodeParams",
                        "benchmark": "benchmarks/navigation.py"}


@dataclasses.dataclass(frozen=True)
class NavPerception:
    """``navigate.depth`` (gt or a depth method) and ``navigate.noise`` (noise beta, >= 0) of conf/navigate."""

    depth: str = "gt"
    noise: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.depth, str) or not self.depth:
            raise ConfigError(f"navigate.depth must be 'gt' or a depth method name, got {self.depth!r}")
        if not isinstance(self.noise, (int, float)) or not math.isfinite(self.noise) or self.noise < 0:
            raise ConfigError(f"navigate.noise must be a finite number >= 0 (noise beta), got {self.noise!r}")

    @classmethod
    def from_navigate(cls, nav: Mapping[str, Any] | None) -> "NavPerception":
        """From the whole ``navigate`` section: its scalar keys are this class's fields, read through
        :func:`~room_pipeline.config.params.params_from_dict` (then :meth:`__post_init__`); its sub-sections
        (:data:`NAVIGATE_SUBSECTIONS`) belong to other readers and are left out, so any other key is unknown
        and raises :class:`ConfigError` naming it."""
        view = {k: v for k, v in dict(nav or {}).items() if k not in NAVIGATE_SUBSECTIONS}
        return params_from_dict(cls, view, "navigate")


def loop_camera(image_px: int, fov_deg: float) -> CameraIntrinsics:
    """The closed loop's camera (as :func:`.closed_loop.run_episode` builds it from ``navigate.episode``'s
    ``image_px`` square and ``fov_deg``; near 0.1 mm, far 0.5 m).  Estimators are built with it; each
    prediction gets the loop's own (``eyes.camera``)."""
    return CameraIntrinsics.from_fov(int(image_px), int(image_px), float(fov_deg), 1e-4, 0.5)


def make_estimator(method: str, depth_cfg: Mapping | None, camera: CameraIntrinsics,
                   output_dir: str | Path | None):
    """The registry's estimator ``method``; InputError (one line: unknown or unavailable here) otherwise."""
    from ..depth.estimators import DepthParams, SequenceInfo, create

    params = DepthParams.from_dict(dict(depth_cfg or {}))
    try:
        return create(method, params, SequenceInfo(camera=camera, output_dir=Path(output_dir) if output_dir else None))
    except ConfigError as exc:
        raise InputError(f"navigate.depth: {exc} (gt or one of the depth registry's methods)") from None
    except BackendUnavailable as exc:
        raise InputError(f"navigate.depth: method {method!r} cannot run here: {exc}") from None


def make_depth_source(perc: NavPerception, depth_cfg: Mapping | None, noise_cfg: Mapping | None,
                      camera: CameraIntrinsics, output_dir: str | Path | None = None
                      ) -> Callable[[Any, np.ndarray], np.ndarray] | None:
    """A ``depth_source(eyes, pose)`` for :func:`.closed_loop.run_episode`; None for ``gt`` without noise.

    With ``gt`` and noise > 0 there is nothing for the noise to act on (ground truth reads no image): refused."""
    if perc.depth == "gt":
        if perc.noise > 0:
            raise InputError("navigate.noise > 0 needs an estimator (navigate.depth=METHOD): ground-truth depth "
                             "reads no image")
        return None
    est = make_estimator(perc.depth, depth_cfg, camera, output_dir)
    profile, seed = None, 0
    if perc.noise > 0:
        from ..noise import NoiseProfile
        from ..noise.params import NoiseParams

        npar = NoiseParams.from_dict(dict(noise_cfg or {}))
        path = npar.profile_path()
        if not path.is_file():
            raise InputError(f"navigate.noise: noise profile {path} missing (noise.profile)")
        profile, seed = NoiseProfile.load(path), npar.seed
    return EstimatorDepth(est, camera, profile, perc.noise, seed)


class EstimatorDepth:
    """Callable ``(eyes, pose) -> depth`` (m): estimator on the (noisy) rendered RGB, median-scaled when relative.

    ``steps`` counts calls (the noise of call k draws from ``SeedSequence([seed, k])``); ``last_scale`` is the
    median scale of the last call (None for a metric estimator)."""

    def __init__(self, estimator, camera: CameraIntrinsics, profile=None, beta: float = 0.0, seed: int = 0) -> None:
        self.estimator, self.camera, self.profile, self.beta, self.seed = estimator, camera, profile, beta, seed
        self.steps = 0
        self.last_scale: float | None = None

    def __call__(self, eyes, pose: np.ndarray) -> np.ndarray:
        from ..depth.base import Frame
        from ..depth.metrics import fit_to_shape

        rgb = eyes.rgb(pose)
        if self.profile is not None and self.beta > 0:
            from ..noise import add_noise

            rgb = add_noise(rgb, self.profile, self.beta, np.random.SeedSequence([int(self.seed), self.steps]))
        k = self.steps
        self.steps += 1
        cam = getattr(eyes, "camera", None) or self.camera
        pred = fit_to_shape(self.estimator.predict(Frame(rgb, cam, k)), (cam.height, cam.width),
                            bool(getattr(self.estimator, "resizes", False)), f"navigate.depth {self.estimator.name}")
        pred = pred.astype(np.float64)
        if getattr(self.estimator, "scaling", "metric") == "median":
            gt = eyes.depth(pose)
            if not (np.isfinite(gt) & (gt > 0)).any():
                self.last_scale = None
                return np.zeros_like(pred)
            try:
                pred, self.last_scale = median_scale(pred, gt)
            except InputError:                     # no pixel valid in both: no answer this step
                self.last_scale = None
                return np.zeros_like(pred)
        else:
            pred = np.where(np.isfinite(pred) & (pred > 0), pred, 0.0)
        return pred

    def close(self) -> None:
        close = getattr(self.estimator, "close", None)
        if close:
            close()
