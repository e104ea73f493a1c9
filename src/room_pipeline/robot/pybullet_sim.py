"""Physics simulation of the ROOM scope in the airway (PyBullet, DIRECT mode).

The only module of room-pipeline that imports :mod:`pybullet`.

Scope model
    The bending segment (length ``geometry.l``) is a chain of ``n_links`` rigid capsules
    (diameter ``scope_diameter_mm``; default 5.0 mm, the Ambu aScope 4 Regular) joined at
    the polygon vertices ``s_i = i l / n`` by **two revolute joints** (about the link's x,
    the bending axis, and y, out of plane).  The chain's base is the bending-segment base,
    rolled by ``q2`` (the whole scope rotates), so the nominal constant-curvature shape of
    :mod:`~room_pipeline.robot.kinematics` is ``theta_x = kappa(q1) l / n`` at every inner
    vertex and ``kappa l / (2 n)`` at the base (the polygon's vertices then lie on the arc;
    its chords are ``l/n`` long, a relative length error ``(kappa l/n)^2 / 24``), ``theta_y = 0``.
    The tip camera sits at the last vertex; its view direction is the last chord turned by
    half the last vertex's actual joint angles (the discrete tangent there).
    Every joint is a spring-damper about its target (``joint_stiffness``, ``joint_damping``),
    applied as a torque each step (motors off: velocity control with force 0).  Default
    (``joint_integration: implicit``): stable PD (Tan, Liu & Turk 2011): the spring acts at
    ``theta + dt*omega`` and the damper at the velocity predicted with the joint-space mass
    matrix, so the stiff, light chain is stable at a 5 ms step.  ``explicit``:
    ``tau = k (theta* - theta) - c dtheta/dt`` with raised link inertia (``inertia_factor``).

Units and stability
    SI (metres, kg, s).  With the scope's real mass (0.03 kg/m: 0.15 g per 5 mm link) the stable
    PD keeps free space exact but the chain in contact needs tiny steps: the physical-mass run
    converges only near 0.5 ms (1 ms differs from 0.5 ms by p95 0.9 mm at the recorded 10 Hz
    states) and tunnels the wall at 5 ms.  The motion is quasi-static (mm/s; joint time constant
    damping/stiffness = 25 ms), so the mass is **scaled** (``mass_scale``, default x10) at a 5 ms
    step: its 10 Hz tip states match the converged physical-mass run within p95 0.03 mm / 0.6 deg
    (benchmarks/results/simulation_converged.md; x30 or x100 at 10 ms are p95 0.3-1 mm off).
    Optional mass-proportional damping ``alpha M`` (``mass_damping_per_s``, default 0) vanishes
    as ``mass_scale -> 1`` (with x100 it added ~0.3 s of lag).  The joint-space mass matrix of
    the stable PD is refreshed every ``mass_matrix_every`` steps (default 4, measured there).
    A press ten times harder than the default sequences' largest contact (0.5 N spread over the
    links, :func:`friction_probe`; the sequences peak below 0.05 N) chatters at x10 / 5 ms (normal
    force ~13 N, i.e. ~3 mm deep): past ``unstable_penetration_mm`` :func:`simulate` redoes the run
    at half the step, where that press is stable (mu_d recovered, tests/test_simulation.py).  Gravity is off by default
    (``gravity_m_s2: 0``: the scope's weight, ~0.3 g per bending segment, is carried by the
    handle and the airway; the kinematic model has none).

Contact
    Soft normal contact ``f = k_n delta + c_n d(delta)/dt`` via
    ``changeDynamics(contactStiffness=k_n, contactDamping=c_n)`` **on the scope's links only**
    (set on both bodies the two springs act in series and the penetration doubles).
    Coulomb friction: Bullet has one coefficient per pair, the *product* of the two bodies'
    ``lateralFriction``; the wall carries 1.0 and each scope link ``mu``.  With
    ``friction_model: switch`` a link's ``mu`` is ``mu_s`` while its speed is below
    ``slip_speed_mm_s`` and ``mu_d`` while it slides (re-evaluated every frame); with
    ``dynamic`` it is always ``mu_d`` (slightly more slip than the static law allows).

Airway
    A static concave triangle mesh (``GEOM_MESH`` with ``GEOM_FORCE_CONCAVE_TRIMESH``) of the
    lumen surface; the scope is inside it (triangle contacts are two-sided, so the wall
    pushes the scope back into the lumen).  Its Bullet collision margin is ``wall_margin_mm``
    (default 0): Bullet's own default (1 mm) inflates every triangle by the margin, i.e. the
    lumen was 1 mm narrower than the mesh (a capsule rests 1 mm above a triangle floor), and
    the margin also enlarges every triangle query, doubling the step time deep in a narrow
    branch (benchmarks/results/simulation.md).  Only the wall near the route is loaded
    (``collision_corridor_mm``): every triangle whose bounding sphere reaches within that
    distance of the planned path, extended back by the bending segment and the passive shaft;
    the run records how far inside the corridor the scope's surface stayed
    (``corridor_margin_mm``) and is redone with the corridor doubled if that went negative
    (three times, then the whole mesh).  The wall goes to Bullet in bodies of at most
    ``max_body_faces`` triangles (cut along the route), so no mesh size reaches
    ``createCollisionShape``'s limit (131,708 faces passed, 200,914 failed).  With ``crop_mesh`` only the triangles whose
    centroid is within ``crop_radius_mm`` of the scope are loaded, and the crop is rebuilt
    when any scope point has moved more than ``crop_rebuild_mm`` since the last build.

Insertion (``insertion_model``)
    ``kinematic``: the proximal shaft is constrained to the planned route: the
    bending-segment base moves kinematically along the trajectory's path at arclength
    ``q3`` (extended straight before its start and after its end), its frame the path's
    rotation-minimising frame rolled by ``q2``.  ``passive``: only the route point at
    ``q3 - passive_shaft_length_mm`` is kinematic; the last ``passive_shaft_length_mm`` of
    the shaft is a chain of stiffer passive links (bending stiffness
    ``shaft_bending_stiffness_nm2``, straight at rest) that follows the lumen through contact.
    With ``insertion_by_velocity`` (default) the base is not only placed but given the velocity
    of that motion each step (linear and angular, from its pose one step earlier), so the links
    carry the insertion speed: the contact solver sees the axial slip, friction acts along the
    shaft and the static/dynamic switch reads sliding (teleporting the base left every link at
    0 mm/s; :func:`friction_probe` measures mu_d both ways, tests/test_simulation.py).

Time stepping per 10 Hz frame
    The controller (:mod:`~room_pipeline.robot.controller`) computes, at frame ``k-1``, the
    command for waypoint ``k``; the command ramps linearly to it over the frame; the
    actuator (:mod:`~room_pipeline.robot.actuation`) delays it and applies its gain; every
    physics step sets the base pose and the joint targets from the actual ``q``.  Near zero
    bending the controller holds ``q2`` (``roll_hold_q1_fraction``, ``roll_free_q1_fraction``:
    :func:`~room_pipeline.robot.controller.regularise_roll`), and the report scores the camera
    roll against the plan (``camera_roll_deg``).

Errors
    :func:`simulate` turns bad trajectories and meshes (:func:`check_inputs`) and any failure
    inside PyBullet, the controller or the linear algebra into one :class:`InputError` line.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import time
from typing import Any, Mapping

import numpy as np
import pybullet as p
from scipy.spatial import cKDTree

from ..errors import ConfigError, InputError, RoomError
from ..io.mesh import Mesh
from ..progress import progress
from .actuation import Actuator, CommandSignal, sample_delay
from .controller import IKController, rate_limit
from .kinematics import ScopeGeometry, camera_roll, kappa, straight_roll_change  # noqa: F401 (re-exported)

INSERTION_MODELS = ("kinematic", "passive")
FRICTION_MODELS = ("switch", "dynamic")
TRACK_MODES = ("joints", "pose")


# --------------------------------------------------------------------------- parameters


@dataclasses.dataclass
class SimParams:
    """Knobs of the simulation; field names are the keys of ``conf/simulate/default.yaml``."""

    seed: int = 0                           # actuation delay RNG seed
    time_step_s: float = 5e-3               # physics step (accurate against the converged physical-mass run)
    unstable_penetration_mm: float = 1.0    # a run deeper than this (or non-finite) is redone at half the step
    max_step_halvings: int = 2              # ... at most this many times
    solver_iterations: int = 10             # Bullet constraint-solver iterations per step
    n_links: int = 10                       # capsules in the bending segment
    scope_diameter_mm: float = 5.0          # outer diameter (Ambu aScope 4 Regular: 5.0 mm)
    linear_density_kg_m: float = 0.03       # scope mass per length
    mass_scale: float = 10.0                # simulated mass = physical x this (1 = physical)
    mass_damping_per_s: float = 0.0         # implicit: extra joint damping alpha * M (mass-proportional), 1/s
    joint_integration: str = "implicit"     # implicit (stable PD) | explicit spring-damper torques
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
        if self.joint_integration not in ("implicit", "explicit"):
            raise ConfigError(f"simulate.joint_integration must be implicit or explicit, got {self.joint_integration!r}")
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
        for name in ("collision_corridor_mm", "max_step_halvings", "wall_margin_mm", "inertia_factor", "mass_damping_per_s", "contact_damping", "friction_static", "friction_dynamic", "slip_speed_mm_s", "gravity_m_s2",
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
        d = dict(d or {})
        known = [f.name for f in dataclasses.fields(cls)]
        for key in d:
            if key not in known:
                raise ConfigError(f"simulate: unknown config key '{key}' (known: {', '.join(known)})")
        return cls(**d)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def robot_config(params: SimParams, geometry: ScopeGeometry) -> dict:
    """Model parameters for ``sequence_YYY/metadata/robot_config.json`` (SI units)."""
    dt = params.time_step_s
    return {
        "description": "ROOM continuum bronchoscope: 3-DoF constant-curvature kinematics and the PyBullet "
                       "multibody used to simulate it",
        "units": {"length": "m", "angle": "rad", "time": "s", "mass": "kg", "force": "N"},
        "kinematics": {"model": "constant curvature, kappa = -q1 / (2 gamma l); r(0) = [0, 0, q3], R(0) = Rot_z(q2)",
                       "bending_length": geometry.l, "gamma": geometry.gamma, "q1_max": geometry.q1_max,
                       "kappa_max": geometry.kappa_max, "theta_max": geometry.theta_max,
                       "joints": ["q1 tendon differential (m)", "q2 axial rotation (rad)", "q3 insertion (m)"]},
        "scope": {"outer_diameter": params.scope_diameter_mm * 1e-3, "n_links": params.n_links,
                  "link_length": geometry.l / params.n_links, "linear_density": params.linear_density_kg_m,
                  "joints_per_vertex": "2 revolute (bending axis x, out-of-plane y)",
                  "joint_stiffness": params.joint_stiffness, "joint_damping": params.joint_damping,
                  "link_rotational_inertia": params.inertia_factor * params.joint_damping * dt,
                  "camera": "at the tip vertex; view direction = last chord turned by half the last joint angles"},
        "contact": {"normal_law": "f = max(0, k_n delta + c_n d delta/dt), on the scope only",
                    "k_n": params.contact_stiffness, "c_n": params.contact_damping,
                    "mu_s": params.friction_static, "mu_d": params.friction_dynamic,
                    "friction_model": params.friction_model, "slip_speed": params.slip_speed_mm_s * 1e-3},
        "actuation": {"enabled": params.actuation, "delay": f"U(0, {params.delay_max_s}) s, one draw per sequence",
                      "q1": f"q1cmd(t - dt) (1 + {params.gain_q1} |q1cmd| / q1_max)",
                      "q2": f"q2cmd(t - dt) (1 + {params.gain_q2} |q2cmd| / 2 pi)", "q3": "q3cmd(t - dt)",
                      "seed": params.seed},
        "insertion_model": params.insertion_model,
        "passive_shaft": ({"length": params.passive_shaft_length_mm * 1e-3, "links": params.passive_shaft_links,
                           "bending_stiffness": params.shaft_bending_stiffness_nm2}
                          if params.insertion_model == "passive" else None),
        "simulator": {"engine": "pybullet", "version": p.getAPIVersion(), "mode": "DIRECT", "time_step": dt,
                      "instability": f"penetration > {params.unstable_penetration_mm} mm or non-finite: rerun at half "
                                     f"the step, at most {params.max_step_halvings} times (simulation.json: "
                                     "report.time_step_s, report.unstable_runs)",
                      "solver_iterations": params.solver_iterations, "gravity": params.gravity_m_s2,
                      "wall_collision_margin": params.wall_margin_mm * 1e-3,
                      "mesh_crop": ({"radius": params.crop_radius_mm * 1e-3, "rebuild": params.crop_rebuild_mm * 1e-3}
                                    if params.crop_mesh else None)},
    }


# --------------------------------------------------------------------------- small geometry helpers


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis x angle, rad) of the rotation matrix ``R``."""
    c = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    a = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if a < 1e-6:
        return 0.5 * v
    if math.pi - a < 1e-6:   # half turn: axis from the symmetric part
        i = int(np.argmax(np.diag(R)))
        axis = R[:, i] + np.eye(3)[i]
        return a * axis / np.linalg.norm(axis)
    return a / (2.0 * math.sin(a)) * v


