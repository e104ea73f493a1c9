"""Closed-form kinematics of the ROOM continuum bronchoscope (3 DoF, constant curvature).

Model
    Kirchhoff reduction of a Cosserat rod along the distal bending segment,
    arc length ``s`` in [0, l] (m)::

        dr/ds = R e3,   dR/ds = R hat(u),   u = [kappa(q1), 0, 0] (constant strain, 1/m)
        r(0) = [0, 0, q3],   R(0) = Rot_z(q2),   kappa(q1) = -q1 / (2 gamma l)

    Joints: ``q1`` (m) the antagonistic tendon differential, limited to
    [-q1_max, q1_max] (bending); ``q2`` (rad) the axial rotation of the bending
    plane, any real; ``q3`` (m) the insertion, any real.  The solution is
    ``R(s) = Rot_z(q2) Rot_x(theta)`` with ``theta = kappa s`` and
    ``r(s) = [0, 0, q3] + Rot_z(q2) [0, -(1 - cos theta)/kappa, sin(theta)/kappa]``.

Base frame (robot base, SI metres/radians)
    +z is the insertion axis (the direction the scope advances); ``q3`` moves the
    base of the bending segment to ``[0, 0, q3]``.  At ``q2 = 0`` the segment bends
    in the base y-z plane: towards -y for ``q1 < 0`` (``kappa > 0``), towards +y
    for ``q1 > 0``; ``q2`` turns that plane right-handedly about +z.  Placing the
    base in the CT world (RAS+) is a later stage's job.

Tip frame (the columns of ``fk(q)[:3, :3]``)
    z = the backbone tangent at ``s`` = the viewing direction; x = the bending
    axis ``Rot_z(q2) e1`` (constant along the segment); y = z cross x.  With
    ``kappa > 0`` the tangent turns towards the tip's -y.

Tip camera
    The camera's OpenCV frame (x right, y down, z forward) *is* the tip frame
    for a camera on the tip axis with zero roll, so ``fk(q)`` is directly the
    camera-to-base pose (4x4, :data:`room_pipeline.conventions.POSE_CONVENTION`);
    ``kappa > 0`` (``q1 < 0``) then bends the view towards the image top (-y).

Joint limits
    :func:`fk` and :func:`jacobian` evaluate any finite ``q`` (beyond
    ``|q1| > q1_max`` the constant-curvature model is merely extrapolated);
    :func:`clamp_q` and :func:`ik` enforce ``|q1| <= q1_max``.  ``q2`` and ``q3``
    have no limits.

Numerics
    Every ``1/kappa`` is written through ``sinc(x) = sin(x)/x`` and
    ``cosc(x) = (1 - cos x)/x^2 = sinc(x/2)^2 / 2`` (no 0/0 at ``kappa = 0``);
    ``sinc`` switches to its Taylor series for ``|x| < 0.1`` and the Jacobian's
    ``(sin x - x cos x)/x^2`` for ``|x| < 2``, where both branches agree to about
    one ulp, so values and first derivatives are continuous across the switches.

The inverse kinematics (:func:`~room_pipeline.robot.inverse_kinematics.ik`: closed-form branches and a
Levenberg-Marquardt refinement on this model) is :mod:`~room_pipeline.robot.inverse_kinematics`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError


#: ``theta`` (rad) where the lateral tip offset ``(1 - cos theta)/kappa`` peaks for a given
#: arc length (``tan(theta/2) = theta``); position-only IK stays on ``|theta| <= THETA_TURN``.
THETA_TURN = 2.331122370414423

_SINC_SWITCH = 0.1
# sin(x)/x = sum_k (-1)^k x^(2k) / (2k+1)!, through x^8 (next term < 3e-18 at the switch)
_SINC_COEFFS = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(5))
_D_SWITCH = 2.0
# (sin x - x cos x)/x^2 = x * sum_{k>=1} (-1)^(k+1) 2k x^(2k-2) / (2k+1)!, 14 terms
# (next term < 3e-24 relative at the switch)
_D_COEFFS = tuple((-1) ** (k + 1) * 2 * k / math.factorial(2 * k + 1) for k in range(1, 15))


@dataclasses.dataclass(frozen=True)
class ScopeGeometry:
    """Geometry of the bending segment.

    Attributes:
        l: bending-segment length, m.
        gamma: tendon offset from the backbone (the ``gamma`` of ``kappa = -q1/(2 gamma l)``), m.
        q1_max: tendon-differential limit, m (``|q1| <= q1_max``).
    """

    l: float = 0.05
    gamma: float = 1.75e-3
    q1_max: float = 0.008

    def __post_init__(self) -> None:
        for name in ("l", "gamma", "q1_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"robot.{name} must be a number, got {value!r}")
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"robot.{name} must be finite and > 0, got {value!r}")
            object.__setattr__(self, name, float(value))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "ScopeGeometry":
        """Build from a mapping with keys ``l``, ``gamma``, ``q1_max`` (m; no conf/ section: the scope's
        geometry is the code default) through :func:`~room_pipeline.config.params.params_from_dict`, then
        :meth:`__post_init__`; an unknown key or a bad value raises :class:`ConfigError` naming it."""
        return params_from_dict(cls, d, "robot")

    @property
    def kappa_max(self) -> float:
        """Largest curvature magnitude, ``q1_max / (2 gamma l)``, 1/m."""
        return self.q1_max / (2.0 * self.gamma * self.l)

    @property
    def theta_max(self) -> float:
        """Largest bending angle of the whole segment, ``kappa_max * l``, rad."""
        return self.kappa_max * self.l


DEFAULT_GEOMETRY = ScopeGeometry()


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(x)/x, 1 at 0; Taylor series for |x| < 0.1."""
    if np.ndim(x) == 0:
        return _sinc_scalar(float(x))
    small = np.abs(x) < _SINC_SWITCH
    xs = np.where(small, x, 0.0)
    x2 = xs * xs
    series = np.zeros_like(x2)
    for c in reversed(_SINC_COEFFS):
        series = series * x2 + c
    xl = np.where(small, 1.0, x)
    return np.where(small, series, np.sin(xl) / xl)


