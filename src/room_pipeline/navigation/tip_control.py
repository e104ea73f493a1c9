"""Tip control of the closed loop's scope (issue #19): joint commands from a target point or a path.

The bending segment is one constant-curvature arc of length ``l`` (:class:`~room_pipeline.robot.kinematics.
ScopeGeometry`) on a base that follows the shaft's path (``base_frame(q3)``: world pose of the segment's base
at insertion ``q3``, roll 0).  :func:`reach_command` bends toward one look-ahead point (position only);
:func:`path_command` puts the tip on a path where the path crosses the dome of reachable tips (follow the
leader); :func:`_model_error` is the simulated tip's deflection from the arc model.  Lengths m, angles rad.
"""
from __future__ import annotations

import math

import numpy as np

from ..robot.controller import _wrap, regularise_roll
from ..robot.kinematics import ScopeGeometry


def reach_command(target_world: np.ndarray, base_frame, q_prev: np.ndarray, geometry: ScopeGeometry,
                  advance_m: float, hold_fraction: float = 0.05, free_fraction: float = 0.15,
                  preview_m: float = 0.0, sideways_rad: float = 0.0) -> np.ndarray:
    """Joint command inserting ``advance_m`` more and bending the tip as near ``target_world`` as it can get
    once the insertion has gone ``preview_m`` further (the bend that will have brought the tip there).

    ``base_frame(q3)``: world pose of the bending-segment base at insertion ``q3`` (roll 0; z = insertion).
    At the new insertion the constant-curvature tip lies at ``Rot_z(q2) [0, -l (1 - cos t)/t, l sin t / t]``
    (``t = theta = -q1 / (2 gamma)``; :mod:`room_pipeline.robot.kinematics`) in that frame: ``q2`` puts the
    bending plane through the target (``atan2(x, -y)``), ``theta`` (grid over ``[0, theta_max]``, 0.5 mrad)
    minimises the distance to it.  Near zero bending the roll is held (:func:`~room_pipeline.robot.controller.
    regularise_roll`, the simulate config's fractions), except (``sideways_rad`` > 0) for a target more than
    ``sideways_rad`` off the held bending plane (either half): a held roll would bend the tip in the wrong plane.
    Insertion is commanded, the bend follows the target: the position-only tip control of a follow-the-leader
    scope.
    """
    q3 = float(q_prev[2]) + advance_m
    B = base_frame(float(q_prev[2]) + max(advance_m, preview_m))
    t = B[:3, :3].T @ (np.asarray(target_world, float) - B[:3, 3])
    r, z = math.hypot(t[0], t[1]), float(t[2])
    l = geometry.l
    th = _THETA_GRID * geometry.theta_max
    lat = l * np.where(th > 1e-9, (1 - np.cos(th)) / np.maximum(th, 1e-12), 0.0)
    ax = l * np.where(th > 1e-9, np.sin(th) / np.maximum(th, 1e-12), 1.0)
    theta = float(th[np.argmin((lat - r) ** 2 + (ax - z) ** 2)])
    return _bend_command(theta, float(t[0]), float(t[1]), q_prev, q3, geometry, hold_fraction, free_fraction,
                         sideways_rad)


def _bend_command(theta: float, x: float, y: float, q_prev: np.ndarray, q3: float, geometry: ScopeGeometry,
                  hold_fraction: float, free_fraction: float, sideways_rad: float = 0.0) -> np.ndarray:
    """Joints bending the segment by ``theta`` (rad) toward the base-frame direction (``x``, ``y``): q2 the
    roll nearest ``q_prev``'s that points the bend there (kept when the direction is the axis), q1 clipped to
    its limit, the roll held near zero bending (:func:`regularise_roll`) unless ``sideways_rad`` > 0 and the
    direction lies more than that off the held plane (its nearer half)."""
    r = math.hypot(x, y)
    q2 = float(q_prev[1]) + _wrap(math.atan2(x, -y) - float(q_prev[1])) if r > 1e-9 else float(q_prev[1])
    q = np.array([-2.0 * geometry.gamma * theta, q2, q3])
    q[0] = max(-geometry.q1_max, min(geometry.q1_max, q[0]))
    off = math.acos(min(1.0, abs(math.cos(q2 - float(q_prev[1])))))     # angle to the held plane, [0, pi/2]
    if (hold_fraction > 0 or free_fraction > 0) and not (sideways_rad > 0 and r > 1e-9 and off > sideways_rad):
        q = regularise_roll(q, float(q_prev[1]), geometry.q1_max, hold_fraction, free_fraction, project=False)
    return q


_THETA_GRID = np.linspace(0.0, 1.0, 2001)


