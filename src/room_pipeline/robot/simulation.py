"""Physics simulation of the ROOM scope in the airway: drive the simulated scope along a planned
trajectory (:func:`simulate`) and record what it did (:class:`SimResult`, :func:`robot_config`).

Domain code: the PyBullet world (the scope multibody, the contact law, the wall bodies; its model is
described there) is :mod:`~room_pipeline.robot.pybullet_adapter`, the only module that imports PyBullet;
the parameters are :mod:`~room_pipeline.robot.sim_params`, the shaft's path
:mod:`~room_pipeline.robot.route`, the choice of wall faces :mod:`~room_pipeline.robot.wall`.

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
    links, :func:`~room_pipeline.robot.probes.friction_probe`; the sequences peak below 0.05 N) chatters at x10 / 5 ms (normal
    force ~13 N, i.e. ~3 mm deep): past ``unstable_penetration_mm`` :func:`simulate` redoes the run
    at half the step, where that press is stable (mu_d recovered, tests/test_simulation.py).  Gravity is off by default
    (``gravity_m_s2: 0``: the scope's weight, ~0.3 g per bending segment, is carried by the
    handle and the airway; the kinematic model has none).

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
    0 mm/s; :func:`~room_pipeline.robot.probes.friction_probe` measures mu_d both ways, tests/test_simulation.py).

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
import math
import time

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError, RoomError
from ..geometry.rotations import log_so3_batch
from ..geometry.rotations import rz as _rz
from ..io.mesh import Mesh
from ..progress import progress
from .actuation import Actuator, CommandSignal, sample_delay
from .controller import IKController, rate_limit
from .kinematics import ScopeGeometry, camera_roll, straight_roll_change
from .pybullet_adapter import PhysicsError, ScopeSim, engine_version
from .route import Route
from .sim_params import SimParams
from .wall import crop_faces, route_corridor


BACKBONE_SHAFT_STEP_M = 0.01    #: m between the backbone points recorded on the shaft behind the body (few: small file)


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
        "simulator": {"engine": "pybullet", "version": engine_version(), "mode": "DIRECT", "time_step": dt,
                      "instability": f"penetration > {params.unstable_penetration_mm} mm or non-finite: rerun at half "
                                     f"the step, at most {params.max_step_halvings} times (simulation.json: "
                                     "report.time_step_s, report.unstable_runs)",
                      "solver_iterations": params.solver_iterations, "gravity": params.gravity_m_s2,
                      "wall_collision_margin": params.wall_margin_mm * 1e-3,
                      "mesh_crop": ({"radius": params.crop_radius_mm * 1e-3, "rebuild": params.crop_rebuild_mm * 1e-3}
                                    if params.crop_mesh else None)},
    }


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
        backbones: per frame the backbone (P_k, 3), world m, entrance to tip: the shaft on the route behind the body
            every :data:`BACKBONE_SHAFT_STEP_M`, then the body's link vertices as PyBullet has them, last the tip.
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
    backbones: list | None = None

    def to_dict(self) -> dict:
        return {"description": "simulated scope: per-frame actual tip camera pose, joints, contact, tracking, backbone",
                "units": {"timestamp": "s", "pose": "4x4 camera-to-world, world RAS+ m", "q": "[q1 m, q2 rad, q3 m]",
                          "contact_force": "N", "penetration": "m", "tracking_error": "m / rad",
                          "backbone": f"(P, 3) world RAS+ m to 1 um, entrance to tip: shaft on the route every "
                                      f"{BACKBONE_SHAFT_STEP_M * 1e3:g} mm, then the body's link vertices to the tip"},
                "report": self.report,
                "frames": [{"index": i, "timestamp": float(self.timestamps[i]),
                            "tip_pose": np.round(self.tip_poses[i], 12).tolist(),
                            "q_cmd": self.q_cmd[i].tolist(), "q_act": self.q_act[i].tolist(),
                            "contact_force_n": float(self.contact_force_n[i]),
                            "penetration_m": float(self.penetration_m[i]),
                            "tracking_error_m": float(self.tracking_error_m[i]),
                            "tracking_error_rad": float(self.tracking_error_rad[i]),
                            **({"backbone": np.round(self.backbones[i], 6).tolist()} if self.backbones else {})}
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
    except (PhysicsError, np.linalg.LinAlgError, FloatingPointError, ValueError, ZeroDivisionError,
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
    passive = params.insertion_model == "passive"
    Lp = params.passive_shaft_length_mm * 1e-3 if passive else 0.0
    sim = ScopeSim(params, geometry, n_shaft=params.passive_shaft_links if passive else 0, shaft_length=Lp)
    try:
        return _drive(sim, route, trajectory, mesh, params, geometry, t_wall0)
    finally:
        sim.close()


def _drive(sim: ScopeSim, route: Route, trajectory, mesh: Mesh | None, params: SimParams, geometry: ScopeGeometry,
           t_wall0: float) -> SimResult:
    """The run loop of :func:`_simulate` in the world ``sim`` (closed by the caller)."""
    poses = np.asarray(trajectory.poses, float)
    ts = np.asarray(trajectory.timestamps, float)
    T = len(ts)
    passive = params.insertion_model == "passive"
    Lp = params.passive_shaft_length_mm * 1e-3 if passive else 0.0
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
    # the wall near the route only (see pybullet_adapter.py, Airway): faces within collision_corridor_mm of
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
    backbones: list = [None] * T

    def record(k: int, t: float) -> None:
        nonlocal dev_max
        tip[k] = sim.tip_pose()
        q_cmd[k] = signal(t)
        q_act[k] = act(t)
        force[k], pen[k] = sim.contacts()
        body = sim.sample_points()
        backbones[k] = np.vstack([route.polyline(float(q_act[k, 2]) - Lp, BACKBONE_SHAFT_STEP_M), body])
        if corridor_tree is not None:
            dev_max = max(dev_max, float(corridor_tree.query(body)[0].max()))

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
                     penetration_m=pen, tracking_error_m=err_m, tracking_error_rad=err_rad, report=report,
                     backbones=backbones)


def _advance(B: np.ndarray, ds: float) -> np.ndarray:
    T = B.copy()
    T[:3, 3] = B[:3, 3] + ds * B[:3, 2]
    return T
