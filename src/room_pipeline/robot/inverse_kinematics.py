"""Inverse kinematics of the ROOM scope's constant-curvature model (:mod:`~room_pipeline.robot.kinematics`):
joints ``q`` that put the tip at a target position, optionally looking along a target direction.

Position only: closed form (the bend from a monotone scalar equation, safeguarded Newton).
Position and direction: closed form when the pair is reachable, else the nearest reachable pose
(the bend searched globally in 1-D, then Levenberg-Marquardt with the analytic Jacobian).
``|q1| <= q1_max`` always.  Details: :func:`ik`.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .kinematics import (DEFAULT_GEOMETRY, THETA_TURN, ScopeGeometry, _cosc, _dsinc, _sinc, _sinc_scalar, clamp_q,
                         fk)


@dataclasses.dataclass(frozen=True)
class IKResult:
    """Result of :func:`ik`.

    Attributes:
        q: joint vector ``[q1 (m), q2 (rad), q3 (m)]``, always within the joint limits.
        position_error_m: ``|p(q) - p_target|``, m.
        direction_error_rad: angle between the tip direction and the target direction, rad
            (0.0 when no direction was asked for).
        reachable: both errors within the requested tolerances.
        iterations: Newton (position-only) or Levenberg-Marquardt iterations spent (0: closed form).
    """

    q: np.ndarray
    position_error_m: float
    direction_error_rad: float
    reachable: bool
    iterations: int


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    ax, ay, az = (float(v) for v in a)
    bx, by, bz = (float(v) for v in b)
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


def _wrap_near(angle: float, ref: float) -> float:
    """``angle`` shifted by a multiple of 2 pi into (ref - pi, ref + pi]."""
    return ref - math.remainder(ref - angle, 2.0 * math.pi)


def _pick_branch(q: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """Of the two equivalent joint vectors ``(q1, q2)`` and ``(-q1, q2 + pi)`` (same tip position
    and direction, roll differing by pi) the one whose q2 is nearer q0's; q2 wrapped near q0's."""
    a = _wrap_near(q[1], q0[1])
    b = _wrap_near(q[1] + math.pi, q0[1])
    if q[0] != 0.0 and (abs(b - q0[1]), abs(-q[0] - q0[0])) < (abs(a - q0[1]), abs(q[0] - q0[0])):
        return np.array([-q[0], b, q[2]])
    return np.array([q[0], a, q[2]])


def _lateral_unit(theta: float) -> float:
    """(1 - cos theta)/theta: the lateral offset divided by s."""
    return float(theta * _cosc(np.float64(theta)))


def _solve_lateral(c: float, theta_hi: float, max_iter: int = 60) -> tuple[float, int]:
    """theta in [0, theta_hi] with (1 - cos theta)/theta = c (increasing there); safeguarded Newton.

    Stops when the residual stops shrinking (rounding level: the root is ill-conditioned near
    THETA_TURN, where the derivative vanishes) and returns the best iterate and the iterations.
    """
    lo, hi = 0.0, theta_hi
    theta = min(2.0 * c, theta_hi)               # (1 - cos t)/t ~ t/2
    best, best_abs = theta, math.inf
    for it in range(1, max_iter + 1):
        f = _lateral_unit(theta) - c
        if abs(f) >= best_abs and best_abs <= 1e-13 * c:
            return best, it
        if abs(f) < best_abs:
            best, best_abs = theta, abs(f)
        if f == 0.0:
            return theta, it
        if f > 0:
            hi = theta
        else:
            lo = theta
        df = float(_sinc(np.float64(theta)) - _cosc(np.float64(theta)))
        new = theta - f / df if df > 0 else 0.5 * (lo + hi)
        if not (lo <= new <= hi):
            new = 0.5 * (lo + hi)
        if new == theta:
            return theta, it
        theta = new
    return best, max_iter


def _position_ik(p: np.ndarray, q0: np.ndarray, s: float, geometry: ScopeGeometry):
    """Closed-form position-only IK (kappa >= 0 branch before :func:`_pick_branch`)."""
    rho = math.hypot(p[0], p[1])
    if rho == 0.0:
        return np.array([0.0, q0[1], p[2] - s]), 0
    theta_hi = min(geometry.kappa_max * s, THETA_TURN)
    if s == 0.0:
        theta, its = 0.0, 0
    elif rho >= s * _lateral_unit(theta_hi):
        theta, its = theta_hi, 0                 # unreachable (or on the boundary): radial projection
    else:
        theta, its = _solve_lateral(rho / s, theta_hi)
    k = theta / s if s > 0 else 0.0
    q1 = 0.0 - 2.0 * geometry.gamma * geometry.l * k
    q2 = math.atan2(p[0], -p[1])
    q3 = p[2] - s * float(_sinc(np.float64(theta)))
    return np.array([q1, q2, q3]), its


def _direction_ik(p: np.ndarray, t: np.ndarray, q0: np.ndarray, s: float,
                  geometry: ScopeGeometry) -> list[np.ndarray]:
    """Joint vectors pointing the tip along ``t``, with z matched exactly: one per bend
    ``theta = theta_t + 2 pi k`` within the limits (only k = 0 unless theta_max > pi), or the
    bend clamped to the limit when ``t`` is out of reach."""
    sigma = math.hypot(t[0], t[1])
    theta_t = math.atan2(sigma, t[2])            # [0, pi]
    q2 = math.atan2(t[0], -t[1]) if sigma > 0.0 else float(q0[1])
    theta_max = geometry.kappa_max * s
    k_lo = math.ceil((-theta_max - theta_t) / (2.0 * math.pi))
    k_hi = math.floor((theta_max - theta_t) / (2.0 * math.pi))
    thetas = [theta_t + 2.0 * math.pi * k for k in range(k_lo, k_hi + 1)] or [theta_max]
    out = []
    for theta in thetas:
        k = theta / s if s > 0 else 0.0
        q1 = 0.0 - 2.0 * geometry.gamma * geometry.l * k
        q3 = p[2] - s * float(_sinc(np.float64(theta)))
        out.append(np.array([q1, q2, q3]))
    return out


def _pose_start(p: np.ndarray, t: np.ndarray, w: float, q0: np.ndarray, s: float,
                geometry: ScopeGeometry, n: int = 129) -> np.ndarray:
    """Global minimiser (to ~1e-9 rad in theta) of ``|p - p*|^2 + w^2 |t - t*|^2`` over the joints.

    With ``q3`` matching z and ``u = (sin q2, -cos q2)`` the cost is
    ``A^2 + rho^2 + 2 w^2 - 2 u.m - 2 w^2 cos(theta) t*_z`` with ``m = A p*_xy + w^2 sin(theta) t*_xy``
    (``A`` the lateral offset), so the best ``q2`` points ``u`` along ``m`` and only a 1-D
    problem in ``theta`` in [0, theta_max] remains (``-theta`` is the ``q2 + pi`` branch):
    a grid, then golden-section search around the best grid point.
    """
    theta_max = geometry.kappa_max * s
    pxy, txy = p[:2], t[:2]

    def parts(theta):
        theta = np.asarray(theta, dtype=float)
        lateral = s * theta * _cosc(theta)
        m = lateral[..., None] * pxy + (w * w * np.sin(theta))[..., None] * txy
        cost = lateral**2 - 2.0 * np.hypot(m[..., 0], m[..., 1]) - 2.0 * w * w * np.cos(theta) * t[2]
        return cost, m

    px, py, tx, ty, tz, w2 = float(pxy[0]), float(pxy[1]), float(txy[0]), float(txy[1]), float(t[2]), w * w

    def cost1(theta: float) -> float:   # parts(theta)[0] for one float, in plain floats
        h = _sinc_scalar(0.5 * theta)
        lateral = s * theta * 0.5 * h * h
        sn = math.sin(theta)
        mx, my = lateral * px + w2 * sn * tx, lateral * py + w2 * sn * ty
        return lateral * lateral - 2.0 * math.hypot(mx, my) - 2.0 * w2 * math.cos(theta) * tz

    grid = np.linspace(0.0, theta_max, n)
    i = int(np.argmin(parts(grid)[0]))
    a, b = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, n - 1)])
    golden = 0.5 * (math.sqrt(5.0) - 1.0)
    c, d = b - golden * (b - a), a + golden * (b - a)
    fc, fd = cost1(c), cost1(d)
    while b - a > 1e-9:
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - golden * (b - a)
            fc = cost1(c)
        else:
            a, c, fc = c, d, fd
            d = a + golden * (b - a)
            fd = cost1(d)
    theta = 0.5 * (a + b)
    m = parts(theta)[1]
    q2 = math.atan2(m[0], -m[1]) if np.any(m != 0.0) else float(q0[1])
    k = theta / s if s > 0 else 0.0
    return np.array([0.0 - 2.0 * geometry.gamma * geometry.l * k, q2,
                     p[2] - s * float(_sinc(np.float64(theta)))])


def _lm(q: np.ndarray, p: np.ndarray, t: np.ndarray, w: float, s: float, geometry: ScopeGeometry,
        max_iter: int) -> tuple[np.ndarray, float, int]:
    """Levenberg-Marquardt on |p(q) - p*|^2 + w^2 |t(q) - t*|^2 with |q1| <= q1_max (active set)."""
    scale = np.array([1.0, 1.0, 1.0, w, w, w])
    q1_max = geometry.q1_max
    dk = -1.0 / (2.0 * geometry.gamma * geometry.l)
    px, py, pz, tx, ty, tz = (float(v) for v in (*p, *t))

    # fk and jacobian of one q in plain floats (the same closed forms; the LM's inner loop calls them
    # ~10 times per solve, and the numpy-array versions cost ~20x more per call)
    def residual(qq):
        theta = dk * float(qq[0]) * s
        h = _sinc_scalar(0.5 * theta)
        lateral = s * theta * 0.5 * h * h
        c2, s2 = math.cos(qq[1]), math.sin(qq[1])
        ct, st = math.cos(theta), math.sin(theta)
        return np.array([s2 * lateral - px, -c2 * lateral - py, float(qq[2]) + s * _sinc_scalar(theta) - pz,
                         w * (s2 * st - tx), w * (-c2 * st - ty), w * (ct - tz)])

    def jac(qq):
        theta = dk * float(qq[0]) * s
        sinc = _sinc_scalar(theta)
        h = _sinc_scalar(0.5 * theta)
        cosc = 0.5 * h * h
        lateral = s * theta * cosc
        d_lateral = s * s * (sinc - cosc) * dk
        d_axial = -s * s * float(_dsinc(theta)) * dk
        c2, s2 = math.cos(qq[1]), math.sin(qq[1])
        ct, st = math.cos(theta), math.sin(theta)
        return np.array([[s2 * d_lateral, c2 * lateral, 0.0], [-c2 * d_lateral, s2 * lateral, 0.0],
                         [d_axial, 0.0, 1.0], [s * dk * s2 * ct, c2 * st, 0.0], [-s * dk * c2 * ct, s2 * st, 0.0],
                         [-s * dk * st, 0.0, 0.0]])

    q = clamp_q(q, geometry)
    r = residual(q)
    cost = float(r @ r)
    lam = 1e-3
    it = 0
    while it < max_iter and cost >= 1e-32:
        J = jac(q) * scale[:, None]
        g = J.T @ r
        H = J.T @ J
        free = np.ones(3, dtype=bool)
        if (q[0] >= q1_max and g[0] < 0.0) or (q[0] <= -q1_max and g[0] > 0.0):
            free[0] = False                      # the bound is active: keep q1 on it
        Hf = H[np.ix_(free, free)]
        d = np.diag(Hf).copy()
        d = np.maximum(d, 1e-12 * max(float(d.max()), 1e-30))
        improved = False
        while lam < 1e16:
            step = np.zeros(3)
            try:
                step[free] = np.linalg.solve(Hf + lam * np.diag(d), -g[free])
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            q_new = q + step
            q_new[0] = min(max(q_new[0], -q1_max), q1_max)
            r_new = residual(q_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            break
        gain = cost - cost_new
        q, r, cost = q_new, r_new, cost_new
        it += 1
        lam = max(lam / 3.0, 1e-12)
        if gain <= 1e-15 * cost:
            break
    return q, cost, it


def ik(target_position, target_direction=None, *, q0=None, s=None,
       geometry: ScopeGeometry = DEFAULT_GEOMETRY, direction_weight_m: float | None = None,
       position_tol_m: float = 1e-9, direction_tol_rad: float = 1e-9, max_iter: int = 100) -> IKResult:
    """Joints putting the point at arc length ``s`` (default the tip) on a target, within the limits.

    Position only (``target_direction=None``): closed form.  The bending plane is
    ``q2 = atan2(x, -y)``; the bend solves the monotone scalar equation
    ``(1 - cos theta)/kappa = hypot(x, y)`` (safeguarded Newton to machine precision;
    ``theta`` restricted to ``[0, min(theta_max, THETA_TURN)]``, the least bend), and
    ``q3 = z - sin(theta)/kappa``.  The reachable set is the solid cylinder
    ``hypot(x, y) <= rho_max`` about the base z axis; outside it the result is the
    exact Euclidean nearest reachable tip position (radial projection, full bend).
    A target on the axis gives ``q1 = 0`` and keeps ``q0``'s ``q2``.

    Position and direction: the direction fixes ``theta`` and ``q2`` (closed form,
    ``q3`` then matches z exactly); when that also hits the position the target is
    reachable.  Otherwise the result is the nearest reachable pose in the metric
    ``|p - p*|^2 + direction_weight_m^2 |t - t*|^2`` (m^2, ``t`` the unit tip direction):
    ``q3`` and ``q2`` are eliminated in closed form, the remaining 1-D problem in the
    bend is searched globally (grid + golden section), and Levenberg-Marquardt with
    the analytic Jacobian and the q1 bound clamped (active set) polishes the result.

    Two joint vectors, ``(q1, q2)`` and ``(-q1, q2 + pi)``, give the same tip position
    and direction (roll differs by pi); the one whose ``q2`` is nearer ``q0[1]`` is
    returned, with ``q2`` wrapped into ``(q0[1] - pi, q0[1] + pi]``.

    Args:
        target_position: (3,) target in the base frame, m.
        target_direction: optional (3,) viewing direction (normalised here).
        q0: reference joints (default zeros): picks the branch and q2 where q2 is free (straight).
        s: arc length in [0, l] of the controlled point, m (default ``l``: the tip).
        geometry: the scope geometry.
        direction_weight_m: length weighting the direction residual, m (default ``l``).
        position_tol_m, direction_tol_rad: tolerances for ``reachable``.
        max_iter: iteration cap of the LM polish.

    Raises:
        ValueError: non-finite or misshaped targets, a zero direction, ``s`` outside [0, l],
            a negative or non-finite ``direction_weight_m``.
    """
    p = np.asarray(target_position, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"target_position must be 3 finite numbers (m), got {target_position!r}")
    q0 = np.zeros(3) if q0 is None else clamp_q(q0, geometry)
    if q0.shape != (3,) or not np.all(np.isfinite(q0)):
        raise ValueError(f"q0 must be 3 finite numbers, got {q0!r}")
    s = geometry.l if s is None else float(s)
    if not 0.0 <= s <= geometry.l:
        raise ValueError(f"arc length s must lie in [0, l = {geometry.l}] m, got {s}")

    def finish(q, its, t=None):
        q = clamp_q(_pick_branch(q, q0), geometry)
        T = fk(q, s, geometry=geometry)
        pos_err = float(np.linalg.norm(T[:3, 3] - p))
        dir_err = 0.0 if t is None else _angle_between(T[:3, 2], t)
        ok = pos_err <= position_tol_m and dir_err <= direction_tol_rad
        return IKResult(q=q, position_error_m=pos_err, direction_error_rad=dir_err,
                        reachable=bool(ok), iterations=int(its))

    q_pos, its = _position_ik(p, q0, s, geometry)
    if target_direction is None:
        return finish(q_pos, its)

    t = np.asarray(target_direction, dtype=float)
    norm = float(np.linalg.norm(t)) if t.shape == (3,) else 0.0
    if not (math.isfinite(norm) and norm > 0.0):
        raise ValueError(f"target_direction must be 3 finite numbers, not all zero, got {target_direction!r}")
    t = t / norm
    q_dirs = _direction_ik(p, t, q0, s, geometry)
    closed = [finish(q, 0, t) for q in q_dirs]
    first = min(closed, key=lambda res: res.position_error_m)
    if first.reachable:
        return first
    w = geometry.l if direction_weight_m is None else float(direction_weight_m)
    if not (math.isfinite(w) and w >= 0.0):
        raise ValueError(f"direction_weight_m must be finite and >= 0 (m), got {direction_weight_m!r}")
    start = _pose_start(p, t, w, q0, s, geometry)
    q, _, its = _lm(start, p, t, w, s, geometry, max_iter)
    return finish(q, its, t)
