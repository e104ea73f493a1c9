"""Camera orientation and speed along a path (steps 5-6 of :func:`~room_pipeline.planning.trajectory.plan_path`):
rotation-minimising frames, the initial image-up direction, the advance-speed profile."""
from __future__ import annotations

import numpy as np

from ..conventions import MM
from .trajectory_params import TrajectoryParams


_WORLD_UP = {"anterior": np.array([0.0, 1.0, 0.0]), "superior": np.array([0.0, 0.0, 1.0])}


def rotation_minimising_frames(points: np.ndarray, tangents: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """Rotation-minimising frames (double reflection, Wang et al. 2008) -> (T, 3, 3) rotations.

    Columns are the OpenCV camera axes: x right, y down, z = the unit tangent.
    ``y0`` (unit, perpendicular to ``tangents[0]``) is the first camera y axis.
    """
    t = np.asarray(tangents, dtype=np.float64)
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    x = np.asarray(points, dtype=np.float64)
    out = np.empty((len(t), 3, 3))
    y = np.asarray(y0, dtype=np.float64)
    for i in range(len(t)):
        if i:
            v1 = x[i] - x[i - 1]
            c1 = float(v1 @ v1)
            if c1 > 1e-24:
                yl = y - (2.0 / c1) * (v1 @ y) * v1
                tl = t[i - 1] - (2.0 / c1) * (v1 @ t[i - 1]) * v1
            else:
                yl, tl = y, t[i - 1]
            v2 = t[i] - tl
            c2 = float(v2 @ v2)
            y = yl - (2.0 / c2) * (v2 @ yl) * v2 if c2 > 1e-24 else yl
            y = y - (y @ t[i]) * t[i]  # keep orthonormal against rounding
            y /= np.linalg.norm(y)
        out[i, :, 2] = t[i]
        out[i, :, 1] = y
        out[i, :, 0] = np.cross(y, t[i])
    return out


def initial_down(tangent: np.ndarray, image_up: str = "anterior") -> np.ndarray:
    """Camera +y (image down) for a view along ``tangent`` with image up nearest ``image_up`` (see module doc)."""
    t = np.asarray(tangent, dtype=np.float64) / np.linalg.norm(tangent)
    for name in (image_up, "superior" if image_up == "anterior" else "anterior"):
        up = _WORLD_UP[name]
        perp = up - (up @ t) * t
        if np.linalg.norm(perp) > 0.2:  # view more than ~11.5 deg away from this up direction
            return -perp / np.linalg.norm(perp)
    e = np.eye(3)[int(np.argmin(np.abs(t)))]
    perp = e - (e @ t) * t
    return -perp / np.linalg.norm(perp)


def _speed_profile(s: np.ndarray, kappa: np.ndarray, junctions: np.ndarray, kappa_max: float,
                   params: TrajectoryParams) -> np.ndarray:
    """Advance speed (m/s) at path arclengths ``s`` (m)."""
    v = np.full(len(s), params.speed_mm_s * MM)
    D = params.bifurcation_distance_mm * MM
    if len(junctions) and D > 0:
        d = np.abs(s[:, None] - junctions[None]).min(axis=1)
        ramp = 0.5 * (1.0 + np.cos(np.pi * np.minimum(d / D, 1.0)))  # 1 at the bifurcation, 0 beyond D
        v *= 1.0 - (1.0 - params.bifurcation_slowdown) * ramp
    v *= 1.0 - (1.0 - params.curvature_slowdown) * np.minimum(np.abs(kappa) / kappa_max, 1.0)
    return v