def _quat_to_mat(qt) -> np.ndarray:
    return np.array(p.getMatrixFromQuaternion(qt)).reshape(3, 3)


def _mat_to_quat(R: np.ndarray):
    # Shepperd's method (x, y, z, w), deterministic
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    if m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        return (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    if m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        return ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
    return ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)


class Route:
    """The path the shaft follows: a trajectory's positions with tangent frames, by arclength.

    ``frame(s)``: 4x4 world pose at arclength ``s`` (m, 0 at the first pose): z = path tangent,
    x/y = the trajectory's rotation-minimising frame made orthogonal to it; extended straight
    (constant frame) before the start and after the end.
    """

    def __init__(self, positions: np.ndarray, arclength: np.ndarray, rotations: np.ndarray) -> None:
        s, idx = np.unique(np.asarray(arclength, float), return_index=True)
        P = np.asarray(positions, float)[idx]
        R = np.asarray(rotations, float)[idx]
        if len(s) < 2:
            raise InputError("the trajectory needs at least two distinct positions to simulate")
        t = np.gradient(P, s, axis=0) if len(s) > 2 else np.repeat((P[1:] - P[:1]) / (s[1] - s[0]), 2, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        x = R[:, :, 0] - np.einsum("ij,ij->i", R[:, :, 0], t)[:, None] * t
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        self.s, self.P, self.t, self.x = s, P, t, x

    @classmethod
    def from_trajectory(cls, trajectory) -> "Route":
        """The shaft's path: the trajectory's ``path_poses`` (a joint-space plan's path) when it has them,
        else its camera poses."""
        P = getattr(trajectory, "path_poses", None)
        P = trajectory.poses if P is None else P
        return cls(P[:, :3, 3], trajectory.arclength, P[:, :3, :3])

    def frame(self, s: float) -> np.ndarray:
        S = self.s
        if s <= S[0]:
            P, t, x = self.P[0] + (s - S[0]) * self.t[0], self.t[0], self.x[0]
        elif s >= S[-1]:
            P, t, x = self.P[-1] + (s - S[-1]) * self.t[-1], self.t[-1], self.x[-1]
        else:
            i = int(np.searchsorted(S, s, side="right")) - 1
            w = (s - S[i]) / (S[i + 1] - S[i])
            P = (1 - w) * self.P[i] + w * self.P[i + 1]
            t = (1 - w) * self.t[i] + w * self.t[i + 1]
            t = t / math.sqrt(t @ t)
            x = (1 - w) * self.x[i] + w * self.x[i + 1]
        x = x - (x @ t) * t
        x = x / math.sqrt(x @ x)
        T = np.eye(4)
        T[:3, 0] = x
        T[:3, 1] = (t[1] * x[2] - t[2] * x[1], t[2] * x[0] - t[0] * x[2], t[0] * x[1] - t[1] * x[0])
        T[:3, 2] = t
        T[:3, 3] = P
        return T

    def frames(self, s, roll=None) -> np.ndarray:
        """:meth:`frame` at every arclength of ``s`` (shape (n,)), each rolled about its z by ``roll``
        (rad, (n,), optional): (n, 4, 4).  One vectorised pass (the physics loop's per-step base poses)."""
        s = np.asarray(s, float).reshape(-1)
        S = self.s
        i = np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(S) - 2)
        w = ((s - S[i]) / (S[i + 1] - S[i]))[:, None]
        P = (1 - w) * self.P[i] + w * self.P[i + 1]
        t = (1 - w) * self.t[i] + w * self.t[i + 1]
        x = (1 - w) * self.x[i] + w * self.x[i + 1]
        for mask, k, s0 in ((s <= S[0], 0, S[0]), (s >= S[-1], -1, S[-1])):
            if mask.any():
                P[mask] = self.P[k] + (s[mask] - s0)[:, None] * self.t[k]
                t[mask] = self.t[k]
                x[mask] = self.x[k]
        t = t / np.sqrt(np.einsum("ij,ij->i", t, t))[:, None]
        x = x - np.einsum("ij,ij->i", x, t)[:, None] * t
        x = x / np.sqrt(np.einsum("ij,ij->i", x, x))[:, None]
        y = np.cross(t, x)
        if roll is not None:
            c, sn = np.cos(roll)[:, None], np.sin(roll)[:, None]
            x, y = c * x + sn * y, c * y - sn * x
        T = np.zeros((len(s), 4, 4))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, t, P
        T[:, 3, 3] = 1.0
        return T