def path_command(path_world: np.ndarray, base_frame, q_prev: np.ndarray, geometry: ScopeGeometry,
                 advance_m: float, hold_fraction: float = 0.05, free_fraction: float = 0.15,
                 preview_m: float = 0.0, tol_m: float = 2.5e-4) -> tuple[np.ndarray, float]:
    """Joint command putting the tip ON the path ``path_world`` ((M, 3) world points, m, ordered away from
    the tip) once the insertion has gone ``max(advance_m, preview_m)`` further; returns (q, residual m).

    Follow-the-leader tip control: at that insertion the constant-curvature tips of all (theta, q2) form a
    dome around the bending-segment base (``base_frame``, as :func:`reach_command`); the path crosses it
    where its distance from the base is about ``l``.  For every path point the bend in its own plane
    (``q2 = atan2(x, -y)``) that brings the tip nearest is found on a theta grid; the first point (walking
    from the tip) within ``tol_m`` of the dome is the target, else the nearest one.  The look-ahead is so
    tied to the bending segment's length instead of a fixed distance, and the tip stays on the path
    instead of cutting it by the constant-curvature arc's sag.  ``residual``: how far the tip stays off the
    path (m); roll held near zero bending as in :func:`reach_command`.
    """
    B = base_frame(float(q_prev[2]) + max(advance_m, preview_m))
    P = (np.asarray(path_world, float) - B[:3, 3]) @ B[:3, :3]
    r, z = np.hypot(P[:, 0], P[:, 1]), P[:, 2]
    l = geometry.l
    th = _THETA_GRID[::2] * geometry.theta_max
    lat = l * np.where(th > 1e-9, (1 - np.cos(th)) / np.maximum(th, 1e-12), 0.0)
    ax = l * np.where(th > 1e-9, np.sin(th) / np.maximum(th, 1e-12), 1.0)
    D = (lat[None, :] - r[:, None]) ** 2 + (ax[None, :] - z[:, None]) ** 2
    j = np.argmin(D, axis=1)
    res = D[np.arange(len(P)), j]
    ok = np.flatnonzero(res <= tol_m ** 2)
    i = int(ok[0]) if len(ok) else int(np.argmin(res))
    theta = float(th[j[i]])
    q2 = (float(q_prev[1]) + _wrap(math.atan2(P[i, 0], -P[i, 1]) - float(q_prev[1])) if r[i] > 1e-9
          else float(q_prev[1]))
    q = np.array([-2.0 * geometry.gamma * theta, q2, float(q_prev[2]) + advance_m])
    q[0] = max(-geometry.q1_max, min(geometry.q1_max, q[0]))
    if hold_fraction > 0 or free_fraction > 0:
        q = regularise_roll(q, float(q_prev[1]), geometry.q1_max, hold_fraction, free_fraction, project=False)
    return q, float(math.sqrt(res[i]))


def aim_command(target_world: np.ndarray, tip_world: np.ndarray, base_frame, q_prev: np.ndarray,
                geometry: ScopeGeometry, advance_m: float, hold_fraction: float = 0.05, free_fraction: float = 0.15,
                preview_m: float = 0.0) -> np.ndarray:
    """Joint command inserting ``advance_m`` more and turning the tip's VIEW toward ``target_world`` (m).

    The direction ``d`` from the tip ``tip_world`` to the target, in the bending-segment base frame at the
    insertion ``max(advance_m, preview_m)`` further (``base_frame``, as :func:`reach_command`), is the end
    tangent the constant-curvature arc must have: ``theta = acos(d_z)`` (clipped to ``theta_max``),
    ``q2 = atan2(d_x, -d_y)``.  The bend is set relative to the shaft, not to the current view, so a target
    fixed in the world is a fixed bend (no pursuit of a point that moves with the view: a look-ahead point
    taken along the current view grows the bend every step); as the tip moves toward the target's side, the
    bend needed shrinks.  Roll held near zero bending as in :func:`reach_command`.
    """
    B = base_frame(float(q_prev[2]) + max(advance_m, preview_m))
    d = B[:3, :3].T @ (np.asarray(target_world, float) - np.asarray(tip_world, float))
    n = float(np.linalg.norm(d))
    q3 = float(q_prev[2]) + advance_m
    if n < 1e-9:
        return np.array([float(q_prev[0]), float(q_prev[1]), q3])
    d = d / n
    theta = min(math.acos(max(-1.0, min(1.0, float(d[2])))), geometry.theta_max)
    return _bend_command(theta, float(d[0]), float(d[1]), q_prev, q3, geometry, hold_fraction, free_fraction)


def _model_error(q: np.ndarray, base_frame, geometry: ScopeGeometry, p_tip: np.ndarray) -> np.ndarray:
    """Simulated tip ``p_tip`` minus the constant-curvature tip of the actuated ``q`` on the shaft's path
    (world, m: how far the walls have pushed the bending segment off its commanded shape)."""
    B = base_frame(float(q[2]))
    th = -float(q[0]) / (2.0 * geometry.gamma)
    l = geometry.l
    lat, ax = (l * (1 - math.cos(th)) / th, l * math.sin(th) / th) if abs(th) > 1e-9 else (0.0, l)
    c, s_ = math.cos(q[1]), math.sin(q[1])
    local = np.array([-s_ * -lat, c * -lat, ax])          # Rot_z(q2) [0, -lat, ax]
    return p_tip - (B[:3, :3] @ local + B[:3, 3])
