"""The route the scope's shaft follows: a planned path's positions and tangent frames, by arclength.

Pure NumPy (the report and the planners use it without PyBullet).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import InputError


class Route:
    """The path the shaft follows: a trajectory's positions with tangent frames, by arclength.

    ``frame(s)``: 4x4 world pose at arclength ``s`` (m, 0 at the first pose): z = path tangent,
    x/y = the trajectory's rotation-minimising frame made orthogonal to it; extended straight
    (constant frame) before the start and after the end.
    """

    def __init__(self, positions: np.ndarray, arclength: np.ndarray, rotations: np.ndarray) -> None:
        s, idx = np.unique(np.asarray(arclength, float), return_index=True)
        P = np.asarray(positions, float)[idx]
        R = np.asarray(rotations, float)[idx]
        if len(s) < 2:
            raise InputError("the trajectory needs at least two distinct positions to simulate")
        t = np.gradient(P, s, axis=0) if len(s) > 2 else np.repeat((P[1:] - P[:1]) / (s[1] - s[0]), 2, axis=0)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        x = R[:, :, 0] - np.einsum("ij,ij->i", R[:, :, 0], t)[:, None] * t
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        self.s, self.P, self.t, self.x = s, P, t, x

    @classmethod
    def from_trajectory(cls, trajectory) -> "Route":
        """The shaft's path: the trajectory's ``path_poses`` (a joint-space plan's path) when it has them,
        else its camera poses."""
        P = getattr(trajectory, "path_poses", None)
        P = trajectory.poses if P is None else P
        return cls(P[:, :3, 3], trajectory.arclength, P[:, :3, :3])

    def polyline(self, s_end: float, step: float) -> np.ndarray:
        """(P, 3) positions (m) from the route's start up to (not including) arclength ``s_end``, every ``step`` m."""
        s = np.arange(float(self.s[0]), s_end, step)
        return np.array([self.frame(float(x))[:3, 3] for x in s]).reshape(-1, 3)

    def frame(self, s: float) -> np.ndarray:
        S = self.s
        if s <= S[0]:
            P, t, x = self.P[0] + (s - S[0]) * self.t[0], self.t[0], self.x[0]
        elif s >= S[-1]:
            P, t, x = self.P[-1] + (s - S[-1]) * self.t[-1], self.t[-1], self.x[-1]
        else:
            i = int(np.searchsorted(S, s, side="right")) - 1
            w = (s - S[i]) / (S[i + 1] - S[i])
            P = (1 - w) * self.P[i] + w * self.P[i + 1]
            t = (1 - w) * self.t[i] + w * self.t[i + 1]
            t = t / math.sqrt(t @ t)
            x = (1 - w) * self.x[i] + w * self.x[i + 1]
        x = x - (x @ t) * t
        x = x / math.sqrt(x @ x)
        T = np.eye(4)
        T[:3, 0] = x
        T[:3, 1] = (t[1] * x[2] - t[2] * x[1], t[2] * x[0] - t[0] * x[2], t[0] * x[1] - t[1] * x[0])
        T[:3, 2] = t
        T[:3, 3] = P
        return T

    def frames(self, s, roll=None) -> np.ndarray:
        """:meth:`frame` at every arclength of ``s`` (shape (n,)), each rolled about its z by ``roll``
        (rad, (n,), optional): (n, 4, 4).  One vectorised pass (the physics loop's per-step base poses)."""
        s = np.asarray(s, float).reshape(-1)
        S = self.s
        i = np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(S) - 2)
        w = ((s - S[i]) / (S[i + 1] - S[i]))[:, None]
        P = (1 - w) * self.P[i] + w * self.P[i + 1]
        t = (1 - w) * self.t[i] + w * self.t[i + 1]
        x = (1 - w) * self.x[i] + w * self.x[i + 1]
        for mask, k, s0 in ((s <= S[0], 0, S[0]), (s >= S[-1], -1, S[-1])):
            if mask.any():
                P[mask] = self.P[k] + (s[mask] - s0)[:, None] * self.t[k]
                t[mask] = self.t[k]
                x[mask] = self.x[k]
        t = t / np.sqrt(np.einsum("ij,ij->i", t, t))[:, None]
        x = x - np.einsum("ij,ij->i", x, t)[:, None] * t
        x = x / np.sqrt(np.einsum("ij,ij->i", x, x))[:, None]
        y = np.cross(t, x)
        if roll is not None:
            c, sn = np.cos(roll)[:, None], np.sin(roll)[:, None]
            x, y = c * x + sn * y, c * y - sn * x
        T = np.zeros((len(s), 4, 4))
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, t, P
        T[:, 3, 3] = 1.0
        return T
