"""TUM RGB-D trajectory text: ``timestamp tx ty tz qx qy qz qw`` per line.

Camera-to-world poses: the camera centre (metres, world RAS+) and the unit
quaternion of the rotation (Hamilton, scalar **last**, written with ``qw >= 0``),
OpenCV camera frame; time in seconds; ``#`` lines are comments.  6 decimals for
time, 9 for positions and quaternion components.  The one writer and parser of
the format: the planned (``metadata/trajectory_tum.txt``) and simulated
(``metadata/simulated_tum.txt``) trajectories and the TUM export use it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError

__all__ = ["tum_text", "parse_tum"]


def tum_text(timestamps: np.ndarray, poses: np.ndarray,
             header: str = "camera-to-world, OpenCV camera, world RAS+, metres, seconds") -> str:
    """TUM trajectory text of (T,) timestamps and (T, 4, 4) poses; quaternions with w >= 0."""
    poses = np.asarray(poses, dtype=np.float64)
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)  # w >= 0 (same rotation)
    lines = [f"# timestamp tx ty tz qx qy qz qw ({header})"]
    for t, p, qq in zip(timestamps, poses[:, :3, 3], q):
        lines.append(f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}")
    return "\n".join(lines) + "\n"


def parse_tum(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse TUM trajectory text -> (timestamps (T,), poses (T, 4, 4)); ``#`` lines are comments."""
    rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    if any(len(r) != 8 for r in rows):
        raise InputError("TUM trajectory lines must hold 8 numbers: timestamp tx ty tz qx qy qz qw")
    a = np.array(rows, dtype=np.float64)
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()
    poses[:, :3, 3] = a[:, 1:4]
    return a[:, 0], poses