def log_so3_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of the rotation matrices ``R`` (n, 3, 3) (:func:`_log_so3`, vectorised;
    the angle from atan2, accurate at small angles; a half turn falls back to the scalar form)."""
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sn = 0.5 * np.sqrt(np.einsum("ij,ij->i", v, v))
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)
    a = np.arctan2(sn, c)
    f = np.where(a < 1e-6, 0.5, a / (2.0 * np.where(a < 1e-6, 1.0, sn)))
    out = f[:, None] * v
    for k in np.flatnonzero(math.pi - a < 1e-6):
        out[k] = _log_so3(R[k])
    return out


def crop_faces(mesh: Mesh, points: np.ndarray, radius: float, tree: cKDTree | None = None) -> np.ndarray:
    """Sorted indices of the faces whose centroid is within ``radius`` of any of ``points``."""
    if tree is None:
        tree = cKDTree(mesh.vertices[mesh.faces].mean(axis=1))
    hits = tree.query_ball_point(np.asarray(points, float).reshape(-1, 3), radius)
    if len(hits) == 0:
        return np.zeros(0, dtype=np.int64)
    idx = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
    return idx


def split_faces(vertices: np.ndarray, faces: np.ndarray, max_faces: int,
                order: np.ndarray | None = None) -> list[np.ndarray]:
    """Face indices cut into consecutive runs of ``order`` of at most ``max_faces`` each, each run sorted.

    ``order`` (a permutation of the faces) defaults to the faces sorted by centroid along the
    mesh's longest bounding-box axis (stable), so every run is a compact slab of the surface.
    Equal sizes (ceil(n / ceil(n / max_faces))).  Deterministic.
    """
    n = len(faces)
    if n == 0:
        return []
    if n <= max_faces:
        return [np.arange(n)]
    if order is None:
        cen = vertices[faces].mean(axis=1)
        axis = int(np.argmax(cen.max(axis=0) - cen.min(axis=0)))
        order = np.argsort(cen[:, axis], kind="stable")
    order = np.asarray(order, np.int64)
    k = -(-n // max_faces)
    size = -(-n // k)
    return [np.sort(order[i:i + size]) for i in range(0, n, size)]


def route_corridor(mesh: Mesh, samples: np.ndarray, radius: float) -> np.ndarray:
    """The wall near a route: every face whose bounding sphere (about its centroid) reaches within
    ``radius`` of a route sample point, so no part of a kept face's neighbourhood is lost to a
    large triangle whose centroid lies farther away.

    ``samples``: (N, 3) points along the route, in order (m).  Returns the face indices ordered
    by the index of their nearest sample (i.e. along the route; stable, deterministic).
    """
    V = mesh.vertices[mesh.faces]
    cen = V.mean(axis=1)
    reach = np.linalg.norm(V - cen[:, None], axis=2).max(axis=1)
    d, j = cKDTree(np.asarray(samples, float).reshape(-1, 3)).query(
        cen, distance_upper_bound=radius + float(reach.max(initial=0.0)))
    keep = np.flatnonzero(np.isfinite(d) & (d - reach <= radius))
    return keep[np.argsort(j[keep], kind="stable")]


# --------------------------------------------------------------------------- the PyBullet world


class ScopeSim:
    """One PyBullet DIRECT world: the scope multibody and (optionally) the airway mesh.

    Args:
        params, geometry: the model.
        n_shaft: passive shaft links behind the bending segment (0: none, the kinematic model).
        shaft_length: their total length, m.
    """

    def __init__(self, params: SimParams, geometry: ScopeGeometry, n_shaft: int = 0, shaft_length: float = 0.0) -> None:
        self.params, self.geometry = params, geometry
        self.cid = p.connect(p.DIRECT)
        c = self.cid
        p.resetSimulation(physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=params.time_step_s, numSolverIterations=params.solver_iterations,
                                    numSubSteps=0, deterministicOverlappingPairs=1, physicsClientId=c)
        p.setGravity(0.0, 0.0, -params.gravity_m_s2, physicsClientId=c)
        self.radius = 0.5 * params.scope_diameter_mm * 1e-3
        self.n_shaft, self.n_bend = int(n_shaft), params.n_links
        self.ds = geometry.l / params.n_links
        self.ds_shaft = shaft_length / n_shaft if n_shaft else 0.0
        self.wall = -1
        self.wall_shape = -1
        self.wall_faces = 0
        self.walls: list[int] = []
        self.max_body_faces = int(params.max_body_faces)
        self._build_scope()

    # ---- construction
    def _build_scope(self) -> None:
        c, prm = self.cid, self.params
        lengths = [self.ds_shaft] * self.n_shaft + [self.ds] * self.n_bend
        masses, shapes, positions, parents, axes, inertias, ipos, k, d = [], [], [], [], [], [], [], [], []
        I_art = prm.inertia_factor * prm.joint_damping * prm.time_step_s
        k_shaft = prm.shaft_bending_stiffness_nm2 / self.ds_shaft if self.n_shaft else 0.0
        d_shaft = k_shaft * prm.joint_damping / prm.joint_stiffness
        I_shaft = prm.inertia_factor * d_shaft * prm.time_step_s
        prev_len = 0.0
        for i, L in enumerate(lengths):
            shaft = i < self.n_shaft
            m = prm.linear_density_kg_m * prm.mass_scale * L
            I_phys = m * (3 * self.radius ** 2 + L ** 2) / 12.0
            I = max(I_phys, I_shaft if shaft else I_art)
            shape = p.createCollisionShape(p.GEOM_CAPSULE, radius=self.radius, height=L,
                                           collisionFramePosition=[0.0, 0.0, 0.5 * L], physicsClientId=c)
            # dummy link carrying the x joint at the vertex, then the capsule on the y joint
            masses += [1e-3 * m, m]
            shapes += [-1, shape]
            positions += [[0.0, 0.0, prev_len], [0.0, 0.0, 0.0]]
            parents += [2 * i if i > 0 else 0, 2 * i + 1]
            axes += [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
            inertias += [[1e-3 * I] * 3, [I] * 3]
            ipos += [[0.0, 0.0, 0.0], [0.0, 0.0, 0.5 * L]]
            kk, dd = (k_shaft, d_shaft) if shaft else (prm.joint_stiffness, prm.joint_damping)
            k += [kk, kk]
            d += [dd, dd]
            prev_len = L
        n = len(masses)
        self.body = p.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
            basePosition=[0.0, 0.0, 0.0], baseOrientation=[0.0, 0.0, 0.0, 1.0],
            linkMasses=masses, linkCollisionShapeIndices=shapes, linkVisualShapeIndices=[-1] * n,
            linkPositions=positions, linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
            linkInertialFramePositions=ipos, linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
            linkParentIndices=parents, linkJointTypes=[p.JOINT_REVOLUTE] * n, linkJointAxis=axes,
            physicsClientId=c)
        self.joints = list(range(n))
        self.capsules = list(range(1, n, 2))
        self.k = np.array(k)
        self.d = np.array(d)
        for j in self.joints:
            p.changeDynamics(self.body, j, localInertiaDiagonal=inertias[j], linearDamping=0.0, angularDamping=0.0,
                             jointDamping=0.0, physicsClientId=c)
        for j in self.capsules:
            p.changeDynamics(self.body, j, contactStiffness=prm.contact_stiffness, contactDamping=prm.contact_damping,
                             lateralFriction=prm.friction_dynamic if prm.friction_model == "dynamic"
                             else prm.friction_static, restitution=0.0, physicsClientId=c)
        self._mu = np.full(len(self.capsules), -1.0)
        p.setJointMotorControlArray(self.body, self.joints, p.VELOCITY_CONTROL, forces=[0.0] * n, physicsClientId=c)
        self.targets = np.zeros(n)
        self._q1_targets = None
        self._bend_pattern = np.zeros(n)          # joint targets per unit vertex angle: half at the base vertex
        self._bend_pattern[2 * self.n_shaft] = 0.5
        self._bend_pattern[2 * self.n_shaft + 2::2] = 1.0
        self._phi_per_q1 = float(kappa(1.0, self.geometry)) * self.ds     # vertex angle per unit q1 (kappa is linear)
        self.base_pose = np.eye(4)
        self.implicit = prm.joint_integration == "implicit"
        self.dt = prm.time_step_s
        self._pd_gain = None
        self._D_joint = np.diag(self.d)
        self._since_mass = 0

    def close(self) -> None:
        if self.cid is not None and self.cid >= 0:
            p.disconnect(physicsClientId=self.cid)
            self.cid = -1

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            if getattr(self, "cid", -1) >= 0 and p.isConnected(self.cid):
                p.disconnect(physicsClientId=self.cid)
        except Exception:
            pass

    # ---- airway
    def set_wall(self, vertices: np.ndarray, faces: np.ndarray, order: np.ndarray | None = None) -> None:
        """Replace the static airway mesh (concave triangle meshes, two-sided contacts).

        Any size: the faces go to Bullet in bodies of at most ``max_body_faces`` each
        (``createCollisionShape`` fails above ~131k-200k faces, ../shared/DESIGN.md), cut
        in ``order`` (face indices, e.g. sorted along the route) or, by default, along the
        mesh's longest extent, so each body is one compact piece of the wall.
        """
        c = self.cid
        for b in self.walls:
            p.removeBody(b, physicsClientId=c)
        self.walls = []
        self.wall = -1
        self.wall_shape = -1   # (Bullet refuses to remove a shape still referenced; it is freed with the world)
        self.wall_faces = 0
        self.add_wall(vertices, faces, order)

    def add_wall(self, vertices: np.ndarray, faces: np.ndarray, order: np.ndarray | None = None) -> None:
        """Add static wall bodies (as :meth:`set_wall`) after those already loaded."""
        c = self.cid
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        vertices = np.asarray(vertices, float)
        self.wall_faces += int(len(faces))
        if len(faces) == 0:
            return
        for part in split_faces(vertices, faces, self.max_body_faces, order):
            F = faces[part]
            used, inv = np.unique(F.ravel(), return_inverse=True)
            try:
                shape = p.createCollisionShape(p.GEOM_MESH, vertices=vertices[used].tolist(),
                                               indices=inv.astype(np.int64).tolist(),
                                               flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=c)
            except p.error:
                shape = -1
            if shape < 0:
                raise ConfigError(f"PyBullet refused a wall body of {len(F)} faces "
                                  f"(simulate.max_body_faces = {self.max_body_faces}); lower it")
            body = p.createMultiBody(0.0, shape, -1, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
            p.changeDynamics(body, -1, lateralFriction=1.0, restitution=0.0,
                             collisionMargin=self.params.wall_margin_mm * 1e-3, physicsClientId=c)
            self.walls.append(body)
        self.wall, self.wall_shape = self.walls[0], -1

    def add_box(self, half_extents, position) -> int:
        """A static box (contact-law checks); friction 1.0 so the pair's coefficient is the scope's."""
        c = self.cid
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half_extents), physicsClientId=c)
        b = p.createMultiBody(0.0, shape, -1, list(position), [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
        p.changeDynamics(b, -1, lateralFriction=1.0, restitution=0.0, physicsClientId=c)
        self.wall = b
        self.walls = [b]
        return b

    # ---- state
    def set_base(self, pose: np.ndarray, prev_pose: np.ndarray | None = None, h: float = 0.0,
                 reset: bool = True) -> None:
        """Place the (fixed) base at ``pose``; with ``prev_pose`` and ``h`` also give it the velocity
        that moved it from ``prev_pose`` in ``h`` seconds (linear and angular, world frame).

        ``resetBasePositionAndOrientation`` zeroes the base velocity (joint velocities are kept), so
        without the velocity every link of a scope inserted at 5 mm/s reads 0 mm/s: the contact
        solver sees no slip along the shaft and the friction switch always reads static.
        The step integrates the base by that velocity, so it is placed at ``prev_pose`` and reaches
        ``pose`` at the end of the next step.  ``reset=False`` (with ``prev_pose``): only the velocity
        is set, the base being where the last step took it (Bullet integrates the fixed base too;
        its error over a 10 Hz frame is second order, |v| |w| h^2 per step, and the caller re-places
        it each frame); ``resetBasePositionAndOrientation`` costs more than a contact step.
        """
        self.base_pose = pose
        c = self.cid
        at = pose if prev_pose is None or h <= 0.0 else prev_pose
        if reset or at is pose:
            p.resetBasePositionAndOrientation(self.body, at[:3, 3].tolist(), _mat_to_quat(at[:3, :3]),
                                              physicsClientId=c)
        if at is not pose:
            v = (pose[:3, 3] - prev_pose[:3, 3]) / h
            w = _log_so3(pose[:3, :3] @ prev_pose[:3, :3].T) / h
            p.resetBaseVelocity(self.body, v.tolist(), w.tolist(), physicsClientId=c)

    def set_base_velocity(self, pose: np.ndarray, v, w) -> None:
        """:meth:`set_base` with ``reset=False`` and the velocity already known (``v``, ``w``: lists, world
        frame): the base is where the last step took it; ``pose`` is where this step takes it."""
        self.base_pose = pose
        p.resetBaseVelocity(self.body, v, w, physicsClientId=self.cid)

    def set_bend(self, q1: float) -> None:
        """Joint targets of the bending segment for tendon differential ``q1`` (in its rolled base)."""
        if q1 == self._q1_targets:
            return
        self._q1_targets = q1
        self.targets = (self._phi_per_q1 * q1) * self._bend_pattern

    def reset_joints(self) -> None:
        """Joints at their targets, at rest."""
        for j in self.joints:
            p.resetJointState(self.body, j, float(self.targets[j]), 0.0, physicsClientId=self.cid)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        js = p.getJointStates(self.body, self.joints, physicsClientId=self.cid)
        return np.array([j[0] for j in js]), np.array([j[1] for j in js])

    def step(self, n: int = 1) -> None:
        c, body, joints = self.cid, self.body, self.joints
        nj = len(joints)
        for i in range(n):
            js = p.getJointStates(body, joints, physicsClientId=c)
            th = np.array([j[0] for j in js])
            om = np.array([j[1] for j in js])
            if self.implicit:
                # stable PD (Tan, Liu & Turk 2011): spring at theta + dt*omega, damper at the predicted
                # velocity omega + dt*acc, acc = (M + dt D)^-1 (e - D omega) from the joint-space mass
                # matrix (bias and contact ignored), i.e. tau = e - D (omega + dt acc) = M (M + dt D)^-1 (e - D omega):
                # one cached matrix, refreshed every `mass_matrix_every` steps (a LAPACK solve per step cost
                # more than the physics step itself: OpenBLAS thread start-up on tiny matrices).
                # Mass-proportional damping alpha*M (mass_damping_per_s) keeps the mass-scaled chain overdamped.
                if self._pd_gain is None or self._since_mass >= self.params.mass_matrix_every:
                    M = np.fromiter(itertools.chain.from_iterable(
                        p.calculateMassMatrix(body, th.tolist(), physicsClientId=c)), float, nj * nj).reshape(nj, nj)
                    alpha = self.params.mass_damping_per_s
                    D = self._D_joint + alpha * M if alpha else self._D_joint
                    self._pd_gain = M @ np.linalg.inv(M + self.dt * D)
                    self._D = D if alpha else None
                    self._since_mass = 0
                self._since_mass += 1
                r = self.k * (self.targets - th - self.dt * om) - (self.d * om if self._D is None else self._D @ om)
                tau = self._pd_gain @ r
            else:
                tau = self.k * (self.targets - th) - self.d * om
            p.setJointMotorControlArray(body, joints, p.TORQUE_CONTROL, forces=tau.tolist(), physicsClientId=c)
            p.stepSimulation(physicsClientId=c)

    def link_frames(self) -> list[np.ndarray]:
        """World 4x4 frames of the capsule links (at their proximal vertex)."""
        out = []
        for s in p.getLinkStates(self.body, self.capsules, computeForwardKinematics=1, physicsClientId=self.cid):
            T = np.eye(4)
            T[:3, :3] = _quat_to_mat(s[5])
            T[:3, 3] = s[4]
            out.append(T)
        return out

    def tip_pose(self) -> np.ndarray:
        """Tip camera pose (4x4 camera-to-world; OpenCV frame = the kinematic tip frame)."""
        s = p.getLinkState(self.body, self.capsules[-1], computeForwardKinematics=1, physicsClientId=self.cid)
        R = _quat_to_mat(s[5])
        last = len(self.joints) - 2
        a = p.getJointStates(self.body, [last, last + 1], physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, 3] = np.array(s[4]) + self.ds * R[:, 2]
        T[:3, :3] = R @ _rx(0.5 * a[0][0]) @ _ry(0.5 * a[1][0])
        return T

    def bend_base_pose(self) -> np.ndarray:
        """World pose of the bending-segment base (rolled by q2): the first bending vertex's parent frame."""
        if self.n_shaft == 0:
            return self.base_pose.copy()
        s = p.getLinkState(self.body, 2 * self.n_shaft - 1, computeForwardKinematics=1, physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, :3] = _quat_to_mat(s[5])
        T[:3, 3] = np.array(s[4]) + self.ds_shaft * T[:3, 2]
        return T

    def sample_points(self) -> np.ndarray:
        """Scope backbone points (every vertex and the tip), world, m."""
        F = self.link_frames()
        pts = [T[:3, 3] for T in F]
        pts.append(F[-1][:3, 3] + self.ds * F[-1][:3, 2])
        return np.array(pts)

    def contacts(self) -> tuple[float, float]:
        """(sum of normal forces N, max penetration m) between the scope and the wall."""
        cps = [cp for w in self.walls for cp in p.getContactPoints(self.body, w, physicsClientId=self.cid)]
        if not cps:
            return 0.0, 0.0
        f = float(sum(cp[9] for cp in cps))
        pen = float(max(0.0, max(-cp[8] for cp in cps)))
        return f, pen

    def update_friction(self) -> None:
        """friction_model 'switch': mu_s for links slower than slip_speed_mm_s, mu_d for the others."""
        prm = self.params
        if prm.friction_model != "switch":
            return
        states = p.getLinkStates(self.body, self.capsules, computeLinkVelocity=1, physicsClientId=self.cid)
        v_base = 0.0
        for i, s in enumerate(states):
            speed = float(np.linalg.norm(s[6])) - v_base
            mu = prm.friction_dynamic if speed > prm.slip_speed_mm_s * 1e-3 else prm.friction_static
            if mu != self._mu[i]:
                p.changeDynamics(self.body, self.capsules[i], lateralFriction=mu, physicsClientId=self.cid)
                self._mu[i] = mu

    def energy(self) -> float:
        """Kinetic energy of the links plus the joint springs' potential energy, J."""
        c = self.cid
        e = 0.0
        states = p.getLinkStates(self.body, self.joints, computeLinkVelocity=1, computeForwardKinematics=1,
                                 physicsClientId=c)
        for j, s in enumerate(states):
            info = p.getDynamicsInfo(self.body, j, physicsClientId=c)
            m, I = info[0], np.array(info[2])
            v, w = np.array(s[6]), np.array(s[7])
            R = _quat_to_mat(s[1])
            wl = R.T @ w
            e += 0.5 * m * float(v @ v) + 0.5 * float(wl @ (I * wl))
        th, _ = self.joint_state()
        e += 0.5 * float(np.sum(self.k * (th - self.targets) ** 2))
        return e


