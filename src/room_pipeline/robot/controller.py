"""IK-based tracking controller for the simulated scope (pure numpy).

At every frame the controller gets the next waypoint (a camera-to-world pose of the
planned trajectory) and a function giving the world pose of the **bending-segment
base** as a function of the insertion ``q3`` (roll excluded: its z axis is the
insertion direction, q2 = 0).  The robot base frame of
:mod:`room_pipeline.robot.kinematics` is that pose shifted back by ``q3`` along its z,
so ``fk(q)`` is the tip relative to it.  :func:`room_pipeline.robot.inverse_kinematics.ik`
(tip position and view direction) is solved in that frame; because the shaft follows a
curved route, the base frame moves with ``q3``: the solve is repeated with the base
frame at the new ``q3`` until ``q3`` changes by less than ``q3_tol_m`` (a fixed point,
2-3 iterations).  The joint command is clamped to the joint limits by ``ik``, then
(:func:`rate_limit`) to the actuators' speed limits: near a straight scope the bending
plane ``q2`` is ill-conditioned (any ``q2`` fits a target on the axis), and an unlimited
IK answer can spin the scope by tens of degrees between two frames.

Roll regularisation (:func:`regularise_roll`): near zero bending any ``q2`` reaches the
target, so the IK's ``q2`` wanders (it swung between 16 and 80 deg over the straight phantom
trachea) and the camera, fixed to the tip, rolls with it.  The commanded ``q2`` therefore
only moves toward the IK's as far as the bending needs it: held while the IK's bend
``|q1|`` is below ``roll_hold_q1_fraction`` of ``q1_max``, followed fully above
``roll_free_q1_fraction`` (linear in between); the bend is then projected onto the held
bending plane (``q1 cos(q2_ik - q2)``: the first-order lateral offset along that plane).
The actuator rate limit still applies afterwards.
"""
from __future__ import annotations

from typing import Callable

import math

import numpy as np

from .inverse_kinematics import ik
from .kinematics import ScopeGeometry

BaseFrameFn = Callable[[float], np.ndarray]


def rate_limit(q_new: np.ndarray, q_prev: np.ndarray, dt_s: float, max_rate: np.ndarray) -> np.ndarray:
    """``q_new`` moved at most ``max_rate * dt_s`` (per joint; m/s, rad/s, m/s) away from ``q_prev``."""
    step = np.clip(np.asarray(q_new, float) - q_prev, -np.asarray(max_rate) * dt_s, np.asarray(max_rate) * dt_s)
    return np.asarray(q_prev, float) + step


def _wrap(a: float) -> float:
    """Angle wrapped into (-pi, pi]."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


def regularise_roll(q_ik: np.ndarray, q2_prev: float, q1_max: float, hold_fraction: float,
                    free_fraction: float, project: bool = True) -> np.ndarray:
    """The IK answer with ``q2`` held near zero bending (see the module docstring).

    ``q_ik``: the IK's ``[q1, q2, q3]``; ``q2_prev``: the current command's roll.  The weight of
    the IK's ``q2`` is 0 for ``|q1| <= hold_fraction q1_max``, 1 for ``|q1| >= free_fraction q1_max``,
    linear in between; ``q1`` is projected onto the resulting bending plane (``project``), or keeps
    its magnitude, bending in the nearer of the two held half-planes (``project=False``: the bend
    grows before the roll, so the scope is no longer straight when it turns).
    """
    q = np.asarray(q_ik, float).copy()
    b = abs(q[0]) / q1_max
    if free_fraction <= hold_fraction:
        w = 1.0 if b > hold_fraction else 0.0
    else:
        w = min(1.0, max(0.0, (b - hold_fraction) / (free_fraction - hold_fraction)))
    if w >= 1.0:
        return q
    dq2 = _wrap(q[1] - q2_prev)
    q2 = q2_prev + w * dq2
    c = math.cos(q[1] - q2)
    q[0] = q[0] * c if project else math.copysign(q[0], q[0] * c if c != 0.0 else q[0])
    q[1] = q2
    return q


def _shift(base_pose: np.ndarray, q3: float) -> np.ndarray:
    """Robot base frame: the bending-segment base pose moved back by q3 along its own z."""
    W = base_pose.copy()
    W[:3, 3] = base_pose[:3, 3] - q3 * base_pose[:3, 2]
    return W


class IKController:
    """Tracks camera-to-world waypoints with insertion, rotation and bending.

    Args:
        geometry: scope geometry (bending-segment length, limits).
        direction_weight_m: weight of the view-direction residual in ``ik`` (m; None: ``l``).
        iterations: fixed-point iterations on the base frame.
        q3_tol_m: stop when the insertion changes by less than this.
        roll_hold_q1_fraction, roll_free_q1_fraction: roll regularisation (:func:`regularise_roll`);
            both 0: the IK's q2 as it is.
    """

    def __init__(self, geometry: ScopeGeometry, direction_weight_m: float | None = None,
                 iterations: int = 4, q3_tol_m: float = 1e-7, roll_hold_q1_fraction: float = 0.0,
                 roll_free_q1_fraction: float = 0.0, roll_project: bool = True) -> None:
        self.geometry = geometry
        self.roll_hold = float(roll_hold_q1_fraction)
        self.roll_free = float(roll_free_q1_fraction)
        self.roll_project = bool(roll_project)
        self.direction_weight_m = direction_weight_m
        self.iterations = int(iterations)
        self.q3_tol_m = float(q3_tol_m)

    def command(self, target_pose: np.ndarray, q_ref: np.ndarray, base_frame: BaseFrameFn) -> np.ndarray:
        """Joint command ``[q1, q2, q3]`` putting the tip camera on ``target_pose`` (4x4, world).

        ``q_ref``: the current command (branch and q2 continuity); ``base_frame(q3)``: world pose
        (4x4) of the bending-segment base at insertion ``q3``, roll 0.
        """
        q = np.asarray(q_ref, dtype=float).copy()
        p_w = target_pose[:3, 3]
        d_w = target_pose[:3, 2]
        for _ in range(max(1, self.iterations)):
            W = _shift(base_frame(q[2]), q[2])
            R, t = W[:3, :3], W[:3, 3]
            p = R.T @ (p_w - t)
            d = R.T @ d_w
            res = ik(p, d, q0=q, geometry=self.geometry, direction_weight_m=self.direction_weight_m,
                     position_tol_m=1e-6, direction_tol_rad=1e-4, max_iter=50)
            dq3 = abs(res.q[2] - q[2])
            q = res.q.copy()
            if dq3 < self.q3_tol_m:
                break
        if self.roll_hold > 0.0 or self.roll_free > 0.0:
            q = regularise_roll(q, float(q_ref[1]), self.geometry.q1_max, self.roll_hold, self.roll_free,
                                self.roll_project)
        return q
