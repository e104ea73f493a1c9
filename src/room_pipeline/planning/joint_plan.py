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
    :func:`plan_joints` finds the whole sequence of joints ``q_k = [q1 (m), q2 (rad), q3 (m)]``,
    k = 0..T-1, of the kinematic model the simulator's controller uses
    (:func:`room_pipeline.robot.kinematics.fk` with the base at ``Route.frame(q3)`` rolled by ``q2``;
    :class:`room_pipeline.robot.route.Route` is the same object the simulator builds from the
    plan) in one sparse nonlinear least-squares problem (every frame at once, so the scope starts to
    bend and roll before a branch, and the end of the route pulls the whole approach), in millimetres::

        sum_k |p(q_k) - c_k|^2 + w_dir^2 |d(q_k) - t_k|^2           (camera on the path point c_k,
                                                                     looking along its tangent t_k)
            + w_wall^2 sum_j max(0, need_kj - clear_kj)^2            (lumen: the scope body)
            + w_smooth^2 sum_i |a_ik / a_max_i|^2 + w_roll^2 |dq2_k / (v_max_2 h)|^2   (smooth joints, roll only
                                                                     where the bend needs it)
            + w_limit^2 (max(0, |v_ik| / v_max_i - 1)^2 + max(0, |a_ik| / a_max_i - 1)^2)   (rate and acceleration limits)
            + w_start^2 q2_0^2                                       (the route frame's roll at the start: image up)

    with ``clear_kj = -sdf`` at ``body_points`` points along the bending segment's backbone (base to
    camera) and ``need_kj = min(scope radius + body_clearance_mm, -sdf of the route at the same
    arclength)``: the scope's surface keeps ``body_clearance_mm`` from the wall, or at least the
    clearance the route itself has there.  ``v`` and ``a`` are the joints' finite-difference rate
    and acceleration.  ``|q1| <= q1_max`` is a bound.  The solver is
    :func:`scipy.optimize.least_squares` (trust region reflective, bounds) with the Jacobian's sparsity
    pattern (frame residuals depend on that frame's joints, rate and acceleration residuals on two or
    three neighbours), so each Jacobian costs a handful of grouped finite-difference evaluations.