def contact_probe(params: SimParams, force_n: float, time_s: float = 1.0) -> tuple[float, float]:
    """Penetration (m) and normal force (N) of one scope link pressed on a static wall by ``force_n``.

    The wall is a triangle-mesh floor built like the airway (concave trimesh, friction 1.0,
    collision margin ``wall_margin_mm``); the link is a free capsule (diameter
    ``scope_diameter_mm``, length ``l / n_links``) with the scope's contact settings (soft
    contact on the link only), lying on it, no gravity; the force acts at its centre for
    ``time_s``.  Penetration is measured against the mesh's true plane (z = 0), so a margin
    that inflates the wall shows up as negative penetration.  The link's mass is the simulated
    one (physical x ``mass_scale``), as in the scope.  The check of the contact law.
    """
    c = p.connect(p.DIRECT)
    try:
        p.setPhysicsEngineParameter(fixedTimeStep=params.time_step_s, numSolverIterations=params.solver_iterations,
                                    numSubSteps=0, deterministicOverlappingPairs=1, physicsClientId=c)
        p.setGravity(0.0, 0.0, 0.0, physicsClientId=c)
        floor = p.createCollisionShape(p.GEOM_MESH, vertices=[[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0],
                                                              [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]],
                                       indices=[0, 1, 2, 0, 2, 3], flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                       physicsClientId=c)
        b = p.createMultiBody(0.0, floor, -1, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
        p.changeDynamics(b, -1, lateralFriction=1.0, restitution=0.0, collisionMargin=params.wall_margin_mm * 1e-3,
                         physicsClientId=c)
        r = 0.5 * params.scope_diameter_mm * 1e-3
        L = 0.05 / params.n_links
        cap = p.createCollisionShape(p.GEOM_CAPSULE, radius=r, height=L, physicsClientId=c)
        s = p.createMultiBody(params.linear_density_kg_m * params.mass_scale * L, cap, -1, [0.0, 0.0, r],
                              p.getQuaternionFromEuler([0.5 * math.pi, 0.0, 0.0]), physicsClientId=c)
        p.changeDynamics(s, -1, contactStiffness=params.contact_stiffness, contactDamping=params.contact_damping,
                         lateralFriction=params.friction_dynamic, restitution=0.0, linearDamping=0.0,
                         angularDamping=0.0, physicsClientId=c)
        for _ in range(int(round(time_s / params.time_step_s))):
            pos = p.getBasePositionAndOrientation(s, physicsClientId=c)[0]
            p.applyExternalForce(s, -1, [0.0, 0.0, -force_n], pos, p.WORLD_FRAME, physicsClientId=c)
            p.stepSimulation(physicsClientId=c)
        z = p.getBasePositionAndOrientation(s, physicsClientId=c)[0][2]
        fn = sum(cp[9] for cp in p.getContactPoints(s, b, physicsClientId=c))
        return r - z, float(fn)
    finally:
        p.disconnect(physicsClientId=c)


def friction_probe(params: SimParams, geometry: ScopeGeometry, normal_force_n: float, speed_mm_s: float = 5.0,
                   time_s: float = 2.0, by_velocity: bool | None = None) -> dict:
    """Push the straight scope along a flat wall at a known normal load and measure the friction.

    The bending segment lies on a triangle-mesh floor (built like the airway: concave trimesh,
    friction 1.0, margin ``wall_margin_mm``), its axis along world x; ``normal_force_n`` is
    spread evenly over its links (pressing them on the floor), and the base is inserted along
    the axis at ``speed_mm_s`` the way :func:`simulate` moves it (``by_velocity``: default
    ``insertion_by_velocity``), the friction switch re-evaluated every 0.1 s as there.  Over the
    second half of ``time_s``: ``mu`` = |sum of the contacts' friction forces| / sum of their
    normal forces (the pair's coefficient, Bullet's product of the two bodies' ``lateralFriction``),
    ``normal_n`` that sum, ``slip_mm_s`` the links' mean speed along the axis and
    ``dynamic_fraction`` the share of (link, frame) pairs the switch put on ``mu_d``.
    """
    by_velocity = params.insertion_by_velocity if by_velocity is None else bool(by_velocity)
    sim = ScopeSim(params, geometry)
    c = sim.cid
    try:
        sim.set_wall(np.array([[-1.0, -0.5, 0.0], [1.0, -0.5, 0.0], [1.0, 0.5, 0.0], [-1.0, 0.5, 0.0]]),
                     np.array([[0, 1, 2], [0, 2, 3]]))
        base = np.eye(4)
        base[:3, :3] = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])   # z (axis) = world x
        base[:3, 3] = [0.0, 0.0, sim.radius]
        sim.set_base(base)
        sim.set_bend(0.0)
        sim.reset_joints()
        dt = params.time_step_s
        n = int(round(time_s / dt))
        per_frame = max(1, int(round(0.1 / dt)))
        f_per_link = normal_force_n / len(sim.capsules)
        fric, normal, slip, dyn = np.zeros(3), 0.0, [], []
        for i in range(n):
            if i % per_frame == 0:
                sim.update_friction()
                dyn.extend(np.isclose(sim._mu, params.friction_dynamic) if params.friction_model == "switch"
                           else [True] * len(sim.capsules))
            nxt = sim.base_pose.copy()
            nxt[0, 3] += speed_mm_s * 1e-3 * dt
            sim.set_base(nxt, sim.base_pose if by_velocity else None, dt)
            for j in sim.capsules:
                pos = p.getLinkState(sim.body, j, computeForwardKinematics=1, physicsClientId=c)[0]
                p.applyExternalForce(sim.body, j, [0.0, 0.0, -f_per_link], pos, p.WORLD_FRAME, physicsClientId=c)
            sim.step(1)
            if i >= n // 2:
                for cp in p.getContactPoints(sim.body, sim.wall, physicsClientId=c):
                    normal += cp[9]
                    fric += cp[10] * np.array(cp[11]) + cp[12] * np.array(cp[13])
                states = p.getLinkStates(sim.body, sim.capsules, computeLinkVelocity=1, physicsClientId=c)
                slip.append(np.mean([s[6][0] for s in states]))
        m = n - n // 2
        return {"mu": float(np.linalg.norm(fric) / normal) if normal > 0 else 0.0, "normal_n": normal / m,
                "slip_mm_s": float(np.mean(slip)) * 1e3, "dynamic_fraction": float(np.mean(dyn))}
    finally:
        sim.close()


