"""Parameters of the camera-path planner (``conf/trajectory/default.yaml``) and their validation
(step list: :mod:`~room_pipeline.planning.trajectory`)."""
from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError


TARGET_MODES = ("leaves", "random_leaves", "points")
UNREACHABLE_MODES = ("error", "nearest")
IMAGE_UP = ("anterior", "superior")


@dataclasses.dataclass
class TrajectoryParams:
    """Knobs of the trajectory planner; field names are the keys of ``conf/trajectory/default.yaml``.

    Lengths in millimetres (``_mm``), speeds mm/s, curvature 1/m, times s, angles deg.
    """

    targets: str = "random_leaves"       # leaves | random_leaves | points
    max_generation: int | None = 6       # leaves: terminal branches of the tree cut at this generation (null: all leaves)
    n: int = 3                           # random_leaves: how many
    seed: int = 0                        # random_leaves: RNG seed
    points: Any = None                   # points: [[x, y, z], ...] metres, or a Med-MPD target.txt path (mm), or a list of paths
    target_tolerance_mm: float = 1.0     # a target point may lie this far outside a centreline point's lumen
    unreachable: str = "nearest"         # error | nearest
    start_offset_mm: float = 10.0        # start this far along the root branch from its first point
    min_lumen_radius_mm: float = 3.5     # the route ends where the lumen radius falls below this (0 = off)
    kappa_max: float | None = None       # 1/m; null: the scope geometry's q1_max / (2 gamma l) = 45.71
    curvature_safety: float = 0.95       # the smoother aims at this fraction of kappa_max
    clearance_fraction: float = 0.25     # margin = max(fraction * r, clearance_min_mm) ...
    clearance_min_mm: float = 0.3
    clearance_max_fraction: float = 0.5  # ... clipped to this fraction of r and of -sdf at the centreline
    smoothing_step_mm: float = 0.5       # point spacing of the smoother
    centring_weight: float = 1e-4        # pull to the centreline vs bending energy, 1/mm^4
    max_iterations: int = 3000           # ADMM iterations per smoothing solve
    relax_iterations: int = 6            # local margin raises after checking against the SDF
    nearest_backoff_mm: float = 3.0      # unreachable: nearest: cut the route this far before a failure
    rate_hz: float = 10.0                # pose rate
    speed_mm_s: float = 5.0              # advance speed away from bifurcations, straight path
    bifurcation_slowdown: float = 0.5    # speed factor at a bifurcation
    bifurcation_distance_mm: float = 5.0 # slow-down zone half-length along the path
    curvature_slowdown: float = 0.5      # speed factor at kappa = kappa_max (linear in kappa)
    image_up: str = "anterior"           # anterior | superior: world direction of image up at the start
    view_jitter_deg: float = 0.0         # RMS angle of the smooth view-direction jitter (0: off)
    view_jitter_time_s: float = 1.0      # correlation time (Gaussian sigma) of the jitter
    jitter_seed: int = 0
    joint_plan: Any = None               # null: camera poses on the path | mapping (JointPlanParams keys): the
                                         # poses are the forward kinematics of a joint-space plan (planning/joint_plan.py)
    stop_at_wall: bool = True            # the insertion ends before the first frame whose tip or body is closer to the
                                         # wall than the scope's radius + stop_clearance_mm (planning/insertion_stop.py)
    stop_clearance_mm: float = 0.0       # stop_at_wall: the scope's surface keeps this from the wall, mm

    def __post_init__(self) -> None:
        def num(name: str, integer: bool = False, optional: bool = False):
            v = getattr(self, name)
            if v is None and optional:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"trajectory.{name} must be a finite number, got {v!r}")
            if integer:
                if float(v) != int(v):
                    raise ConfigError(f"trajectory.{name} must be an integer, got {v!r}")
                setattr(self, name, int(v))
            else:
                setattr(self, name, float(v))

        for name in ("n", "seed", "max_iterations", "relax_iterations", "jitter_seed"):
            num(name, integer=True)
        num("max_generation", integer=True, optional=True)
        num("kappa_max", optional=True)
        for name in ("target_tolerance_mm", "start_offset_mm", "min_lumen_radius_mm", "curvature_safety", "clearance_fraction",
                     "clearance_min_mm", "clearance_max_fraction", "smoothing_step_mm", "centring_weight",
                     "nearest_backoff_mm", "rate_hz", "speed_mm_s", "bifurcation_slowdown",
                     "bifurcation_distance_mm", "curvature_slowdown", "view_jitter_deg", "view_jitter_time_s",
                     "stop_clearance_mm"):
            num(name)
        for name, choices in (("targets", TARGET_MODES), ("unreachable", UNREACHABLE_MODES), ("image_up", IMAGE_UP)):
            if getattr(self, name) not in choices:
                raise ConfigError(f"trajectory.{name} must be one of {', '.join(choices)}, got {getattr(self, name)!r}")
        positive = ("smoothing_step_mm", "rate_hz", "speed_mm_s", "nearest_backoff_mm", "view_jitter_time_s",
                    "n", "max_iterations")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"trajectory.{name} must be > 0, got {getattr(self, name)}")
        nonneg = ("target_tolerance_mm", "start_offset_mm", "min_lumen_radius_mm", "clearance_fraction", "clearance_min_mm",
                  "centring_weight", "bifurcation_distance_mm", "view_jitter_deg", "relax_iterations",
                  "max_generation", "stop_clearance_mm")
        for name in nonneg:
            v = getattr(self, name)
            if v is not None and v < 0:
                raise ConfigError(f"trajectory.{name} must be >= 0, got {v}")
        for name in ("curvature_safety", "bifurcation_slowdown", "curvature_slowdown"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"trajectory.{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0 <= self.clearance_max_fraction < 1:
            raise ConfigError(f"trajectory.clearance_max_fraction must be in [0, 1), got {self.clearance_max_fraction}")
        if self.kappa_max is not None and self.kappa_max <= 0:
            raise ConfigError(f"trajectory.kappa_max must be > 0 (1/m) or null, got {self.kappa_max}")
        if not isinstance(self.stop_at_wall, bool):
            raise ConfigError(f"trajectory.stop_at_wall must be true or false, got {self.stop_at_wall!r}")
        if self.targets == "points" and self.points is None:
            raise ConfigError("trajectory.points is required when trajectory.targets is 'points'")
        if self.joint_plan is not None:
            from .joint_plan import JointPlanParams
            if not isinstance(self.joint_plan, Mapping):
                raise ConfigError(f"trajectory.joint_plan must be null or a mapping, got {self.joint_plan!r}")
            self.joint_plan = {str(k): v for k, v in self.joint_plan.items()}
            enabled = self.joint_plan.pop("enabled", True)
            if not isinstance(enabled, bool):
                raise ConfigError(f"trajectory.joint_plan.enabled must be true or false, got {enabled!r}")
            JointPlanParams.from_dict(self.joint_plan)
            if not enabled:                  # the section's settings are checked, then the path poses are used
                self.joint_plan = None
        if self.points is not None and not isinstance(self.points, (str, os.PathLike, list, tuple, np.ndarray)):
            raise ConfigError(f"trajectory.points must be a list of [x, y, z] (m) or a target file path, got {self.points!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TrajectoryParams":
        """Build from a config section (:func:`~room_pipeline.config.params.params_from_dict`, then
        :meth:`__post_init__`); an unknown key or a bad value raises :class:`ConfigError` naming it.

        The numbers reach :meth:`to_dict` (``trajectory.json``'s ``params``) converted to their field's type
        exactly as a direct ``TrajectoryParams(**d)`` converts them in :meth:`__post_init__` (an int to float
        for a float field), so both write the same bytes (tests/test_params.py)."""
        return params_from_dict(cls, d, "trajectory")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if isinstance(self.points, np.ndarray):
            d["points"] = self.points.tolist()
        elif isinstance(self.points, os.PathLike):
            d["points"] = os.fspath(self.points)
        return d