def _sinc_scalar(x: float) -> float:
    """:func:`_sinc` for one Python float (the same series and switch; ~20x faster in scalar loops)."""
    if abs(x) < _SINC_SWITCH:
        x2 = x * x
        series = 0.0
        for c in reversed(_SINC_COEFFS):
            series = series * x2 + c
        return series
    return math.sin(x) / x


def _cosc(x: np.ndarray) -> np.ndarray:
    """(1 - cos x)/x^2, 1/2 at 0 (as sinc(x/2)^2/2: no cancellation)."""
    h = _sinc(0.5 * x)
    return 0.5 * h * h


def _dsinc(x: np.ndarray) -> np.ndarray:
    """(sin x - x cos x)/x^2 = -d sinc/dx, ~x/3 at 0; Taylor series for |x| < 2."""
    if np.ndim(x) == 0:
        x = float(x)
        if abs(x) < _D_SWITCH:
            x2, series = x * x, 0.0
            for c in reversed(_D_COEFFS):
                series = series * x2 + c
            return x * series
        return (math.sin(x) - x * math.cos(x)) / (x * x)
    small = np.abs(x) < _D_SWITCH
    xs = np.where(small, x, 0.0)
    x2 = xs * xs
    series = np.zeros_like(x2)
    for c in reversed(_D_COEFFS):
        series = series * x2 + c
    xl = np.where(small, 1.0, x)
    return np.where(small, xs * series, (np.sin(xl) - xl * np.cos(xl)) / (xl * xl))


def _joints_and_s(q, s, geometry: ScopeGeometry):
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ValueError(f"q must have shape (..., 3) [q1 m, q2 rad, q3 m], got {q.shape}")
    s = np.asarray(geometry.l if s is None else s, dtype=float)
    if not np.all((s >= 0.0) & (s <= geometry.l)):
        raise ValueError(f"arc length s must lie in [0, l = {geometry.l}] m, got {s}")
    q1, q2, q3, s = np.broadcast_arrays(q[..., 0], q[..., 1], q[..., 2], s)
    return q1, q2, q3, s


def kappa(q1, geometry: ScopeGeometry = DEFAULT_GEOMETRY):
    """Curvature (1/m) of the bending segment for tendon differential ``q1`` (m): ``-q1/(2 gamma l)``."""
    return -np.asarray(q1, dtype=float) / (2.0 * geometry.gamma * geometry.l)