def settle_free(q, params: SimParams, geometry: ScopeGeometry, steps: int | None = None,
                from_straight: bool = True) -> np.ndarray:
    """Tip pose (base frame) of the free scope at ``q`` after settling: the check against ``fk``.

    The base is placed at ``[0, 0, q3]`` rolled by ``q2``; no actuation non-idealities.  With
    ``from_straight`` the segment starts straight and at rest and the joint springs bend it
    (``steps`` default: ``settle_time_s``); otherwise it starts at the targets.
    """
    sim = ScopeSim(params, geometry)
    try:
        q = np.asarray(q, float)
        base = np.eye(4)
        base[:3, :3] = _rz(q[1])
        base[:3, 3] = [0.0, 0.0, q[2]]
        sim.set_base(base)
        if not from_straight:
            sim.set_bend(q[0])
        sim.reset_joints()
        sim.set_bend(q[0])
        if steps is None:
            steps = int(round(max(params.settle_time_s, 0.05) / params.time_step_s))
        sim.step(steps)
        return sim.tip_pose()
    finally:
        sim.close()


# --------------------------------------------------------------------------- the sequence


@dataclasses.dataclass
class SimResult:
    """Per-frame record of a simulated sequence (frames of the trajectory, 10 Hz).

    Attributes:
        timestamps: (T,) s.
        tip_poses: (T, 4, 4) actual tip camera pose, camera-to-world (OpenCV frame, world RAS+ m).
        q_cmd: (T, 3) commanded joints [q1 m, q2 rad, q3 m] at the frame time.
        q_act: (T, 3) actual joints (delay and gain applied).
        contact_force_n: (T,) sum of the wall's normal forces on the scope, N.
        penetration_m: (T,) largest penetration of the scope into the wall, m.
        tracking_error_m: (T,) |actual - planned| camera position, m.
        tracking_error_rad: (T,) angle between the actual and planned view directions, rad.
        report: summary (errors, wall time, steps, realtime factor, mesh crops, delay).
    """

    timestamps: np.ndarray
    tip_poses: np.ndarray
    q_cmd: np.ndarray
    q_act: np.ndarray
    contact_force_n: np.ndarray
    penetration_m: np.ndarray
    tracking_error_m: np.ndarray
    tracking_error_rad: np.ndarray
    report: dict

    def to_dict(self) -> dict:
        return {"description": "simulated scope: per-frame actual tip camera pose, joints, contact and tracking error",
                "units": {"timestamp": "s", "pose": "4x4 camera-to-world, world RAS+ m", "q": "[q1 m, q2 rad, q3 m]",
                          "contact_force": "N", "penetration": "m", "tracking_error": "m / rad"},
                "report": self.report,
                "frames": [{"index": i, "timestamp": float(self.timestamps[i]),
                            "tip_pose": np.round(self.tip_poses[i], 12).tolist(),
                            "q_cmd": self.q_cmd[i].tolist(), "q_act": self.q_act[i].tolist(),
                            "contact_force_n": float(self.contact_force_n[i]),
                            "penetration_m": float(self.penetration_m[i]),
                            "tracking_error_m": float(self.tracking_error_m[i]),
                            "tracking_error_rad": float(self.tracking_error_rad[i])}
                           for i in range(len(self.timestamps))]}


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def simulate(trajectory, mesh: Mesh | None, params: SimParams | None = None,
             geometry: ScopeGeometry | None = None) -> SimResult:
    """Drive the simulated scope along ``trajectory``: see :func:`_simulate`.

    BLAS is limited to one thread meanwhile: the loop does thousands of tiny (20x20) matrix
    operations, for which OpenBLAS's thread hand-off cost ~40 % of the run time here.

    A run that goes unstable (penetration deeper than ``unstable_penetration_mm``, or a
    non-finite pose) is redone with half the time step, at most ``max_step_halvings`` times;
    the report says which step was used (``time_step_s``) and lists the runs given up.

    Raises:
        InputError: a trajectory or mesh the physics cannot use (non-finite, misshaped, timestamps
            not increasing, face indices out of range), a failure inside PyBullet or the controller,
            or a run still non-finite after every step halving: one line naming what failed.
    """
    from threadpoolctl import threadpool_limits

    params = params or SimParams()
    check_inputs(trajectory, mesh)
    given_up = []
    widened = []
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(params.max_step_halvings + 1):
            res = _simulate_or_fail(trajectory, mesh, params, geometry)
            # the scope strayed so far from the route that it may have reached wall left out of the
            # corridor: redo with the corridor doubled (at most three times, then the whole mesh)
            while (res.report["mesh"] or {}).get("corridor_margin_mm", 0.0) < 0.0:
                widened.append({"corridor_mm": params.collision_corridor_mm,
                                "corridor_margin_mm": res.report["mesh"]["corridor_margin_mm"],
                                "wall_time_s": res.report["wall_time_s"]})
                params = dataclasses.replace(params, collision_corridor_mm=(
                    2.0 * params.collision_corridor_mm if len(widened) < 3 else 0.0))
                res = _simulate_or_fail(trajectory, mesh, params, geometry)
            stable = (np.all(np.isfinite(res.tip_poses))
                      and res.report["penetration_mm"]["max"] <= params.unstable_penetration_mm)
            if stable or len(given_up) == params.max_step_halvings:
                break
            given_up.append({"time_step_s": params.time_step_s, "penetration_mm_max": res.report["penetration_mm"]["max"],
                             "wall_time_s": res.report["wall_time_s"]})
            params = dataclasses.replace(params, time_step_s=0.5 * params.time_step_s)
    if not np.all(np.isfinite(res.tip_poses)):
        raise InputError(f"simulate: the scope's pose went non-finite even at time step {params.time_step_s} s "
                         f"(after {len(given_up)} halvings; simulate.max_step_halvings)")
    res.report["unstable_runs"] = given_up
    res.report["corridor_widened"] = [{k: v for k, v in w.items() if k != "wall_time_s"} for w in widened]
    if given_up or widened:       # the speed of the whole call, retries included
        res.report["wall_time_s"] += sum(g["wall_time_s"] for g in given_up + widened)
        res.report["realtime_factor"] = res.report["duration_s"] / res.report["wall_time_s"]
    return res


