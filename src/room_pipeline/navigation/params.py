"""The ``navigate`` config's parameter records: :class:`EpisodeParams` (``navigate.episode``, the closed loop's
knobs) and :class:`BenchmarkParams` (``navigate.benchmark``, the navigation benchmark's draw of targets).

Apart from :mod:`.closed_loop` so the CLI and the benchmark read them without importing the physics (PyBullet).
Each is read by :func:`~room_pipeline.config.params.params_from_dict` (the project's one config reader); its
defaults equal ``conf/navigate/default.yaml`` (tests/test_conf_defaults.py).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from ..config.params import params_from_dict
from ..errors import ConfigError

POLICIES = ("depth", "darkest", "oracle")


@dataclasses.dataclass(frozen=True)
class EpisodeParams:
    """Closed-loop episode knobs (``navigate.episode``); lengths mm, speeds mm/s, times s."""

    policy: str = "depth"
    control_rate_hz: float = 10.0
    max_time_s: float = 60.0
    speed_mm_s: float = 5.0             # insertion speed limit (the trajectory stage's default advance speed)
    image_px: int = 64                  # square image the policy sees (the planner sub-samples nothing more)
    fov_deg: float = 85.0               # horizontal field of view (the render config's default)
    lookahead_mm: float = 4.0           # tip target this far along the plan / route / dark ray
    start_offset_mm: float = 60.0       # start this far down the trachea (>= the 50 mm bending segment)
    reach_fraction: float = 0.5         # success: this far along the target branch
    wrong_branch_mm: float = 5.0        # failure: this far into a branch off the route
    wrong_branch_gap_mm: float = 1.0    # ... and this much nearer its centreline than the route's (sibling
                                        # centrelines run together for mm after a bifurcation)
    stall_time_s: float = 8.0           # failure: < 1 mm of insertion gained over this long
    physics_step_s: float = 0.0025      # replaces simulate.time_step_s: 10 ms tunnelled at a carina (57 N); at 5 ms
                                        # the bending segment wedged in a narrow gen-3 branch chattered (joint speeds
                                        # 15-35 rad/s) until it diverged and went through the wall (session 14)
    slow_factor: float = 0.5            # insertion speed factor while the plan is not collision-free
    dark_quantile: float = 0.05         # darkest: pixels at or below this luminance quantile form the dark regions
    tip_control: str = "point"          # point: bend toward the look-ahead point; path: put the tip on the path;
                                        # aim: turn the view toward the point aim_mm along the plan / route / ray
    depth_target: str = "axis"          # depth policy's tip target: plan (lookahead_mm along the plan) | free_centre
                                        # (centre of the free lumen centre_depth_mm ahead, in the goal's opening)
    centre_depth_mm: float = 10.0
    axis_lead_mm: float = 15.0          # depth_target axis: the axis turns to the chosen child this far before the fork
    fork_child_mm: float = 40.0         # depth_target axis: while the commanded fork is seen nearer than this, the
                                        # tip target is the chosen child's centre (0: off; see closed_loop)
    fork_slow_mm: float = 0.0           # depth_target axis: insert at fork_slow_factor of the speed while a fork is seen
    fork_slow_factor: float = 1.0       # ... nearer than this (0: off)
    fork_child_deg: float = 0.0         # depth_target axis: the held child's centre is the tip target only while it lies
    fork_child_far_mm: float = 15.0     # ... within this angle of the view axis or nearer (planar depth) than this; else
                                        # the axis target (a child seen far and far aside: the branch curves); 0 deg: off
    sideways_deg: float = 45.0          # depth policy's point control: the roll is not held for a target more than
                                        # this off the held bending plane (0: always held near zero bending; the
                                        # oracle and darkest keep it held: with 45 the oracle took a wrong branch
                                        # on 3 of patient_000's 5 benchmark targets)
    aim_mm: float = 20.0                # aim: how far along the plan / route / dark ray the view is turned to
    retract_force_n: float = 0.0        # > 0: retract while the last period's peak contact force exceeded this (N)
    retract_mm_s: float = 2.0           # ... at this speed
    forward_trace: bool = False         # the shaft's path grows by the tip's advance along its view only
    shaft: str = "lumen"                # lumen: the bending segment's base follows the airway's centreline (a passive
                                        # shaft conforming to the lumen); trace: the tip's own swept path
    seed: int = 0                       # actuation delay draw (and the planner's samples: planner.seed + step)

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ConfigError(f"navigate.episode.policy must be one of {POLICIES}, got {self.policy!r}")
        for name in ("control_rate_hz", "max_time_s", "speed_mm_s", "fov_deg", "lookahead_mm", "start_offset_mm",
                     "wrong_branch_mm", "stall_time_s", "physics_step_s", "retract_mm_s", "aim_mm", "centre_depth_mm",
                     "axis_lead_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"navigate.episode.{name} must be > 0, got {v!r}")
        for name in ("wrong_branch_gap_mm", "retract_force_n", "sideways_deg", "fork_slow_mm", "fork_child_mm", "fork_slow_factor",
                     "fork_child_deg", "fork_child_far_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"navigate.episode.{name} must be >= 0, got {v!r}")
        if self.tip_control not in ("point", "path", "aim"):
            raise ConfigError(f"navigate.episode.tip_control must be point, path or aim, got {self.tip_control!r}")
        if self.depth_target not in ("plan", "free_centre", "axis"):
            raise ConfigError(f"navigate.episode.depth_target must be plan, free_centre or axis, got {self.depth_target!r}")
        if self.shaft not in ("trace", "lumen"):
            raise ConfigError(f"navigate.episode.shaft must be trace or lumen, got {self.shaft!r}")
        if self.image_px < 8:
            raise ConfigError("navigate.episode.image_px must be >= 8")
        if not 0 < self.reach_fraction <= 1 or not 0 < self.dark_quantile < 1:
            raise ConfigError("navigate.episode.reach_fraction must be in (0, 1], dark_quantile in (0, 1)")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "EpisodeParams":
        return params_from_dict(cls, d, "navigate.episode")


@dataclasses.dataclass(frozen=True)
class BenchmarkParams:
    """``navigate.benchmark`` (benchmarks/navigation.py): per patient, ``targets_per_patient`` branches of
    generation ``target_generation`` drawn with ``seed`` among the eligible ones, whose every route branch is at
    least ``min_route_radius_mm`` wide (mm)."""

    patients: tuple = ("patient_000", "patient_001")
    target_generation: int = 4
    targets_per_patient: int = 5
    min_route_radius_mm: float = 3.0
    seed: int = 0
    policies: tuple = ("depth", "oracle", "darkest")

    def __post_init__(self) -> None:
        if self.target_generation < 1 or self.targets_per_patient < 1:
            raise ConfigError("navigate.benchmark.target_generation and targets_per_patient must be >= 1")
        if not (math.isfinite(self.min_route_radius_mm) and self.min_route_radius_mm > 0):
            raise ConfigError(f"navigate.benchmark.min_route_radius_mm must be > 0, got {self.min_route_radius_mm!r}")
        bad = [p for p in self.policies if p not in POLICIES]
        if bad or not self.policies:
            raise ConfigError(f"navigate.benchmark.policies must be a non-empty subset of {POLICIES}, got "
                              f"{list(self.policies)!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "BenchmarkParams":
        return params_from_dict(cls, d, "navigate.benchmark")