def clamp_q(q, geometry: ScopeGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """``q`` (shape (..., 3)) with ``q1`` clipped to ``[-q1_max, q1_max]``; ``q2``, ``q3`` unchanged."""
    q = np.array(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ValueError(f"q must have shape (..., 3) [q1 m, q2 rad, q3 m], got {q.shape}")
    q[..., 0] = np.clip(q[..., 0], -geometry.q1_max, geometry.q1_max)
    return q


# --------------------------------------------------------------------------- forward kinematics


def fk(q, s=None, *, geometry: ScopeGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """Tip pose in the base frame at arc length ``s`` (m, default ``l``), closed form.

    Args:
        q: joints ``[q1 (m), q2 (rad), q3 (m)]``, shape (..., 3); any finite q1 is evaluated.
        s: arc length(s) in [0, l], m, broadcast against ``q[..., 0]``; ``None`` means the tip.
        geometry: the scope geometry.

    Returns:
        (..., 4, 4) homogeneous transforms tip-to-base: columns of the rotation are the tip
        x (bending axis), y and z (tangent = view direction) axes; the last column the position, m.
    """
    q1, q2, q3, s = _joints_and_s(q, s, geometry)
    theta = kappa(q1, geometry) * s
    lateral = s * theta * _cosc(theta)      # (1 - cos(kappa s)) / kappa
    axial = s * _sinc(theta)                # sin(kappa s) / kappa
    c2, s2 = np.cos(q2), np.sin(q2)
    ct, st = np.cos(theta), np.sin(theta)
    T = np.zeros(q1.shape + (4, 4))
    T[..., 0, 0] = c2
    T[..., 1, 0] = s2
    T[..., 0, 1] = -s2 * ct
    T[..., 1, 1] = c2 * ct
    T[..., 2, 1] = st
    T[..., 0, 2] = s2 * st
    T[..., 1, 2] = -c2 * st
    T[..., 2, 2] = ct
    T[..., 0, 3] = s2 * lateral
    T[..., 1, 3] = -c2 * lateral
    T[..., 2, 3] = q3 + axial
    T[..., 3, 3] = 1.0
    return T


def jacobian(q, s=None, *, geometry: ScopeGeometry = DEFAULT_GEOMETRY) -> np.ndarray:
    """Analytic Jacobian of (tip position (m), tip direction (unit)) with respect to q.

    Returns:
        (..., 6, 3): rows ``[px, py, pz, tx, ty, tz]`` of :func:`fk`'s position and z axis,
        columns ``[q1 (m), q2 (rad), q3 (m)]``.  Continuous through ``kappa = 0``.
    """
    q1, q2, q3, s = _joints_and_s(q, s, geometry)
    dk = -1.0 / (2.0 * geometry.gamma * geometry.l)          # d kappa / d q1
    theta = kappa(q1, geometry) * s
    sinc = _sinc(theta)
    lateral = s * theta * _cosc(theta)
    d_lateral = s * s * (sinc - _cosc(theta)) * dk          # d lateral / d q1
    d_axial = -s * s * _dsinc(theta) * dk                   # d axial / d q1
    c2, s2 = np.cos(q2), np.sin(q2)
    ct, st = np.cos(theta), np.sin(theta)
    J = np.zeros(q1.shape + (6, 3))
    J[..., 0, 0] = s2 * d_lateral
    J[..., 1, 0] = -c2 * d_lateral
    J[..., 2, 0] = d_axial
    J[..., 0, 1] = c2 * lateral
    J[..., 1, 1] = s2 * lateral
    J[..., 2, 2] = 1.0
    J[..., 3, 0] = s * dk * s2 * ct
    J[..., 4, 0] = -s * dk * c2 * ct
    J[..., 5, 0] = -s * dk * st
    J[..., 3, 1] = c2 * st
    J[..., 4, 1] = s2 * st
    return J


def camera_roll(R_act: np.ndarray, R_plan: np.ndarray) -> float:
    """Roll (rad) of an actual camera about its view axis relative to the planned camera.

    The planned frame is first turned by the least rotation taking its view axis (z) onto the
    actual one; the roll is the signed angle, about the actual z, from its x axis to the actual x.
    """
    za, zp = R_act[:, 2], R_plan[:, 2]
    v = np.cross(zp, za)
    s, c = float(np.linalg.norm(v)), float(zp @ za)
    xp = R_plan[:, 0]
    if s > 1e-12:
        k = v / s
        xp = xp * c + np.cross(k, xp) * s + k * float(k @ xp) * (1.0 - c)
    xa = R_act[:, 0]
    return float(math.atan2(float(np.cross(xp, xa) @ za), float(xp @ xa)))


def straight_roll_change(roll: np.ndarray, q1: np.ndarray, q1_max: float, fraction: float = 0.05) -> float:
    """Largest camera-roll change (rad, max - min of the unwrapped roll) over a straight stretch: a
    run of consecutive frames with ``|q1| < fraction q1_max``; 0 when there is none."""
    roll = np.unwrap(np.asarray(roll, float))
    straight = np.abs(np.asarray(q1, float)) < fraction * q1_max
    worst, i, n = 0.0, 0, len(roll)
    while i < n:
        if not straight[i]:
            i += 1
            continue
        j = i
        while j < n and straight[j]:
            j += 1
        worst = max(worst, float(roll[i:j].max() - roll[i:j].min()))
        i = j
    return worst
