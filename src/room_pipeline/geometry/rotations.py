"""Rotation helpers in plain NumPy: elementary rotations, the rotation vector (log map) of a rotation
matrix, and the matrix -> quaternion conversion PyBullet's poses take.

Radians; quaternions ``(x, y, z, w)`` (PyBullet's order).  Not ``scipy.spatial.transform``: on 1,000
random rotations ``Rotation.from_matrix(R).as_quat()`` differs from :func:`mat_to_quat` in the last bits
of 685 (at most 4.4e-16; tests/test_rotations.py), and the simulation's output bytes follow the base
pose's last bits, so the swap would change the dataset.
"""
from __future__ import annotations

import math

import numpy as np


def rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def log_so3(R: np.ndarray) -> np.ndarray:
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


def mat_to_quat(R: np.ndarray):
    """Unit quaternion ``(x, y, z, w)`` of the rotation matrix ``R``: Shepperd's method, deterministic."""
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


def log_so3_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of the rotation matrices ``R`` (n, 3, 3) (:func:`log_so3`, vectorised;
    the angle from atan2, accurate at small angles; a half turn falls back to the scalar form)."""
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sn = 0.5 * np.sqrt(np.einsum("ij,ij->i", v, v))
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)
    a = np.arctan2(sn, c)
    f = np.where(a < 1e-6, 0.5, a / (2.0 * np.where(a < 1e-6, 1.0, sn)))
    out = f[:, None] * v
    for k in np.flatnonzero(math.pi - a < 1e-6):
        out[k] = log_so3(R[k])
    return out