def check_inputs(trajectory, mesh: Mesh | None) -> None:
    """Raise :class:`InputError` (one line) for a trajectory or mesh the physics cannot use."""
    try:
        ts = np.asarray(trajectory.timestamps, float)
        poses = np.asarray(trajectory.poses, float)
        arc = np.asarray(trajectory.arclength, float)
    except (AttributeError, TypeError, ValueError) as exc:
        raise InputError(f"simulate: unreadable trajectory ({exc})") from None
    T = len(ts)
    if ts.ndim != 1 or T < 2:
        raise InputError(f"simulate: the trajectory needs at least 2 frames, got {T}")
    if poses.shape != (T, 4, 4) or arc.shape != (T,):
        raise InputError(f"simulate: trajectory poses must be ({T}, 4, 4) and arclength ({T},), "
                         f"got {poses.shape} and {arc.shape}")
    for name, a in (("timestamps", ts), ("poses", poses), ("arclength", arc)):
        if not np.all(np.isfinite(a)):
            raise InputError(f"simulate: trajectory {name} contain non-finite values")
    if np.any(np.diff(ts) <= 0):
        raise InputError(f"simulate: trajectory timestamps must increase (first bad frame "
                         f"{int(np.argmax(np.diff(ts) <= 0)) + 1})")
    R = poses[:, :3, :3]
    if np.max(np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3))) > 1e-4:
        raise InputError("simulate: trajectory poses must have orthonormal rotations")
    if mesh is not None:
        V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
            raise InputError("simulate: the collision mesh's vertices must be finite (N, 3)")
        if F.size and (F.ndim != 2 or F.shape[1] != 3 or F.min() < 0 or F.max() >= len(V)):
            raise InputError(f"simulate: the collision mesh's faces must index its {len(V)} vertices")


