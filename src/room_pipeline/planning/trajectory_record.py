"""The planned trajectory record: :class:`Trajectory` (poses, timestamps, clearance, what was asked and
reached) and its serialisations (``trajectory.json``, ``timestamps.json``, TUM)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..conventions import metadata_block
from ..io.tum import tum_text
from .targets import TargetInfo


@dataclasses.dataclass
class Trajectory:
    """A timestamped camera path.

    Attributes:
        timestamps: (T,) seconds from 0 at ``rate_hz``.
        poses: (T, 4, 4) camera-to-world, OpenCV camera frame, world RAS+ metres.
        arclength: (T,) along the smoothed path, metres.
        branch_id: (T,) graph branch at each pose (nearest route vertex).
        clearance: (T,) ``-sdf`` at the camera centre, metres (distance to the wall).
        curvature: (T,) path curvature, 1/m.
        speed: (T,) advance speed, m/s.
        margin: (T,) required clearance, metres.
        target: :class:`TargetInfo`.
        kappa_max: the curvature bound used, 1/m.
        rate_hz: pose rate.
        max_curvature: max over the whole spline (checked every ~0.1 mm), 1/m.
        route_branches: graph branch ids from the root to the target.
        params: the :class:`TrajectoryParams` as a dict.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    arclength: np.ndarray
    branch_id: np.ndarray
    clearance: np.ndarray
    curvature: np.ndarray
    speed: np.ndarray
    margin: np.ndarray
    target: TargetInfo
    kappa_max: float
    rate_hz: float
    max_curvature: float
    route_branches: list
    params: dict = dataclasses.field(default_factory=dict)
    start: dict = dataclasses.field(default_factory=dict)
    path_poses: np.ndarray | None = None     # (T, 4, 4) the smoothed path's poses (rotation-minimising, no jitter)
    joints: np.ndarray | None = None         # (T, 3) joint plan [q1 m, q2 rad, q3 m] (joint_plan on)
    joint_plan: dict | None = None           # its report (planning/joint_plan.py)
    insertion_stop: dict | None = None       # where the insertion ended (trajectory.stop_at_wall; planning/insertion_stop.py)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @property
    def length(self) -> float:
        return float(self.arclength[-1])

    @property
    def duration(self) -> float:
        return float(self.timestamps[-1])

    @property
    def min_clearance(self) -> float:
        return float(self.clearance.min())

    def summary(self) -> dict:
        jp = {} if self.joint_plan is None else {
            "joint_plan_departure_median_mm": self.joint_plan["departure_from_path_mm"]["median"],
            "joint_plan_departure_max_mm": self.joint_plan["departure_from_path_mm"]["max"],
            "joint_plan_view_departure_median_deg": self.joint_plan["view_departure_from_path_deg"]["median"]}
        return {**jp, "frames": int(len(self.timestamps)), "duration_s": self.duration, "length_m": self.length,
                "max_curvature_per_m": float(self.max_curvature), "kappa_max_per_m": float(self.kappa_max),
                "min_clearance_m": self.min_clearance,
                "min_clearance_minus_margin_m": float((self.clearance - self.margin).min()),
                "route_branches": [int(b) for b in self.route_branches]}

    def to_dict(self) -> dict:
        """Content of ``sequence_YYY/metadata/trajectory.json``."""
        return {
            "description": "camera trajectory: timestamped 4x4 camera-to-world poses along the smoothed airway path",
            "conventions": metadata_block(),
            "units": {"timestamp": "s", "position": "m", "arclength": "m", "clearance": "m",
                      "margin": "m", "curvature": "1/m", "speed": "m/s", "rate": "Hz"},
            "pose": "4x4 camera-to-world; camera frame OpenCV (x right, y down, z forward = view direction); "
                    "world RAS+ metres",
            "orientation": ("view along the path tangent; roll by parallel transport (rotation-minimising frame); "
                            f"image up (camera -y) nearest world {self.params.get('image_up', 'anterior')} at the start")
                           + ("" if self.joints is None else
                              "; that is path_pose: pose is the forward kinematics of the joint plan q aimed at it "
                              "(joint_plan)"),
            "joint_plan": self.joint_plan,
            **({} if self.insertion_stop is None else {"insertion_stop": self.insertion_stop}),
            "rate_hz": float(self.rate_hz),
            "target": self.target.to_dict(),
            "start": self.start,
            "summary": self.summary(),
            "params": self.params,
            "frames": [{"index": i, "timestamp": float(self.timestamps[i]),
                        "pose": np.round(self.poses[i], 12).tolist(),
                        "arclength": float(self.arclength[i]), "branch_id": int(self.branch_id[i]),
                        "clearance": float(self.clearance[i]), "curvature": float(self.curvature[i]),
                        "speed": float(self.speed[i]),
                        **({} if self.path_poses is None else {"path_pose": np.round(self.path_poses[i], 12).tolist()}),
                        **({} if self.joints is None else {"q": [float(v) for v in self.joints[i]]})}
                       for i in range(len(self.timestamps))],
        }

    def to_tum(self) -> str:
        """TUM RGB-D trajectory text: ``timestamp tx ty tz qx qy qz qw`` per line (camera-to-world, m, s)."""
        return tum_text(self.timestamps, self.poses)


def timestamps_dict(traj: Trajectory) -> dict:
    """Content of ``timestamps.json``: frame index -> time in seconds."""
    return {"units": "s", "rate_hz": float(traj.rate_hz), "count": int(len(traj.timestamps)),
            "timestamps": [float(t) for t in traj.timestamps]}
