"""Planning in the scope's joint space: a joint trajectory the simulated scope can execute.

Why
    The camera path of :mod:`~room_pipeline.planning.trajectory` is a smoothed centreline with the
    view along its tangent.  The scope cannot put its camera there: its shaft follows the route
    (``simulate.insertion_model: kinematic``: the bending-segment base rides the path at arclength
    ``q3``, tangent to it) and its 50 mm bending segment is one constant-curvature arc, which reaches
    a camera on the path looking along it only where the path between base and camera is itself a
    circular arc.  Tracking such a plan measured the kinematic model's unreachability, not the
    dynamics (``benchmarks/results/simulation_reachability.md``: median 2.6-3.1 mm, max 10.7-11.2 mm
    for the kinematic model alone).

What
    :func:`plan_joints` finds, frame by frame in time order, joints ``q_k = [q1 (m), q2 (rad),
    q3 (m)]`` of the kinematic model the simulator's controller uses
    (:func:`room_pipeline.robot.kinematics.fk` with the base at ``Route.frame(q3)`` rolled by
    ``q2``; :class:`room_pipeline.robot.pybullet_sim.Route` is the same object the simulator builds
    from the plan) minimising, in metres squared::

        |p(q) - c_k|^2 + w_dir^2 |d(q) - t_k|^2                      (camera on the path point c_k,
                                                                   looking along the tangent t_k)
        + w_dep^2 (|e_k - e_{k-1}|^2 + w_dir^2 |f_k - f_{k-1}|^2)     (departure e = p - c, f = d - t changes
                                                                   slowly: the camera moves with the path)
        + w_roll^2 wrap(q2 - q2_{k-1})^2 + w_bend^2 (q1 - q1_{k-1})^2   (roll continuity, smooth bending)
        + w_wall^2 sum_j max(0, need_j - clear_j)^2                  (lumen: the scope body)

    with ``clear_j = -sdf`` at ``n_body`` points along the bending segment's backbone (base to camera)
    and ``need_j = min(scope radius + body_clearance_mm, -sdf of the route at the same arclength)``:
    the scope's surface keeps ``body_clearance_mm`` from the wall, or at least the clearance the
    route itself has there.  Bounds: ``|q1| <= q1_max`` and the actuators' rate limits
    (``|q_k - q_{k-1}| <= max_rate dt``); while the scope is near straight (previous frame's
    ``|q1| < roll_hold_q1_fraction q1_max``) ``q2`` moves at most ``roll_rate_straight_deg_s`` (full rate
    above ``roll_free_q1_fraction``, linear between): the camera may roll slowly to line the bending
    plane up with the next turn, never at the actuator's full rate while straight (the simulated
    camera lags the command by the actuation delay, so a fast planned roll would be a roll error).  Camera roll is ``q2`` (the camera's x axis is the bending
    axis; ``q2 = 0`` is the route's rotation-minimising frame), so the roll-continuity term keeps the
    camera from rolling where the bend does not need it (near zero bending any ``q2`` fits).
    Each frame is solved by bounded least squares (``scipy.optimize.least_squares``, trust region
    reflective) from three starts, the previous joints advanced along the route, the controller's
    pose IK (:class:`~room_pipeline.robot.controller.IKController`) and that IK's bend in the previous
    bending plane, the lowest cost kept.  The solve is greedy (no look-ahead): where the path turns
    harder than the segment can follow from a base on the path, or the lumen narrows, the plan departs
    from the path (at the carina and the routes' ends of the default phantoms: up to 18-20 mm, README).

The planned camera poses are the forward kinematics of that joint plan, so the plan and the
controller agree exactly: the simulator commands ``q_k`` and simulated-vs-planned measures the
dynamics, contact and actuation only.  :func:`plan_joints` also reports how far the plan departs
from the path (camera position and view direction), its clearances and its roll.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from ..conventions import MM
from ..errors import ConfigError
from ..robot.controller import IKController
from ..robot.kinematics import ScopeGeometry, camera_roll, fk, straight_roll_change

SdfFn = Callable[[np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class JointPlanParams:
    """Weights and limits of :func:`plan_joints` (mm, deg, s; see the module docstring)."""

    direction_weight_mm: float = 10.0     # w_dir: 1 rad of view error costs as much as this position error
    roll_weight_mm: float = 10.0          # w_roll: 1 rad of roll change between frames costs this, mm
    bend_weight: float = 1.0              # w_bend: q1 change between frames (m per m)
    departure_rate_weight: float = 3.0    # w_dep: change of the departure from the path between frames (m per m)
    wall_weight: float = 10.0             # w_wall: clearance deficit of the scope body (m per m)
    body_clearance_mm: float = 0.0        # the scope surface keeps this from the wall (or the route's own clearance)
    body_points: int = 11                 # backbone samples checked, base to camera
    scope_diameter_mm: float = 5.0
    max_rate_q1_mm_s: float = 16.0
    max_rate_q2_deg_s: float = 90.0
    max_rate_q3_mm_s: float = 50.0
    roll_hold_q1_fraction: float = 0.05   # q2 moves at most roll_rate_straight_deg_s while the previous frame's
    roll_free_q1_fraction: float = 0.15   # |q1| < hold x q1_max, at max_rate_q2 above free (linear in between)
    roll_rate_straight_deg_s: float = 5.0


    @classmethod
    def from_dict(cls, d) -> "JointPlanParams":
        """From a config mapping (``trajectory.joint_plan``); unknown keys and bad values raise ConfigError."""
        d = dict(d or {})
        known = [f.name for f in dataclasses.fields(cls)]
        for key in d:
            if key not in known:
                raise ConfigError(f"trajectory.joint_plan: unknown key '{key}' (known: {', '.join(known)})")
        out = {}
        for key, v in d.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"trajectory.joint_plan.{key} must be a finite number >= 0, got {v!r}")
            out[key] = int(v) if key == "body_points" else float(v)
        p = cls(**out)
        for key in ("scope_diameter_mm", "max_rate_q1_mm_s", "max_rate_q2_deg_s", "max_rate_q3_mm_s"):
            if getattr(p, key) <= 0:
                raise ConfigError(f"trajectory.joint_plan.{key} must be > 0, got {getattr(p, key)}")
        if p.roll_rate_straight_deg_s <= 0:
            raise ConfigError("trajectory.joint_plan.roll_rate_straight_deg_s must be > 0")
        if p.body_points < 2 or float(d.get("body_points", 2)) != int(d.get("body_points", 2)):
            raise ConfigError(f"trajectory.joint_plan.body_points must be an integer >= 2, got {d.get('body_points')!r}")
        if p.roll_free_q1_fraction < p.roll_hold_q1_fraction:
            raise ConfigError("trajectory.joint_plan.roll_free_q1_fraction must be >= roll_hold_q1_fraction")
        return p


def _wrap(a):
    return (np.asarray(a, float) + math.pi) % (2.0 * math.pi) - math.pi


def camera_poses(route, q: np.ndarray, geometry: ScopeGeometry) -> np.ndarray:
    """World camera poses (n, 4, 4) of joints ``q`` (n, 3) with the base on ``route`` at ``q3``,
    rolled by ``q2`` (the simulator's kinematic insertion model)."""
    q = np.asarray(q, float).reshape(-1, 3)
    F = route.frames(q[:, 2])
    local = fk(np.column_stack([q[:, 0], q[:, 1], np.zeros(len(q))]), geometry=geometry)
    return F @ local


def plan_joints(route, targets: np.ndarray, arclength: np.ndarray, timestamps: np.ndarray, sdf_fn: SdfFn,
                geometry: ScopeGeometry, params: JointPlanParams) -> tuple[np.ndarray, np.ndarray, dict]:
    """Joint plan for camera targets ``targets`` (T, 4, 4: position and view, world m) along ``route``.

    ``arclength``: (T,) the targets' route arclength (m); ``timestamps``: (T,) s.
    Returns ``(q (T, 3), camera poses (T, 4, 4) = FK(q), report)``.
    """
    T = len(timestamps)
    rs = params.scope_diameter_mm * 0.5 * MM
    s_body = np.linspace(0.0, geometry.l, max(2, int(params.body_points)))
    w_dir = params.direction_weight_mm * MM
    w_roll = params.roll_weight_mm * MM
    w_bend, w_wall = params.bend_weight, params.wall_weight
    w_dep = params.departure_rate_weight
    rate = np.array([params.max_rate_q1_mm_s * MM, math.radians(params.max_rate_q2_deg_s),
                     params.max_rate_q3_mm_s * MM])
    q1m = geometry.q1_max
    rate_straight = math.radians(params.roll_rate_straight_deg_s)
    h = 0.0
    dep_prev = None
    # the route's own clearance, by arclength (from the scope's reach behind the start to the end)
    s_lo = float(arclength[0]) - geometry.l - 1e-3
    s_hi = float(arclength[-1]) + 1e-3
    s_grid = np.arange(s_lo, s_hi + 0.25 * MM, 0.25 * MM)
    route_clear = -np.asarray(sdf_fn(route.frames(s_grid)[:, :3, 3]), float)
    need_grid = np.where(route_clear > 0.0, np.minimum(rs + params.body_clearance_mm * MM, route_clear), -np.inf)
    ctrl = IKController(geometry, w_dir, iterations=3)

    def roll_gate(b):
        a, z = params.roll_hold_q1_fraction, params.roll_free_q1_fraction
        if z <= a:
            return 1.0 if b >= a else 0.0
        return min(1.0, max(0.0, (b - a) / (z - a)))

    def body(q):
        F = route.frame(float(q[2]))
        L = fk(np.array([q[0], q[1], 0.0]), s_body, geometry=geometry)
        P = L[:, :3, 3] @ F[:3, :3].T + F[:3, 3]
        d = F[:3, :3] @ L[-1, :3, 2]
        return P, d

    def residual(q, c, t, q_prev, first, h, dep_prev):
        P, d = body(q)
        clear = -np.asarray(sdf_fn(P), float)
        need = np.interp(q[2] + s_body, s_grid, need_grid)
        deficit = np.maximum(0.0, need - clear)
        r = [P[-1] - c, w_dir * (d - t), w_wall * deficit]
        if q_prev is not None:
            dq2 = float(_wrap(q[1] - q_prev[1]))
            r.append([w_roll * dq2, w_bend * (q[0] - q_prev[0])])
            r.append(w_dep * ((P[-1] - c) - dep_prev[0]))
            r.append(w_dep * w_dir * ((d - t) - dep_prev[1]))
        elif first:
            r.append([w_roll * float(_wrap(q[1]))])         # start at the route frame's roll
        return np.concatenate([np.ravel(x) for x in r])

    q_plan = np.zeros((T, 3))
    costs = np.zeros(T)
    nfev = 0
    q_prev = None
    for k in range(T):
        c, t = targets[k, :3, 3], targets[k, :3, 2]
        if q_prev is None:
            lo = np.array([-q1m, -np.inf, -np.inf])
            hi = np.array([q1m, np.inf, np.inf])
            starts = [np.array([0.0, 0.0, float(arclength[k]) - geometry.l])]
        else:
            h = float(timestamps[k] - timestamps[k - 1])
            r = rate * h
            g = roll_gate(abs(float(q_prev[0])) / q1m)
            r[1] = (1.0 - g) * min(rate_straight, rate[1]) * h + g * rate[1] * h
            lo = np.maximum(q_prev - r, [-q1m, -np.inf, -np.inf])
            hi = np.minimum(q_prev + r, [q1m, np.inf, np.inf])
            adv = q_prev + np.array([0.0, 0.0, float(arclength[k] - arclength[k - 1])])
            starts = [adv]
        q_ik = ctrl.command(targets[k], starts[0], route.frame)
        if q_prev is not None:
            q_ik[1] = q_prev[1] + float(_wrap(q_ik[1] - q_prev[1]))
            # the IK's bend in the nearer half of the held bending plane (bend first, then roll)
            held = q_ik.copy()
            held[1] = q_prev[1]
            held[0] = math.copysign(abs(q_ik[0]), q_ik[0] * math.cos(q_ik[1] - q_prev[1]) or 1.0)
            starts.append(held)
        starts.append(q_ik)
        best = None
        for x0 in starts:
            x0 = np.minimum(np.maximum(x0, lo), hi)
            # strictly inside the bounds (least_squares' requirement)
            span = np.where(np.isfinite(hi - lo), hi - lo, 0.0)
            x0 = np.clip(x0, lo + 1e-9 * span, hi - 1e-9 * span)
            sol = least_squares(residual, x0, bounds=(lo, hi), args=(c, t, q_prev, q_prev is None, h, dep_prev),
                                x_scale=np.array([1e-3, 0.1, 1e-3]), method="trf", xtol=1e-10, ftol=1e-10,
                                gtol=1e-10, max_nfev=200)
            nfev += int(sol.nfev)
            if best is None or sol.cost < best.cost:
                best = sol
        q_plan[k] = best.x
        costs[k] = best.cost
        q_prev = best.x.copy()
        P_, d_ = body(q_prev)
        dep_prev = (P_[-1] - c, d_ - t)
    poses = camera_poses(route, q_plan, geometry)
    # departure from the path, clearances, roll, rates: what the plan is, nothing hidden
    pos_err = np.linalg.norm(poses[:, :3, 3] - targets[:, :3, 3], axis=1)
    view_err = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", poses[:, :3, 2], targets[:, :3, 2]), -1, 1)))
    body_clear, deficit = [], []
    for q in q_plan:   # where the route itself is in the lumen (not the straight extension above a cut trachea)
        inside = np.interp(q[2] + s_body, s_grid, route_clear) > 0.0
        c = -np.asarray(sdf_fn(body(q)[0]), float)
        need = np.interp(q[2] + s_body, s_grid, need_grid)
        body_clear.append(float(c[inside].min()) if inside.any() else np.inf)
        deficit.append(float(np.max(need[inside] - c[inside], initial=0.0)))
    body_clear = np.array(body_clear) - rs
    cam_clear = -np.asarray(sdf_fn(poses[:, :3, 3]), float)
    roll = np.array([camera_roll(poses[i, :3, :3], targets[i, :3, :3]) for i in range(T)])
    dq = np.diff(q_plan, axis=0) / np.maximum(np.diff(timestamps), 1e-12)[:, None] if T > 1 else np.zeros((1, 3))
    dq[:, 1] = np.diff(np.unwrap(q_plan[:, 1])) / np.maximum(np.diff(timestamps), 1e-12) if T > 1 else 0.0

    def stats(a, scale=1.0):
        a = np.asarray(a, float) * scale
        return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}

    report = {
        "description": "joint-space plan: q(t) = [q1 tendon differential m, q2 axial rotation rad, q3 insertion m] "
                       "of the constant-curvature scope with its bending-segment base on the route at arclength q3 "
                       "(rolled by q2); frames[].pose = its forward kinematics (the camera the scope can reach); "
                       "frames[].path_pose = the smoothed centreline path pose it aims at "
                       "(planning/joint_plan.py)",
        "params": dataclasses.asdict(params),
        "departure_from_path_mm": stats(pos_err, 1e3),
        "view_departure_from_path_deg": stats(view_err),
        "roll_vs_path_deg": {"description": "planned camera roll about its view axis relative to the path's "
                                            "rotation-minimising frame",
                             "max_abs": float(np.degrees(np.abs(np.unwrap(roll)).max())),
                             "straight_stretch_change_max": math.degrees(straight_roll_change(roll, q_plan[:, 0], q1m)),
                             "straight_stretch": "consecutive frames with |q1| < 0.05 q1_max"},
        "camera_clearance_min_mm": float(cam_clear.min() * 1e3),
        "body_surface_clearance_min_mm": float(body_clear.min() * 1e3),
        "body_clearance_deficit_max_mm": float(max(deficit) * 1e3),
        "body_clearance_rule": "backbone -sdf >= min(scope radius + body_clearance_mm, the route's own -sdf at the "
                               "same arclength) (soft, weight wall_weight); deficit = how far a plan frame falls short",
        "q1_max_fraction": float(np.abs(q_plan[:, 0]).max() / q1m),
        "joint_rate_max": {"q1_mm_s": float(np.abs(dq[:, 0]).max() * 1e3),
                           "q2_deg_s": float(np.degrees(np.abs(dq[:, 1]).max())),
                           "q3_mm_s": float(np.abs(dq[:, 2]).max() * 1e3)},
        "cost_max_m2": float(costs.max() * 2.0),
        "function_evaluations": int(nfev),
    }
    return q_plan, poses, report