Roll hold (hard)
    Near zero bending every ``q2`` fits the camera position, and the camera rolls with ``q2`` (its x
    axis is the bending axis; ``q2 = 0`` is the route's rotation-minimising frame).  ``q2`` may change
    between frames k-1 and k only where the scope is bent: ``|q1_j| >= (1 + roll_hold_margin)
    roll_hold_q1_fraction q1_max`` for every frame j from ``k - 1 - roll_hold_guard_frames`` to
    ``k + roll_hold_guard_frames`` (the guard covers the simulated actuation delay, up to one frame).
    It is exact, not a penalty: a first pass with ``q2`` free (and its roll-rate cost) says which
    frames bend and which way; the next passes make those frames' ``|q1|`` bounds one-sided
    (``q1 >= thr`` or ``<= -thr``) and give every run of frames where ``q2`` may not change one shared
    ``q2`` variable, and repeat while a held frame ends up bent.  A final forward pass clips the joint
    rates exactly and holds ``q2`` wherever the rule does not allow a change (the report records how far
    that moved the solution).  So on the plan the camera's roll relative to the path is constant over
    every straight stretch (``|q1| < roll_hold_q1_fraction q1_max``) up to the path frame's own twist.

The planned camera poses are the forward kinematics of that joint plan, so the plan and the
controller agree exactly: the simulator commands ``q_k`` and simulated-vs-planned measures the
dynamics, contact and actuation only.  :func:`plan_joints` also reports how far the plan departs
from the path (camera position and view direction, and at the route's end), its clearances, rates,
accelerations and roll.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
from scipy.sparse import coo_matrix

from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import ConfigError
from ..robot.controller import IKController
from ..robot.kinematics import ScopeGeometry, camera_roll, fk, straight_roll_change

SdfFn = Callable[[np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class JointPlanParams:
    """Weights and limits of :func:`plan_joints` (mm, deg, s; see the module docstring)."""

    direction_weight_mm: float = 10.0     # w_dir: 1 rad of view error costs as much as this position error
    wall_weight: float = 10.0             # w_wall: clearance deficit of the scope body (mm per mm)
    body_clearance_mm: float = 0.0        # the scope surface keeps this from the wall (or the route's own clearance)
    body_points: int = 11                 # backbone samples checked, base to camera
    scope_diameter_mm: float = 5.0
    smooth_weight_mm: float = 1.0         # w_smooth: a joint acceleration at its limit costs this position error, mm
    roll_weight_mm: float = 1.0           # w_roll: a q2 rate at its limit costs this, mm
    start_roll_weight_mm: float = 1.0     # w_start: 1 rad of q2 at the first frame costs this, mm
    limit_weight_mm: float = 1000.0       # w_limit: a rate or acceleration 100 % over its limit costs this, mm
    max_rate_q1_mm_s: float = 16.0
    max_rate_q2_deg_s: float = 90.0
    max_rate_q3_mm_s: float = 10.0
    max_acc_q1_mm_s2: float = 10.0
    max_acc_q2_deg_s2: float = 360.0
    max_acc_q3_mm_s2: float = 20.0
    roll_hold_q1_fraction: float = 0.05   # q2 held unless |q1| >= (1 + margin) x this x q1_max on the frames around
    roll_hold_margin: float = 0.2
    roll_hold_guard_frames: int = 1       # ... frames k-1-guard .. k+guard (the simulated actuation delay)
    max_passes: int = 4                   # solves: the first with q2 free, then with the hold, while it changes
    max_iterations: int = 400             # least-squares function evaluations per pass

    def __post_init__(self) -> None:
        """Every value a finite number >= 0 (rates, limits and the scope > 0); ConfigError names the key."""
        p = self
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"trajectory.joint_plan.{f.name} must be a finite number >= 0, got {v!r}")
        for key in ("scope_diameter_mm", "max_rate_q1_mm_s", "max_rate_q2_deg_s", "max_rate_q3_mm_s",
                    "max_acc_q1_mm_s2", "max_acc_q2_deg_s2", "max_acc_q3_mm_s2", "limit_weight_mm"):
            if getattr(p, key) <= 0:
                raise ConfigError(f"trajectory.joint_plan.{key} must be > 0, got {getattr(p, key)}")
        if p.body_points < 2:
            raise ConfigError(f"trajectory.joint_plan.body_points must be an integer >= 2, got {p.body_points!r}")
        if p.max_passes < 1 or p.max_iterations < 1:
            raise ConfigError("trajectory.joint_plan.max_passes and max_iterations must be >= 1")
        if p.roll_hold_q1_fraction * (1.0 + p.roll_hold_margin) >= 1.0:
            raise ConfigError("trajectory.joint_plan: (1 + roll_hold_margin) x roll_hold_q1_fraction must be < 1")

    @classmethod
    def from_dict(cls, d) -> "JointPlanParams":
        """From a config mapping (``trajectory.joint_plan`` less its ``enabled`` key); unknown keys and bad values
        raise ConfigError (:func:`~room_pipeline.config.params.params_from_dict`, then :meth:`__post_init__`)."""
        return params_from_dict(cls, d, "trajectory.joint_plan")


def _wrap(a):
    return (np.asarray(a, float) + math.pi) % (2.0 * math.pi) - math.pi


def camera_poses(route, q: np.ndarray, geometry: ScopeGeometry) -> np.ndarray:
    """World camera poses (n, 4, 4) of joints ``q`` (n, 3) with the base on ``route`` at ``q3``,
    rolled by ``q2`` (the simulator's kinematic insertion model)."""
    q = np.asarray(q, float).reshape(-1, 3)
    F = route.frames(q[:, 2])
    local = fk(np.column_stack([q[:, 0], q[:, 1], np.zeros(len(q))]), geometry=geometry)
    return F @ local


def roll_allowed(q1: np.ndarray, threshold: float, guard: int) -> np.ndarray:
    """(T,) bool: may q2 change from frame k-1 to k (index k; index 0 is False)?  Only where every frame
    from k-1-guard to k+guard has ``|q1| >= threshold``."""
    bent = np.abs(np.asarray(q1, float)) >= threshold
    T = len(bent)
    ok = np.zeros(T, bool)
    for k in range(1, T):
        ok[k] = bool(bent[max(0, k - 1 - guard):min(T, k + guard + 1)].all())
    return ok


def _first_guess(route, targets, arclength, geometry, w_dir) -> np.ndarray:
    """Per-frame pose IK (the controller's), q2 unwrapped and (q1, q2) ~ (-q1, q2 + pi) chosen for continuity."""
    T = len(targets)
    ctrl = IKController(geometry, w_dir, iterations=3)
    q = np.zeros((T, 3))
    prev = np.array([0.0, 0.0, float(arclength[0]) - geometry.l])
    for k in range(T):
        if k:
            prev = q[k - 1] + np.array([0.0, 0.0, float(arclength[k] - arclength[k - 1])])
        qk = ctrl.command(targets[k], prev, route.frame)
        a = float(_wrap(qk[1] - prev[1]))
        if abs(a) > 0.5 * math.pi:                    # the same arc bent the other way, rolled by pi
            qk[0], a = -qk[0], float(_wrap(a + math.pi))
        qk[1] = prev[1] + a
        qk[0] = min(max(qk[0], -geometry.q1_max), geometry.q1_max)
        q[k] = qk
    return q


def _least_roll(q: np.ndarray) -> np.ndarray:
    """The same poses with q2 shifted by the multiple of pi (q1 flipped for an odd one) that brings its median
    nearest 0: the actuator's gain error grows with |q2| (simulate.gain_q2), so the plan keeps |q2| small."""
    n = int(np.round(np.median(q[:, 1]) / math.pi))
    out = q.copy()
    out[:, 1] -= n * math.pi
    if n % 2:
        out[:, 0] = -out[:, 0]
    return out


class _Problem:
    """The whole-sequence least-squares problem for one assignment of q2 groups (see the module docstring).

    Variables z = [q1 (T, mm), q2 per group (G, rad), q3 (T, mm)]."""

    def __init__(self, route, targets, timestamps, sdf_fn, geometry, params, s_grid, need_grid, gid):
        self.route, self.sdf_fn, self.geometry, self.p = route, sdf_fn, geometry, params
        self.c = targets[:, :3, 3]
        self.t = targets[:, :3, 2]
        self.T = T = len(targets)
        self.gid = np.asarray(gid, int)
        self.G = int(self.gid.max()) + 1
        self.h = np.maximum(np.diff(np.asarray(timestamps, float)), 1e-9)
        self.s_body = np.linspace(0.0, geometry.l, max(2, int(params.body_points)))
        self.nb = len(self.s_body)
        self.s_grid, self.need_grid = s_grid, need_grid
        self.rs = params.scope_diameter_mm * 0.5 * MM
        # rate / acceleration limits in the variables' units (mm, rad)
        self.vmax = np.array([params.max_rate_q1_mm_s, math.radians(params.max_rate_q2_deg_s), params.max_rate_q3_mm_s])
        self.amax = np.array([params.max_acc_q1_mm_s2, math.radians(params.max_acc_q2_deg_s2), params.max_acc_q3_mm_s2])
        self.sparsity = self._sparsity()

    def joints(self, z):
        T, G = self.T, self.G
        return np.column_stack([z[:T] * MM, z[T:T + G][self.gid], z[T + G:] * MM])

    def pack(self, q):
        T = self.T
        q2g = np.zeros(self.G)
        best = np.full(self.G, -1.0)
        for k in range(T):                      # a group takes q2 of its most bent frame (its plane matters there)
            g = self.gid[k]
            if abs(q[k, 0]) > best[g]:
                best[g], q2g[g] = abs(q[k, 0]), q[k, 1]
        return np.concatenate([q[:, 0] / MM, q2g, q[:, 2] / MM])

    def body(self, q):
        """Backbone points (T, nb, 3) and camera view directions (T, 3), world."""
        F = self.route.frames(q[:, 2])
        qq = np.column_stack([q[:, 0], q[:, 1], np.zeros(self.T)])
        L = fk(qq[:, None, :], self.s_body[None, :], geometry=self.geometry)
        P = np.einsum("kij,kbj->kbi", F[:, :3, :3], L[:, :, :3, 3]) + F[:, None, :3, 3]
        d = np.einsum("kij,kj->ki", F[:, :3, :3], L[:, -1, :3, 2])
        return P, d

    def _diffs(self, q):
        """Rates (T-1, 3) and accelerations (T-2, 3) in mm/s, rad/s, mm/s^2, rad/s^2."""
        v = np.diff(q * np.array([1.0 / MM, 1.0, 1.0 / MM]), axis=0) / self.h[:, None]
        a = np.diff(v, axis=0) / (0.5 * (self.h[1:] + self.h[:-1]))[:, None] if self.T > 2 else np.zeros((0, 3))
        return v, a

    def residual(self, z):
        p = self.p
        q = self.joints(z)
        P, d = self.body(q)
        clear = -np.asarray(self.sdf_fn(P.reshape(-1, 3)), float).reshape(self.T, self.nb)
        need = np.interp(q[:, 2:3] + self.s_body[None, :], self.s_grid, self.need_grid)
        deficit = np.maximum(0.0, need - clear)
        frame = np.concatenate([(P[:, -1] - self.c) / MM, p.direction_weight_mm * (d - self.t),
                                p.wall_weight * deficit / MM], axis=1).ravel()
        v, a = self._diffs(q)
        rv, ra = v / self.vmax, a / self.amax
        W = p.limit_weight_mm
        out = [frame,
               (W * np.maximum(0.0, np.abs(rv) - 1.0)).T.ravel(),
               (W * np.maximum(0.0, np.abs(ra) - 1.0)).T.ravel(),
               (p.smooth_weight_mm * ra).T.ravel(),
               p.roll_weight_mm * rv[:, 1],
               [p.start_roll_weight_mm * q[0, 1]]]
        return np.concatenate([np.ravel(x) for x in out])

    def _sparsity(self):
        T, G, nb = self.T, self.G, self.nb
        col = [np.arange(T), T + self.gid, T + G + np.arange(T)]      # column of joint i at frame k
        rows, cols = [], []
        nf = 6 + nb
        r = np.arange(T * nf).reshape(T, nf)
        for i in range(3):
            rows.append(r.ravel())
            cols.append(np.repeat(col[i], nf))
        off = T * nf
        nv, na = max(T - 1, 0), max(T - 2, 0)
        for block, n, width in (("v", nv, 2), ("a", na, 3), ("a", na, 3)):
            for i in range(3):
                rr = off + np.arange(n)
                for j in range(width):
                    rows.append(rr)
                    cols.append(col[i][j:j + n])
                off += n
        rr = off + np.arange(nv)                                        # roll rate
        for j in range(2):
            rows.append(rr)
            cols.append(col[1][j:j + nv])
        off += nv
        rows.append(np.array([off]))
        cols.append(np.array([T]))                                      # the first frame's q2 group
        off += 1
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(off, 2 * T + G)).tocsr()


def plan_joints(route, targets: np.ndarray, arclength: np.ndarray, timestamps: np.ndarray, sdf_fn: SdfFn,
                geometry: ScopeGeometry, params: JointPlanParams) -> tuple[np.ndarray, np.ndarray, dict]:
    """Joint plan for camera targets ``targets`` (T, 4, 4: position and view, world m) along ``route``.

    ``arclength``: (T,) the targets' route arclength (m); ``timestamps``: (T,) s.
    Returns ``(q (T, 3), camera poses (T, 4, 4) = FK(q), report)``.
    """
    targets = np.asarray(targets, float)
    timestamps = np.asarray(timestamps, float)
    T = len(timestamps)
    if T == 0 or len(targets) != T or len(arclength) != T:
        raise ValueError("plan_joints needs one target and arclength per timestamp (and at least one)")
    rs = params.scope_diameter_mm * 0.5 * MM
    q1m = geometry.q1_max
    thr = params.roll_hold_q1_fraction * q1m
    thr_plan = thr * (1.0 + params.roll_hold_margin)
    guard = int(params.roll_hold_guard_frames)
    # the route's own clearance, by arclength (from the scope's reach behind the start to the end)
    s_lo = float(arclength[0]) - 2.0 * geometry.l - 1e-3
    s_hi = float(arclength[-1]) + geometry.l + 1e-3
    s_grid = np.arange(s_lo, s_hi + 0.25 * MM, 0.25 * MM)
    route_clear = -np.asarray(sdf_fn(route.frames(s_grid)[:, :3, 3]), float)
    need_grid = np.where(route_clear > 0.0, np.minimum(rs + params.body_clearance_mm * MM, route_clear), -np.inf)

    q = _least_roll(_first_guess(route, targets, arclength, geometry, params.direction_weight_mm * MM))
    allowed = np.ones(T, bool)
    allowed[0] = False
    sign = np.zeros(T)                 # +1 / -1: q1 bounded to that side of +-thr_plan; 0: free in [-q1_max, q1_max]
    from scipy.optimize import least_squares   # here, not at import: config validation loads this module

    nfev, passes, history = 0, 0, []
    for passes in range(1, int(params.max_passes) + 1):
        gid = np.cumsum(allowed)
        prob = _Problem(route, targets, timestamps, sdf_fn, geometry, params, s_grid, need_grid, gid)
        lo = np.full(prob.sparsity.shape[1], -np.inf)
        hi = np.full_like(lo, np.inf)
        lo[:T], hi[:T] = -q1m / MM, q1m / MM
        lo[:T][sign > 0] = thr_plan / MM
        hi[:T][sign < 0] = -thr_plan / MM
        z0 = np.clip(prob.pack(q), lo, hi)
        span = np.where(np.isfinite(hi - lo), hi - lo, 0.0)
        z0 = np.clip(z0, lo + 1e-9 * span, hi - 1e-9 * span)
        sol = least_squares(prob.residual, z0, jac_sparsity=prob.sparsity, bounds=(lo, hi), method="trf",
                            tr_solver="lsmr", x_scale=1.0, xtol=1e-8, ftol=1e-8, gtol=1e-8,
                            max_nfev=int(params.max_iterations))
        nfev += int(sol.nfev)
        q = prob.joints(sol.x)
        history.append({"pass": passes, "cost_mm2": float(2.0 * sol.cost), "nfev": int(sol.nfev),
                        "roll_steps_allowed": int(allowed.sum()) if passes > 1 else None})
        # which frames bend (pass 1: at the rule's own threshold; later: the held frames that came out bent)
        if passes == 1:
            q = _least_roll(q)
            new_allowed = roll_allowed(q[:, 0], thr, guard)
        else:
            new_allowed = allowed | roll_allowed(q[:, 0], thr_plan * (1.0 - 1e-9), guard)
        if passes > 1 and np.array_equal(new_allowed, allowed):
            break
        if passes == int(params.max_passes):
            break
        allowed = new_allowed
        window = np.zeros(T, bool)
        for k in np.flatnonzero(allowed):
            window[max(0, k - 1 - guard):min(T, k + guard + 1)] = True
        sign = np.where(window, np.where(q[:, 0] >= 0.0, 1.0, -1.0), 0.0)

    # exact limits: a forward pass clips the rates and holds q2 wherever the rule does not allow a change
    q_opt = q.copy()
    h = np.maximum(np.diff(timestamps), 0.0)
    vmax = np.array([params.max_rate_q1_mm_s * MM, math.radians(params.max_rate_q2_deg_s), params.max_rate_q3_mm_s * MM])
    q[:, 0] = np.clip(q[:, 0], -q1m, q1m)
    for k in range(1, T):
        r = vmax * h[k - 1]
        q[k] = np.clip(q[k], q[k - 1] - r, q[k - 1] + r)
        q[k, 0] = min(max(q[k, 0], -q1m), q1m)
    ok = roll_allowed(q[:, 0], thr_plan * (1.0 - 1e-6), guard) & allowed
    for k in range(1, T):
        if not ok[k]:
            q[k, 1] = q[k - 1, 1]
        else:
            q[k, 1] = min(max(q[k, 1], q[k - 1, 1] - vmax[1] * h[k - 1]), q[k - 1, 1] + vmax[1] * h[k - 1])
    projection = np.abs(q - q_opt)

    poses = camera_poses(route, q, geometry)
    report = _report(route, targets, arclength, timestamps, sdf_fn, geometry, params, q, poses, s_grid,
                     route_clear, need_grid, rs)
    report.update({
        "solver": "scipy.optimize.least_squares (trf, lsmr, sparse Jacobian pattern), whole sequence; "
                  "pass 1 with q2 free, then the hard roll hold",
        "passes": history,
        "roll_steps_allowed": int(ok.sum()),
        "final_projection_max": {"q1_mm": float(projection[:, 0].max() / MM),
                                 "q2_deg": float(np.degrees(projection[:, 1].max())),
                                 "q3_mm": float(projection[:, 2].max() / MM)},
        "function_evaluations": int(nfev),
    })
    return q, poses, report


def _report(route, targets, arclength, timestamps, sdf_fn, geometry, params, q, poses, s_grid, route_clear,
            need_grid, rs) -> dict:
    """What the plan is, nothing hidden: departure from the path, end, clearances, roll, rates."""
    T = len(q)
    q1m = geometry.q1_max
    pos_err = np.linalg.norm(poses[:, :3, 3] - targets[:, :3, 3], axis=1)
    view_err = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", poses[:, :3, 2], targets[:, :3, 2]), -1, 1)))
    s_body = np.linspace(0.0, geometry.l, max(2, int(params.body_points)))
    F = route.frames(q[:, 2])
    L = fk(np.column_stack([q[:, 0], q[:, 1], np.zeros(T)])[:, None, :], s_body[None, :], geometry=geometry)
    P = np.einsum("kij,kbj->kbi", F[:, :3, :3], L[:, :, :3, 3]) + F[:, None, :3, 3]
    c = -np.asarray(sdf_fn(P.reshape(-1, 3)), float).reshape(T, -1)
    sb = q[:, 2:3] + s_body[None, :]
    inside = np.interp(sb, s_grid, route_clear) > 0.0     # not the straight extension above a cut trachea
    need = np.interp(sb, s_grid, need_grid)
    body_clear = np.where(inside, c, np.inf).min(axis=1) - rs
    deficit = np.where(inside, need - c, 0.0).max(axis=1).clip(min=0.0)
    cam_clear = -np.asarray(sdf_fn(poses[:, :3, 3]), float)
    roll = np.array([camera_roll(poses[i, :3, :3], targets[i, :3, :3]) for i in range(T)])
    h = np.maximum(np.diff(timestamps), 1e-12)
    dq = np.diff(q, axis=0) / h[:, None] if T > 1 else np.zeros((1, 3))
    acc = np.diff(dq, axis=0) / (0.5 * (h[1:] + h[:-1]))[:, None] if T > 2 else np.zeros((1, 3))
    # the end: the last camera against the last path point, and its arclength short of the path's end
    seg = route.frames(np.linspace(float(arclength[-1]) - 2 * geometry.l, float(arclength[-1]), 801))[:, :3, 3]
    j = int(np.argmin(np.linalg.norm(seg - poses[-1, :3, 3], axis=1)))
    shortfall = 2 * geometry.l * (1.0 - j / 800.0)

    def stats(a, scale=1.0):
        a = np.asarray(a, float) * scale
        return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max())}

    return {
        "description": "joint-space plan: q(t) = [q1 tendon differential m, q2 axial rotation rad, q3 insertion m] "
                       "of the constant-curvature scope with its bending-segment base on the route at arclength q3 "
                       "(rolled by q2), optimised over the whole sequence; frames[].pose = its forward kinematics "
                       "(the camera the scope can reach); frames[].path_pose = the smoothed centreline path pose "
                       "it aims at (planning/joint_plan.py)",
        "params": dataclasses.asdict(params),
        "departure_from_path_mm": stats(pos_err, 1e3),
        "view_departure_from_path_deg": stats(view_err),
        "end": {"departure_mm": float(pos_err[-1] * 1e3), "view_departure_deg": float(view_err[-1]),
                "short_of_path_end_mm": float(shortfall * 1e3),
                "description": "last frame: camera to the path's last point; arclength from the path point nearest "
                               "the camera to the path's end"},
        "roll_vs_path_deg": {"description": "planned camera roll about its view axis relative to the path's "
                                            "rotation-minimising frame",
                             "max_abs": float(np.degrees(np.abs(np.unwrap(roll)).max())),
                             "straight_stretch_change_max": math.degrees(straight_roll_change(roll, q[:, 0], q1m)),
                             "straight_stretch": "consecutive frames with |q1| < 0.05 q1_max"},
        "camera_clearance_min_mm": float(cam_clear.min() * 1e3),
        "body_surface_clearance_min_mm": float(body_clear.min() * 1e3),
        "body_clearance_deficit_max_mm": float(deficit.max() * 1e3),
        "body_clearance_rule": "backbone -sdf >= min(scope radius + body_clearance_mm, the route's own -sdf at the "
                               "same arclength) (soft, weight wall_weight); deficit = how far a plan frame falls short",
        "q1_max_fraction": float(np.abs(q[:, 0]).max() / q1m),
        "joint_rate_max": {"q1_mm_s": float(np.abs(dq[:, 0]).max() * 1e3),
                           "q2_deg_s": float(np.degrees(np.abs(dq[:, 1]).max())),
                           "q3_mm_s": float(np.abs(dq[:, 2]).max() * 1e3)},
        "joint_acceleration_max": {"q1_mm_s2": float(np.abs(acc[:, 0]).max() * 1e3),
                                   "q2_deg_s2": float(np.degrees(np.abs(acc[:, 1]).max())),
                                   "q3_mm_s2": float(np.abs(acc[:, 2]).max() * 1e3)},
    }
