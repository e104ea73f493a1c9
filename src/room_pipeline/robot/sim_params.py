"""Parameters of the scope simulation (``conf/simulate/default.yaml``) and their validation.

No PyBullet here: the config is checked (``room`` validates every section before any stage) without
loading the physics engine.  :meth:`SimParams.from_dict` reads a config section the project's one way
(:func:`~room_pipeline.config.params.params_from_dict`: unknown keys, value types); ``__post_init__``
checks the ranges, the choices and, for a ``SimParams(...)`` built in code, the types too.
The model they parameterise: :mod:`~room_pipeline.robot.simulation` and
:mod:`~room_pipeline.robot.pybullet_adapter`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

from ..config.params import params_from_dict
from ..errors import ConfigError

INSERTION_MODELS = ("kinematic", "passive")
FRICTION_MODELS = ("switch", "dynamic")
TRACK_MODES = ("joints", "pose")


@dataclasses.dataclass
class SimParams:
    """Knobs of the simulation; field names are the keys of ``conf/simulate/default.yaml``."""

    seed: int = 0                           # actuation delay RNG seed
    time_step_s: float = 5e-3               # physics step (accurate against the converged physical-mass run)
    unstable_penetration_mm: float = 1.0    # a run deeper than this (or non-finite) is redone at half the step
    max_step_halvings: int = 2              # ... at most this many times
    solver_iterations: int = 10             # Bullet constraint-solver iterations per step
    solver_residual_threshold: float = 1.0e-7  # Bullet stops iterating when the squared impulse change is below this
    contact_slop_mm: float = 0.01           # Bullet leaves penetration up to this uncorrected (linear slop), mm
    n_links: int = 10                       # capsules in the bending segment
    scope_diameter_mm: float = 5.0          # outer diameter (Ambu aScope 4 Regular: 5.0 mm)
    linear_density_kg_m: float = 0.03       # scope mass per length
    mass_scale: float = 10.0                # simulated mass = physical x this (1 = physical)
    mass_damping_per_s: float = 0.0         # implicit: extra joint damping alpha * M (mass-proportional), 1/s
    joint_integration: str = "implicit"     # implicit (stable PD) | explicit spring-damper torques | motor (velocity motors)
    inertia_factor: float = 0.0             # explicit: link rotational inertia >= factor * joint_damping * time_step_s
    joint_stiffness: float = 2.0e-2         # N m/rad, bending-segment joints
    joint_damping: float = 5.0e-4           # N m s/rad
    contact_stiffness: float = 4.0e3        # k_n, N/m (on the scope only)
    contact_damping: float = 0.8            # c_n, N s/m
    friction_static: float = 0.3            # mu_s
    friction_dynamic: float = 0.25          # mu_d
    friction_model: str = "switch"          # switch | dynamic
    slip_speed_mm_s: float = 0.5            # switch: a link faster than this slides (mu_d)
    gravity_m_s2: float = 0.0               # along world -z (RAS+ inferior); 0: off
    actuation: bool = True                  # apply the actuation non-idealities
    delay_max_s: float = 0.1                # command delay ~ U(0, delay_max_s), one draw per sequence
    gain_q1: float = 0.05                   # q1 gain error at |q1| = q1_max
    gain_q2: float = 0.05                   # q2 gain error at |q2| = 2 pi
    insertion_model: str = "kinematic"      # kinematic | passive
    passive_shaft_length_mm: float = 40.0   # passive: free shaft length behind the bending segment
    passive_shaft_links: int = 8
    shaft_bending_stiffness_nm2: float = 2.0e-3  # passive shaft EI, N m^2 (joint k = EI / link length)
    wall_margin_mm: float = 0.0             # Bullet collision margin of the airway mesh (inflates it; Bullet: 1 mm)
    crop_mesh: bool = False                 # load only the triangles near the scope (no gain measured)
    crop_radius_mm: float = 12.0
    crop_rebuild_mm: float = 3.0
    collision_corridor_mm: float = 15.0     # wall = triangles within this of the route (0: whole mesh); see _simulate
    max_body_faces: int = 100_000           # faces per Bullet wall body (createCollisionShape: 131,708 ok, 200,914 failed)
    settle_time_s: float = 0.3              # settling before the first frame
    ik_direction_weight_mm: float | None = None  # weight of the view direction in IK (null: l)
    controller_iterations: int = 2
    mass_matrix_every: int = 4              # implicit: refresh the joint-space mass matrix every n steps
    max_rate_q1_mm_s: float = 16.0          # actuator rate limits of the command: tendon differential, mm/s
    max_rate_q2_deg_s: float = 90.0         # axial rotation, deg/s
    max_rate_q3_mm_s: float = 50.0          # insertion, mm/s
    roll_hold_q1_fraction: float = 0.05     # controller: q2 held while the IK's |q1| < this x q1_max
    roll_free_q1_fraction: float = 0.15     # ... and follows the IK's q2 fully above this (linear between)
    roll_hold_project: bool = False         # held: bend projected on the held plane | false: full bend, nearer half-plane
    insertion_by_velocity: bool = True      # the base's velocity is set each step (friction sees the slip)
    track: str = "joints"                   # joints: command the plan's joint trajectory (if it has one) | pose: IK

    def __post_init__(self) -> None:
        ints = ("seed", "solver_iterations", "n_links", "passive_shaft_links", "controller_iterations",
                "mass_matrix_every", "max_step_halvings", "max_body_faces")
        for name in ints:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or float(v) != int(v):
                raise ConfigError(f"simulate.{name} must be an integer, got {v!r}")
            setattr(self, name, int(v))
        for name, f in self.__dataclass_fields__.items():
            if name in ints or f.type in ("str", "bool") or name == "ik_direction_weight_mm":
                continue
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"simulate.{name} must be a finite number, got {v!r}")
            setattr(self, name, float(v))
        if self.ik_direction_weight_mm is not None:
            v = self.ik_direction_weight_mm
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"simulate.ik_direction_weight_mm must be >= 0 or null, got {v!r}")
        for name in ("actuation", "crop_mesh", "insertion_by_velocity", "roll_hold_project"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"simulate.{name} must be true or false, got {getattr(self, name)!r}")
        if self.track not in TRACK_MODES:
            raise ConfigError(f"simulate.track must be one of {', '.join(TRACK_MODES)}, got {self.track!r}")
        if self.insertion_model not in INSERTION_MODELS:
            raise ConfigError(f"simulate.insertion_model must be one of {', '.join(INSERTION_MODELS)}, "
                              f"got {self.insertion_model!r}")
        if self.joint_integration not in ("implicit", "explicit", "motor"):
            raise ConfigError(f"simulate.joint_integration must be implicit, explicit or motor, "
                              f"got {self.joint_integration!r}")
        if self.friction_model not in FRICTION_MODELS:
            raise ConfigError(f"simulate.friction_model must be one of {', '.join(FRICTION_MODELS)}, "
                              f"got {self.friction_model!r}")
        positive = ("time_step_s", "solver_iterations", "scope_diameter_mm", "linear_density_kg_m", "mass_scale",
                    "joint_stiffness", "joint_damping", "contact_stiffness", "passive_shaft_length_mm",
                    "passive_shaft_links", "shaft_bending_stiffness_nm2", "crop_radius_mm", "crop_rebuild_mm",
                    "controller_iterations", "mass_matrix_every", "max_rate_q1_mm_s", "max_rate_q2_deg_s",
                    "max_rate_q3_mm_s", "unstable_penetration_mm", "max_body_faces")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"simulate.{name} must be > 0, got {getattr(self, name)}")
        for name in ("collision_corridor_mm", "max_step_halvings", "wall_margin_mm", "inertia_factor", "mass_damping_per_s", "contact_damping",
                     "solver_residual_threshold", "contact_slop_mm", "friction_static", "friction_dynamic", "slip_speed_mm_s", "gravity_m_s2",
                     "delay_max_s", "gain_q1", "gain_q2", "settle_time_s",
                     "roll_hold_q1_fraction", "roll_free_q1_fraction"):
            if getattr(self, name) < 0:
                raise ConfigError(f"simulate.{name} must be >= 0, got {getattr(self, name)}")
        if self.n_links < 2:
            raise ConfigError(f"simulate.n_links must be >= 2, got {self.n_links}")
        if self.friction_dynamic > self.friction_static:
            raise ConfigError(f"simulate.friction_dynamic ({self.friction_dynamic}) must be <= friction_static "
                              f"({self.friction_static})")
        if self.roll_free_q1_fraction < self.roll_hold_q1_fraction:
            raise ConfigError(f"simulate.roll_free_q1_fraction ({self.roll_free_q1_fraction}) must be >= "
                              f"roll_hold_q1_fraction ({self.roll_hold_q1_fraction})")
        if self.time_step_s > 0.05:
            raise ConfigError(f"simulate.time_step_s must be <= 0.05 s, got {self.time_step_s}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SimParams":
        """Build from a config section; an unknown key raises :class:`ConfigError` naming it."""
        return params_from_dict(cls, d, "simulate")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