def _simulate_or_fail(trajectory, mesh, params, geometry):
    """One run of :func:`_simulate`; a failure of the physics becomes one ``InputError`` line."""
    try:
        return _simulate(trajectory, mesh, params, geometry)
    except RoomError:
        raise
    except (p.error, np.linalg.LinAlgError, FloatingPointError, ValueError, ZeroDivisionError,
            OverflowError, MemoryError) as exc:
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"simulate: the physics failed at time step {params.time_step_s} s "
                         f"({type(exc).__name__}: {msg})") from None


def _simulate(trajectory, mesh: Mesh | None, params: SimParams | None = None,
              geometry: ScopeGeometry | None = None) -> SimResult:
    """Drive the simulated scope along ``trajectory`` (a planned :class:`Trajectory`) in ``mesh``.

    ``mesh``: the closed lumen surface (world RAS+ m), or None for free space.  The
    trajectory should start at least ``geometry.l`` inside the airway (the bending segment
    starts there; e.g. ``start_offset_mm >= 60``).
    """
    params = params or SimParams()
    geometry = geometry or ScopeGeometry()
    t_wall0 = time.perf_counter()
    route = Route.from_trajectory(trajectory)
    poses = np.asarray(trajectory.poses, float)
    ts = np.asarray(trajectory.timestamps, float)
    T = len(ts)
    passive = params.insertion_model == "passive"
    Lp = params.passive_shaft_length_mm * 1e-3 if passive else 0.0
    sim = ScopeSim(params, geometry, n_shaft=params.passive_shaft_links if passive else 0, shaft_length=Lp)
    rng = np.random.default_rng(params.seed)
    delay = sample_delay(rng, params.delay_max_s) if params.actuation else 0.0
    signal = CommandSignal()
    act = Actuator(signal, delay, geometry.q1_max, params.gain_q1, params.gain_q2, enabled=params.actuation)
    ctrl = IKController(geometry, None if params.ik_direction_weight_mm is None else params.ik_direction_weight_mm * 1e-3,
                        iterations=params.controller_iterations, roll_hold_q1_fraction=params.roll_hold_q1_fraction,
                        roll_free_q1_fraction=params.roll_free_q1_fraction, roll_project=params.roll_hold_project)
    max_rate = np.array([params.max_rate_q1_mm_s * 1e-3, math.radians(params.max_rate_q2_deg_s),
                         params.max_rate_q3_mm_s * 1e-3])
    use_crop = mesh is not None and params.crop_mesh
    face_tree = cKDTree(mesh.vertices[mesh.faces].mean(axis=1)) if use_crop else None
    crop_pts = None
    n_builds, faces_loaded = 0, []
    t_build = 0.0

    def load_wall() -> None:
        nonlocal crop_pts, n_builds, t_build
        t0 = time.perf_counter()
        pts = sim.sample_points()
        idx = crop_faces(mesh, pts, params.crop_radius_mm * 1e-3, face_tree)
        F = mesh.faces[idx]
        used, inv = np.unique(F.ravel(), return_inverse=True)
        sim.set_wall(mesh.vertices[used], inv.reshape(-1, 3))
        crop_pts = pts
        n_builds += 1
        faces_loaded.append(len(idx))
        t_build += time.perf_counter() - t0

    def apply(q: np.ndarray, h: float = 0.0, reset: bool = True) -> None:
        base = route.frame(q[2] - Lp)
        base[:3, :3] = base[:3, :3] @ _rz(q[1])
        prev = sim.base_pose if (params.insertion_by_velocity and h > 0.0) else None
        sim.set_base(base, prev, h, reset=reset)
        sim.set_bend(q[0])

    def base_frame_fn():
        if not passive:
            return route.frame
        B = sim.bend_base_pose()
        q_now = q_act_now
        B[:3, :3] = B[:3, :3] @ _rz(-q_now[1])
        return lambda q3: _advance(B, q3 - q_now[2])

    # the command: the plan's joints (a joint-space plan with the shaft on its path: the plan and the
    # controller's kinematic model are the same), else the pose IK on the planned camera poses
    plan_q = getattr(trajectory, "joints", None)
    use_joints = params.track == "joints" and plan_q is not None and not passive
    if use_joints:
        plan_q = np.asarray(plan_q, float)
        if plan_q.shape != (T, 3) or not np.all(np.isfinite(plan_q)):
            raise InputError(f"simulate: the trajectory's joint plan must be ({T}, 3) finite numbers")
    # initial command: straight-on estimate of the base, then the controller
    q_ref = np.array([0.0, 0.0, float(trajectory.arclength[0]) - geometry.l])
    q0 = plan_q[0].copy() if use_joints else ctrl.command(poses[0], q_ref, route.frame)
    signal.add(0.0, q0)
    q_act_now = act(0.0)
    apply(q_act_now)
    sim.reset_joints()
    # the wall near the route only (see module docstring, Airway): faces within collision_corridor_mm of
    # the planned path, extended back by the bending segment and the passive shaft (the scope's reach)
    R = params.collision_corridor_mm * 1e-3
    use_corridor = mesh is not None and not use_crop and R > 0
    corridor_tree, dev_max = None, 0.0
    if mesh is not None:
        if use_crop:
            load_wall()
        else:
            t0 = time.perf_counter()
            if use_corridor:
                step = 1e-3
                s_lo = float(trajectory.arclength[0]) - geometry.l - Lp - step
                s_hi = float(trajectory.arclength[-1]) + step
                samples = np.array([route.frame(s)[:3, 3] for s in np.arange(s_lo, s_hi + 0.5 * step, step)])
                along = route_corridor(mesh, samples, R)
                keep = np.sort(along)      # the mesh's own face order (Bullet's contact order follows it) ...
                F = mesh.faces[keep]
                corridor_tree = cKDTree(samples)
                sim.set_wall(mesh.vertices, F, order=np.searchsorted(keep, along))   # ... bodies cut along the route
                faces_loaded = [len(F)]
            else:
                sim.set_wall(mesh.vertices, mesh.faces)
                faces_loaded = [mesh.n_faces]
            t_build += time.perf_counter() - t0
            n_builds = 1
    dt = params.time_step_s
    steps = 0
    n_settle = int(round(params.settle_time_s / dt))
    sim.step(n_settle)
    steps += n_settle

    tip = np.zeros((T, 4, 4))
    q_cmd = np.zeros((T, 3))
    q_act = np.zeros((T, 3))
    force = np.zeros(T)
    pen = np.zeros(T)

    def record(k: int, t: float) -> None:
        nonlocal dev_max
        tip[k] = sim.tip_pose()
        q_cmd[k] = signal(t)
        q_act[k] = act(t)
        force[k], pen[k] = sim.contacts()
        if corridor_tree is not None:
            dev_max = max(dev_max, float(corridor_tree.query(sim.sample_points())[0].max()))

    record(0, 0.0)
    t_now = 0.0
    for k in progress(range(1, T), T - 1, "simulate"):
        if use_crop:
            pts = sim.sample_points()
            if np.max(np.linalg.norm(pts - crop_pts, axis=1)) > params.crop_rebuild_mm * 1e-3:
                load_wall()
        sim.update_friction()
        q_prev = signal(ts[k - 1])
        q_target = plan_q[k] if use_joints else ctrl.command(poses[k], q_prev, base_frame_fn())
        qk = rate_limit(q_target, q_prev, ts[k] - ts[k - 1], max_rate)
        signal.add(ts[k], qk)
        n = max(1, int(round((ts[k] - ts[k - 1]) / dt)))
        h = (ts[k] - ts[k - 1]) / n
        if params.insertion_by_velocity:
            # the frame's n base poses and velocities in one vectorised pass (the same formulas as apply():
            # each step's base velocity takes it from its pose one step earlier to its pose now)
            Q = act.batch(ts[k - 1] + np.arange(1, n + 1) * h)
            B = route.frames(Q[:, 2] - Lp, Q[:, 1])
            prev = np.concatenate([sim.base_pose[None], B[:-1]])
            Va = (B[:, :3, 3] - prev[:, :3, 3]) / h
            Wa = log_so3_batch(B[:, :3, :3] @ prev[:, :3, :3].transpose(0, 2, 1)) / h
            # Bullet keeps a base velocity from step to step: set it again only where it changes (a piece of the
            # route or of the command signal ends) by more than 1e-6 m/s or 1e-5 rad/s from the step before: the
            # base then strays at most n^2 h tol / 2 from its route within a frame (~1 um, 0.5 urad x 50 mm at
            # 20 steps of 5 ms) and is re-placed at the next frame
            changed = ((np.abs(np.diff(Va, axis=0)).max(axis=1) > 1e-6)
                       | (np.abs(np.diff(Wa, axis=0)).max(axis=1) > 1e-5)).tolist()
            V, W = Va.tolist(), Wa.tolist()
            sim.set_base(B[0], prev[0], h, reset=True)
            sim.set_bend(float(Q[0, 0]))
            sim.step(1)
            for j in range(1, n):
                if changed[j - 1]:
                    sim.set_base_velocity(B[j], V[j], W[j])
                else:
                    sim.base_pose = B[j]
                sim.set_bend(float(Q[j, 0]))
                sim.step(1)
            q_act_now = Q[-1]
        else:
            for j in range(n):
                t_now = ts[k - 1] + (j + 1) * h
                q_act_now = act(t_now)
                apply(q_act_now, h, reset=(j == 0))
                sim.step(1)
        steps += n
        record(k, ts[k])
    wall = time.perf_counter() - t_wall0
    n_bodies = len(sim.walls)
    sim.close()

    err_m = np.linalg.norm(tip[:, :3, 3] - poses[:, :3, 3], axis=1)
    err_rad = np.array([_angle(tip[i, :3, 2], poses[i, :3, 2]) for i in range(T)])
    roll = np.array([camera_roll(tip[i, :3, :3], poses[i, :3, :3]) for i in range(T)])
    roll_rel = np.unwrap(roll) - np.unwrap(roll)[0]
    duration = float(ts[-1] - ts[0]) if T > 1 else 0.0
    report = {
        "frames": int(T), "duration_s": duration, "steps": int(steps), "time_step_s": dt,
        "wall_time_s": wall, "realtime_factor": duration / wall if wall > 0 else float("inf"),
        "tracking_error_mm": {"median": float(np.median(err_m) * 1e3), "max": float(err_m.max() * 1e3),
                              "mean": float(err_m.mean() * 1e3)},
        "tracking_error_deg": {"median": float(np.degrees(np.median(err_rad))), "max": float(np.degrees(err_rad.max()))},
        "camera_roll_deg": {"description": "actual camera roll about its view axis relative to the planned camera, "
                                           "change since the first frame",
                            "median_abs": float(np.degrees(np.median(np.abs(roll_rel)))),
                            "max_abs": float(np.degrees(np.abs(roll_rel).max())),
                            "straight_stretch_change_max": float(np.degrees(straight_roll_change(
                                roll, q_act[:, 0], geometry.q1_max))),
                            "straight_stretch": "consecutive frames with |q1| < 0.05 q1_max"},
        "contact_force_n": {"max": float(force.max()), "mean": float(force.mean()),
                            "frames_in_contact": int((force > 0).sum())},
        "penetration_mm": {"max": float(pen.max() * 1e3)},
        "actuation_delay_s": delay,
        "insertion_model": params.insertion_model,
        "command": ("the plan's joint trajectory (trajectory.json frames[].q), rate-limited" if use_joints
                    else "pose IK on the planned camera poses (robot/controller.py)"),
        "mesh": None if mesh is None else {"faces": int(mesh.n_faces), "cropped": bool(use_crop), "builds": n_builds,
                                           "faces_loaded_mean": float(np.mean(faces_loaded)) if faces_loaded else 0.0,
                                           "build_time_s": t_build,
                                           "bodies": n_bodies,
                                           **({"corridor_mm": params.collision_corridor_mm,
                                               "corridor_faces": int(faces_loaded[0]),
                                               # how far inside the corridor the scope's surface stayed: R - (its
                                               # backbone's max distance from the route samples) - scope radius;
                                               # < 0: it may have reached a left-out triangle, so simulate() widens
                                               "corridor_margin_mm": (R - dev_max - sim.radius) * 1e3}
                                              if use_corridor else {})},
    }
    return SimResult(timestamps=ts.copy(), tip_poses=tip, q_cmd=q_cmd, q_act=q_act, contact_force_n=force,
                     penetration_m=pen, tracking_error_m=err_m, tracking_error_rad=err_rad, report=report)


def _advance(B: np.ndarray, ds: float) -> np.ndarray:
    T = B.copy()
    T[:3, 3] = B[:3, 3] + ds * B[:3, 2]
    return T
